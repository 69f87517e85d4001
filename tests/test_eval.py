import dataclasses
import json
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import mixnerf_eqx as mx
from mixnerf_eqx import evaluate, fit, render_views
from mixnerf_eqx.inference import render_rays
from mixnerf_eqx._nn.chunks import join_chunks, map_ray_chunks
from mixnerf_eqx.cli.eval import main as eval_main
from mixnerf_eqx.data import rays_for_views
from mixnerf_eqx.metrics import lpips_available


def _with_train(config, **changes):
    return dataclasses.replace(config, train=dataclasses.replace(config.train, **changes))


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_scene):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx import load_config

    config = load_config("builtin", TINY_OVERRIDES)
    run_dir = tmp_path_factory.mktemp("eval") / "run"
    config = _with_train(config, max_steps=30, run_dir=str(run_dir))
    return fit(config, dataset=tiny_scene, progress=False, write_renders=False)


def test_chunked_rendering_does_not_depend_on_the_chunk(trained, tiny_scene):
    views = tiny_scene.test.select([0])
    rays = rays_for_views(views, tiny_scene.near, tiny_scene.far)
    # 1024 rays: one whole chunk, or 7 chunks of 150 with the last one padded.
    whole = render_rays(trained.model, rays, chunk=1024)
    pieces = render_rays(trained.model, rays, chunk=150)
    for name in ("rgb", "depth", "acc"):
        a, b = getattr(whole, name), getattr(pieces, name)
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, atol=1e-5)
    # Counts: every real ray once; the padding of the last chunk is evaluated, not needed.
    per_ray = trained.model.samples_per_ray
    assert whole.counts.rays == pieces.counts.rays == 1024
    assert pieces.counts.field_evaluations == 1024 * per_ray
    assert pieces.counts.padded_evaluations == 7 * 150 * per_ray
    per_view = render_views(trained.model, views, tiny_scene.near, tiny_scene.far, chunk=150)
    np.testing.assert_allclose(per_view.rgb, whole.rgb, atol=1e-5)
    # More rays than one chunk holds, fewer than two, and none at all.
    few = rays.reshape(-1)[:7]
    np.testing.assert_allclose(
        render_rays(trained.model, few, chunk=5).rgb, whole.rgb.reshape(-1, 3)[:7], atol=1e-5
    )
    assert render_rays(trained.model, rays.reshape(-1)[:0], chunk=5).rgb.shape == (0, 3)
    with pytest.raises(ValueError, match="chunk"):
        render_rays(trained.model, rays, chunk=0)


def test_eval_command_reproduces_the_training_metrics(trained, tiny_scene, capsys):
    code = eval_main([str(trained.run_dir), "--no-progress", "--no-typecheck"])
    assert code == 0
    printed = capsys.readouterr().out
    written = json.loads((trained.run_dir / "eval" / "metrics.json").read_text())
    assert written["num_views"] == tiny_scene.test.num_views
    assert [v["view"] for v in written["per_view"]] == list(tiny_scene.test.ids)
    # The same checkpoint, rendered again, scores what training reported at its end.
    for name in ("psnr", "ssim", "depth_mae"):
        assert written["mean"][name] == pytest.approx(trained.metrics["test"][name], abs=1e-6)
    if lpips_available():
        assert 0 <= written["mean"]["lpips"] <= 1
        assert written["mean"]["average"] > 0
    else:
        assert written["mean"]["lpips"] is None and "unavailable" in written["lpips"]
    assert "mean" in printed and f"{written['mean']['psnr']:.4f}" in printed
    pngs = sorted(p.name for p in (trained.run_dir / "eval").glob("*.png"))
    assert len(pngs) == 3 * tiny_scene.test.num_views
    assert any(name.endswith("_depth.png") for name in pngs)
    # The run folder explains itself: its training curves, drawn from the log.
    assert written["curves"] == str(trained.run_dir / "curves.png")
    with Image.open(trained.run_dir / "curves.png") as curves:
        assert curves.size == (1500, 400)
        pixels = np.asarray(curves.convert("L"))
    assert pixels.min() < 100 < 200 < pixels.max()  # lines drawn on a light background


def test_eval_of_the_validation_views(trained, tiny_scene, capsys):
    code = eval_main(
        [str(trained.run_dir), "--split", "val", "--no-progress", "--no-typecheck", "--no-lpips"]
    )
    assert code == 0
    written = json.loads((trained.run_dir / "eval_val" / "metrics.json").read_text())
    assert written["split"] == "val" and written["num_views"] == tiny_scene.val.num_views
    assert [v["view"] for v in written["per_view"]] == list(tiny_scene.val.ids)
    # The scores that training wrote for its validation views at the end.
    assert written["mean"]["psnr"] == pytest.approx(trained.metrics["val"]["psnr"], abs=1e-6)
    assert not set(tiny_scene.val.ids) & set(tiny_scene.test.ids)


def test_eval_of_validation_views_a_scene_lacks_is_one_line_and_status_2(tmp_path, capsys):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx import load_config

    config = load_config("builtin", [*TINY_OVERRIDES, "data.num_val_views=0"])
    config = _with_train(config, max_steps=2, eval_every=0, run_dir=str(tmp_path / "run"))
    fit(config, progress=False, write_renders=False)
    capsys.readouterr()
    code = eval_main([str(tmp_path / "run"), "--split", "val", "--no-progress", "--no-lpips"])
    error = capsys.readouterr().err.strip()
    assert code == 2
    assert error.startswith("error: ") and "has no validation views" in error and "\n" not in error
    assert not (tmp_path / "run" / "eval_val").exists()


def test_eval_of_a_subset_and_without_lpips(trained, tiny_scene, tmp_path):
    out = tmp_path / "subset"
    code = eval_main(
        [str(trained.run_dir), "--max-views", "2", "--no-lpips", "--no-renders", "--out", str(out)]
    )
    assert code == 0
    written = json.loads((out / "metrics.json").read_text())
    assert written["num_views"] == 2
    assert written["mean"]["lpips"] is None and written["lpips"].startswith("skipped")
    assert not list(out.glob("*.png"))


def test_eval_with_skipping_reports_its_cost_and_stays_within_a_tenth_of_a_db(trained, tmp_path):
    out = tmp_path / "skipping"
    code = eval_main(
        [
            str(trained.run_dir),
            "--skipping",
            "on",
            "--no-lpips",
            "--no-renders",
            "--no-progress",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    written = json.loads((out / "metrics.json").read_text())
    render = written["render"]
    assert render["skipping"] and render["grid_seconds"] > 0
    assert render["needed_evaluations_per_frame"] <= render["field_evaluations_per_frame"]
    assert render["field_evaluations_per_frame"] <= render["dense_evaluations_per_frame"]
    assert written["mean"]["psnr"] == pytest.approx(trained.metrics["test"]["psnr"], abs=0.1)


def test_evaluate_means_are_means_of_the_views(trained, tiny_scene):
    result = evaluate(trained.model, tiny_scene, chunk=512, with_lpips=False)
    assert result.means["psnr"] == pytest.approx(np.mean([v["psnr"] for v in result.per_view]))
    assert result.means["lpips"] is None
    assert result.counts.rays == tiny_scene.test.num_views * tiny_scene.test.height * tiny_scene.test.width


@pytest.mark.parametrize("argument", ["does_not_exist", "."])
def test_eval_of_a_folder_that_is_no_run_is_one_clear_error(argument, tmp_path):
    target = tmp_path / argument
    process = subprocess.run(
        [sys.executable, "-m", "mixnerf_eqx.eval", str(target), "--no-progress"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert process.returncode == 2
    assert process.stderr.startswith("error:") and "config.json" in process.stderr
    assert "Traceback" not in process.stderr


def test_masked_scores_follow_the_dtu_protocol():
    from mixnerf_eqx.inference import image_metrics
    from mixnerf_eqx.metrics import ssim

    rng = np.random.default_rng(0)
    target = rng.uniform(size=(40, 36, 3)).astype(np.float32)
    prediction = np.clip(target + rng.normal(0, 0.1, target.shape), 0, 1).astype(np.float32)
    mask = np.zeros((40, 36), bool)
    mask[8:30, 5:25] = True
    # Outside the mask the prediction is wildly wrong: a masked score must not see it.
    prediction[~mask] = 1.0 - target[~mask]
    scores = image_metrics(prediction, target, mask=mask, with_lpips=False)
    inside = (prediction[mask].astype(np.float64) - target[mask]) ** 2
    assert scores["psnr"] == pytest.approx(-10 * np.log10(inside.mean()), rel=1e-9)
    white_pred, white_target = prediction.copy(), target.copy()
    white_pred[~mask] = 1.0
    white_target[~mask] = 1.0
    assert scores["ssim"] == pytest.approx(ssim(white_pred, white_target), rel=1e-12)
    unmasked = image_metrics(prediction, target, with_lpips=False)
    assert unmasked["psnr"] < scores["psnr"] - 3


@pytest.mark.parametrize("count, chunk", [(10, 4), (8, 4), (3, 8), (1, 1), (0, 4)])
def test_the_chunk_map_sees_whole_chunks_and_returns_every_ray_once(count, chunk):
    """`map_ray_chunks` (rendering and the predictive pass): every call gets the same number
    of rays (the last chunk padded with the last ray), `extra` rows stay with their rays, and
    `join_chunks` gives back each real ray once, in order."""
    index = np.arange(count, dtype=np.float32)
    rays = mx.nn.RayBundle(
        origins=jnp.stack([jnp.asarray(index)] * 3, axis=-1).reshape(count, 3),
        directions=jnp.tile(jnp.asarray([0.0, 0.0, -1.0]), (count, 1)),
        viewdirs=jnp.tile(jnp.asarray([0.0, 0.0, -1.0]), (count, 1)),
        radii=jnp.full((count, 1), 1e-3),
        near=jnp.full((count, 1), 2.0),
        far=jnp.full((count, 1), 6.0),
    )
    seen = []

    def fn(piece, real, extra):
        seen.append((piece.batch_shape, real))
        np.testing.assert_array_equal(np.asarray(piece.origins[:, 0]), np.asarray(extra[:, 0]))
        return {"origin": piece.origins[:, 0], "pair": jnp.stack([piece.origins[:, 0]] * 2)}

    parts, got_count = map_ray_chunks(fn, rays, chunk, extra=index if count else None)
    assert got_count == count
    size = max(1, min(chunk, count))
    assert [shape for shape, _ in seen] == [(size,)] * (-(-count // size))
    assert sum(real for _, real in seen) == count
    if count:
        np.testing.assert_array_equal(join_chunks([p["origin"] for p in parts], count), index)
        np.testing.assert_array_equal(join_chunks([p["pair"] for p in parts], count, axis=1), [index] * 2)
    with pytest.raises(ValueError, match="chunk must be at least 1"):
        map_ray_chunks(fn, rays, 0)


def test_curves_need_a_log_and_plot_every_non_zero_term(trained, tmp_path, capsys):
    from mixnerf_eqx._util.curves import plot_curves, read_log

    assert plot_curves(tmp_path) is None
    assert "does not exist" in capsys.readouterr().out
    steps, evaluations = read_log(trained.run_dir / "train_log.jsonl")
    assert steps and all("psnr" in entry for entry in steps)
    assert plot_curves(trained.run_dir, tmp_path / "c.png") == tmp_path / "c.png"


def test_curves_survive_a_skipped_step_and_a_line_cut_short(tmp_path):
    """A skipped step logs `null` for its loss terms and a kill can leave half a line: the
    figure is still drawn, with gaps."""
    from mixnerf_eqx._util.curves import plot_curves, read_log

    entries = [
        {
            "step": 10,
            "loss": 1.0,
            "mse_fine": 0.1,
            "nll_colour": -2.0,
            "psnr": 10.0,
            "lr": 1e-3,
            "lambda_colour": 1.0,
        },
        {
            "step": 20,
            "loss": None,
            "mse_fine": None,
            "nll_colour": None,
            "psnr": None,
            "lr": 1e-3,
            "lambda_colour": 1.0,
        },
        {"step": 20, "eval": {"psnr": 12.0, "ssim": None}, "split": "val"},
        {
            "step": 30,
            "loss": 0.5,
            "mse_fine": 0.05,
            "nll_colour": -3.0,
            "psnr": 13.0,
            "lr": 5e-4,
            "lambda_colour": 0.1,
        },
    ]
    text = "".join(json.dumps(entry) + "\n" for entry in entries) + '{"step": 40, "loss": 0.'
    (tmp_path / "train_log.jsonl").write_text(text)
    steps, evaluations = read_log(tmp_path / "train_log.jsonl")
    assert [entry["step"] for entry in steps] == [10, 20, 30] and len(evaluations) == 1
    assert plot_curves(tmp_path) == tmp_path / "curves.png"


def test_without_matplotlib_plots_are_skipped_with_a_word(tmp_path, capsys, monkeypatch):
    """Without matplotlib a run's curves and a benchmark's plots are skipped, saying what is
    missing and how to install it; nothing is written."""
    from mixnerf_eqx._util.curves import plot_curves, pyplot

    (tmp_path / "train_log.jsonl").write_text(json.dumps({"step": 10, "loss": 1.0, "psnr": 10.0}) + "\n")
    for name in ("matplotlib", "matplotlib.pyplot"):
        monkeypatch.setitem(sys.modules, name, None)  # `import` now raises ImportError
    assert pyplot("plots") is None
    assert (
        "no plots: matplotlib is not installed (pip install 'mixnerf_eqx[plots]')" in capsys.readouterr().out
    )
    assert plot_curves(tmp_path) is None
    assert "no curves: matplotlib is not installed" in capsys.readouterr().out
    assert not (tmp_path / "curves.png").exists()
    monkeypatch.undo()
    assert pyplot("plots").get_backend().lower() == "agg"  # files only, no window


def test_eval_of_a_run_folder_it_cannot_write_to_asks_for_out(trained, monkeypatch, capsys):
    # The suite runs as root, which file permissions do not stop: the refusal a read-only run
    # folder gives is simulated where eval creates its staging folder.
    from pathlib import Path

    real_mkdir = Path.mkdir

    def read_only(self, *args, **kwargs):
        if self.name.endswith(".partial") and self.parent == trained.run_dir:
            raise PermissionError(13, "Permission denied", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    before = sorted(p.name for p in trained.run_dir.iterdir())
    code = eval_main([str(trained.run_dir), "--no-progress", "--no-lpips", "--no-renders"])
    error = capsys.readouterr().err.strip()
    assert code == 2
    assert "is not writable: give --out a folder you can write to" in error and "\n" not in error
    assert sorted(p.name for p in trained.run_dir.iterdir()) == before


def test_a_second_evaluation_into_the_same_folder_is_refused_before_it_touches_it(trained, tmp_path, capsys):
    from mixnerf_eqx._util.lock import hold_folder

    out = tmp_path / "shared"
    arguments = [str(trained.run_dir), "--no-lpips", "--no-progress", "--out", str(out)]
    assert eval_main(arguments) == 0
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    capsys.readouterr()
    # Another evaluation into `shared` holds its lock (as a running `eval --out shared` does).
    with hold_folder(tmp_path, "evaluation", "--out", name=".shared.eval.lock", label=out):
        assert eval_main(arguments) == 2
    message = capsys.readouterr().err
    assert f"{out} is in use by another evaluation" in message and "--out" in message
    # Neither the results nor a staging folder were touched.
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before
    assert not (tmp_path / "shared.partial").exists()
    # Once the other evaluation has ended, the same command runs.
    assert eval_main(arguments) == 0
