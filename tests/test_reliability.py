"""What the package promises on interrupts, crashes, damaged files and bad input.

`docs/reliability.md` lists each promise next to the test here that checks it.
"""

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
import mixnerf_eqx._runs.loop as train_module
from mixnerf_eqx import ConfigError
from mixnerf_eqx._util.progress import Progress


def _with(config, section, **changes):
    return dataclasses.replace(config, **{section: dataclasses.replace(getattr(config, section), **changes)})


def _leaves(state):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(state.model, eqx.is_array))]


def _assert_same_model(a, b):
    for x, y in zip(_leaves(a), _leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def _short(tiny_config, run_dir):
    config = _with(tiny_config, "train", max_steps=10, checkpoint_every=4, eval_every=5, run_dir=str(run_dir))
    # A small grid, updated every other step, so that interrupts can land in its update too.
    return _with(config, "occupancy", enabled=True, resolution=8, update_every=2, choose_threshold=False)


def fit_quietly(config, dataset, **kwargs):
    return mx.fit(config, dataset=dataset, progress=False, write_renders=False, log_every=2, **kwargs)


def _interrupting(function, calls: dict, at: int = 1):
    """`function`, raising a real Ctrl-C (SIGINT) in its `at`-th call, before it runs."""

    def interrupted(*args, **kwargs):
        calls["count"] += 1
        if calls["count"] == at:
            signal.raise_signal(signal.SIGINT)  # a real Ctrl-C, in the middle of this call
        return function(*args, **kwargs)

    return interrupted


# Where a Ctrl-C lands (a name in `mixnerf_eqx._runs.loop` called there) and the step whose
# checkpoint it leaves, one after the other in one run: while the host waits for a step, in a
# log entry, in the grid update, inside the periodic evaluation's render, and inside a
# checkpoint write.
INTERRUPTS = [
    ("make_train_step", 1),
    ("_scalars", 2),
    ("update_grid", 4),
    ("_periodic_evaluation", 5),
    ("save_checkpoint", 8),
]


def test_a_ctrl_c_anywhere_in_the_loop_resumes_to_the_uninterrupted_run(
    tiny_config, tiny_scene, monkeypatch, tmp_path
):
    straight = fit_quietly(_short(tiny_config, tmp_path / "straight"), tiny_scene)
    config = _short(tiny_config, tmp_path / "run")
    for point, expected in INTERRUPTS:
        original, calls = getattr(train_module, point), {"count": 0}
        if point == "make_train_step":
            # The step is compiled: interrupt the compiled step's call, not its tracing.
            def patched(*args, original=original, calls=calls, **kwargs):
                return _interrupting(original(*args, **kwargs), calls)
        else:
            patched = _interrupting(original, calls)
        monkeypatch.setattr(train_module, point, patched)
        with pytest.raises(KeyboardInterrupt):
            fit_quietly(config, tiny_scene)
        monkeypatch.setattr(train_module, point, original)
        saved = mx.runs.read_checkpoint_meta(mx.runs.latest_checkpoint(config.train.run_dir))["step"]
        assert saved == expected, point
    resumed = fit_quietly(config, tiny_scene)
    _assert_same_model(resumed.state, straight.state)
    assert resumed.metrics["test"] == straight.metrics["test"]
    log = [
        json.loads(line) for line in (Path(config.train.run_dir) / "train_log.jsonl").read_text().splitlines()
    ]
    assert [entry["step"] for entry in log if "loss" in entry] == [2, 4, 6, 8, 10]
    # The evaluation cut short at step 5 (its step checkpointed without it) is made on resuming.
    straight_log = (Path(straight.run_dir) / "train_log.jsonl").read_text().splitlines()
    evaluations = [entry for entry in log if "eval" in entry]
    assert evaluations == [entry for entry in map(json.loads, straight_log) if "eval" in entry]
    assert [entry["step"] for entry in evaluations] == [5]


def test_a_ctrl_c_in_the_set_up_before_the_loop_stops_the_run(tiny_scene, tmp_path, monkeypatch):
    """Soak finding: before the loop deferred interrupts, a Ctrl-C in the set-up could land in
    JAX's garbage-collection callback, where Python drops the KeyboardInterrupt, and the run
    trained to its end. Now `train` defers from its start: a Ctrl-C while the scene loads stops
    the run at the loop's first safe point."""
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx._runs import loop as _train
    from mixnerf_eqx.cli import train as train_cli

    loaded = []

    def load_interrupted(config):
        signal.raise_signal(signal.SIGINT)  # a real Ctrl-C, while the scene loads
        loaded.append(True)  # recorded, not raised here, in the middle of the set-up
        return tiny_scene

    monkeypatch.setattr(_train, "load_dataset", load_interrupted)
    run_dir = tmp_path / "run"
    code = train_cli.main(
        ["--config", "builtin", *TINY_OVERRIDES, "--run-dir", str(run_dir), "--no-progress"]
    )
    assert code == 130 and loaded == [True]
    steps = [json.loads(line)["step"] for line in (run_dir / "train_log.jsonl").read_text().splitlines()]
    assert max(steps, default=0) < 150  # stopped long before train.max_steps


DROPPED_INTERRUPT = """
import gc, signal, time
# Ctrl-C handled as in a terminal: a test runner started in the background (`cmd &` in a
# script) passes SIGINT on ignored, and then Python installs no handler of its own.
signal.signal(signal.SIGINT, signal.default_int_handler)
from mixnerf_eqx._util.interrupt import deferred_interrupts, raise_if_interrupted, redeliver_dropped_interrupts
redeliver_dropped_interrupts()  # as the commands and `fit` do when they start
import jax  # noqa: F401

def ctrl_c_here(phase, info):
    # A Ctrl-C that Python's handler raises inside a gc callback (as in JAX's): Python drops it.
    gc.callbacks.remove(ctrl_c_here)
    raise KeyboardInterrupt

def other_error(phase, info):
    gc.callbacks.remove(other_error)
    raise ValueError("an unrelated unraisable error")

gc.callbacks.append(other_error)
gc.collect()
with deferred_interrupts():
    # (Here a dropped interrupt is one raised by hand: inside the block only a second Ctrl-C
    # raises, and the hook must still compose with the deferral.)
    gc.callbacks.append(ctrl_c_here)
    gc.collect()
    # The interrupt is handed back from another thread: wait for it at safe points, up to a
    # limit generous enough for a machine loaded with other tests.
    try:
        for _ in range(200):
            time.sleep(0.05)
            raise_if_interrupted()
        print("deferred: lost")
    except KeyboardInterrupt:
        print("deferred: raised at the safe point")
gc.callbacks.append(ctrl_c_here)
gc.collect()
for _ in range(200):
    time.sleep(0.05)
print("outside: lost")
"""


def test_a_ctrl_c_that_python_drops_in_a_gc_callback_is_raised_again():
    """Soak finding: a Ctrl-C in the first seconds, during the imports, could land in JAX's
    garbage-collection callback; Python dropped it and the run trained to its end."""
    result = subprocess.run(
        [sys.executable, "-c", DROPPED_INTERRUPT], capture_output=True, text=True, timeout=120
    )
    assert "deferred: raised at the safe point" in result.stdout
    assert "lost" not in result.stdout
    assert result.returncode != 0 and result.stderr.rstrip().endswith("KeyboardInterrupt")
    # Other unraisable errors are still reported by Python's hook, once.
    assert result.stderr.count("an unrelated unraisable error") == 1
    assert "Exception ignored" in result.stderr and result.stderr.count("Exception ignored") == 1


def test_ctrl_c_while_rendering_ends_cleanly(tiny_config, tiny_scene, monkeypatch, capsys):
    config = _with(tiny_config, "train", max_steps=2)
    fit_quietly(config, tiny_scene)
    from mixnerf_eqx._inference import rendering

    original = rendering._render_dense
    calls = {"count": 0}

    def interrupted(*args):
        calls["count"] += 1
        if calls["count"] == 2:
            signal.raise_signal(signal.SIGINT)
        return original(*args)

    monkeypatch.setattr(rendering, "_render_dense", interrupted)
    from mixnerf_eqx.cli.eval import main as eval_main

    code = eval_main([config.train.run_dir, "--no-progress", "--chunk", "256"])
    assert code == 130
    assert "interrupted" in capsys.readouterr().err
    # Rendering stopped at the next chunk after the Ctrl-C.
    assert calls["count"] == 2


def test_an_eval_interrupted_while_it_rewrites_its_folder_changes_nothing(tiny_config, tiny_scene, monkeypatch, capsys):
    config = _with(tiny_config, "train", max_steps=2)
    fit_quietly(config, tiny_scene)
    from mixnerf_eqx.cli import eval as eval_command

    run = Path(config.train.run_dir)
    assert eval_command.main([str(run), "--no-progress", "--no-lpips"]) == 0
    before = {p.name: p.read_bytes() for p in (run / "eval").iterdir()}
    assert "metrics.json" in before and any(name.endswith(".png") for name in before)
    original, calls = eval_command.write_view_renders, {"count": 0}
    # A real Ctrl-C after the first view's PNGs.
    monkeypatch.setattr(eval_command, "write_view_renders", _interrupting(original, calls, at=2))
    capsys.readouterr()
    assert eval_command.main([str(run), "--no-progress", "--no-lpips", "--max-views", "2"]) == 130
    assert "nothing was changed in the run" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in (run / "eval").iterdir()} == before
    assert not (run / "eval.partial").exists() and not (run / "eval.old").exists()
    # A replacement cut short between its two renames gives the old results back.
    (run / "eval").rename(run / "eval.old")
    monkeypatch.setattr(eval_command, "write_view_renders", original)
    assert eval_command.main([str(run), "--no-progress", "--no-lpips", "--max-views", "1"]) == 0
    assert json.loads((run / "eval" / "metrics.json").read_text())["num_views"] == 1
    # A folder of the user's is never replaced.
    mine = run.parent / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    capsys.readouterr()
    assert eval_command.main([str(run), "--no-progress", "--no-lpips", "--out", str(mine)]) == 2
    assert "holds files eval did not write (notes.txt)" in capsys.readouterr().err
    assert (mine / "notes.txt").read_text() == "keep"


def test_a_run_records_its_scene_and_eval_refuses_other_data(tiny_config, tiny_scene, capsys):
    from mixnerf_eqx._runs.run_folder import dataset_fingerprint
    from mixnerf_eqx.cli import eval as eval_command
    from mixnerf_eqx.data.procedural import make_builtin_scene

    config = _with(tiny_config, "train", max_steps=2)
    fit_quietly(config, tiny_scene)
    run = Path(config.train.run_dir)
    record = json.loads((run / "dataset.json").read_text())
    assert record == {"root": None, "scene": "builtin", "fingerprint": dataset_fingerprint(tiny_scene)}
    # The same run against other data: refused, naming both fingerprints.
    other = make_builtin_scene(resolution=32, num_train_views=3, num_test_views=3)
    assert dataset_fingerprint(other) != record["fingerprint"]
    with pytest.raises(ConfigError, match="holds other data"):
        mx.runs.restore_run(run, dataset=other)
    # A changed file under the same name is other data too: the fingerprint sees the pixels.
    changed = dataclasses.replace(
        tiny_scene, test=dataclasses.replace(tiny_scene.test, images=tiny_scene.test.images * 0.5)
    )
    with pytest.raises(ConfigError, match="holds other data"):
        mx.runs.restore_run(run, dataset=changed)
    # eval loads the scene its config names: the same data, so it runs.
    assert eval_command.main([str(run), "--no-progress", "--no-lpips", "--no-renders"]) == 0
    assert json.loads((run / "eval" / "metrics.json").read_text())["dataset"] == record
    assert json.loads((run / "metrics.json").read_text())["dataset"] == record


def test_a_relative_data_dir_is_stored_absolute(tiny_config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    config = _with(tiny_config, "data", data_dir="data")
    config = _with(config, "train", max_steps=1, run_dir=str(tmp_path / "run"))
    mx.fit(config, progress=False, write_renders=False)
    stored = json.loads((tmp_path / "run" / "config.json").read_text())["data"]["data_dir"]
    assert stored == str((tmp_path / "data").resolve())


def test_ctrl_c_in_the_final_render_leaves_the_run_folder_as_it_was(tiny_config, tiny_scene, monkeypatch):
    config = _with(tiny_config, "train", max_steps=2)
    run_dir = Path(config.train.run_dir)
    original, calls = train_module.write_view_renders, {"count": 0}
    # A real Ctrl-C after the first view's PNGs.
    monkeypatch.setattr(train_module, "write_view_renders", _interrupting(original, calls, at=2))
    with pytest.raises(KeyboardInterrupt):
        mx.fit(config, dataset=tiny_scene, progress=False, log_every=2)
    assert calls["count"] == 2
    assert not (run_dir / "renders").exists() and not (run_dir / "renders.partial").exists()
    assert not (run_dir / "metrics.json").exists()
    monkeypatch.setattr(train_module, "write_view_renders", original)
    # Run again: the final evaluation is made in full, every test view's three PNGs at once.
    mx.fit(config, dataset=tiny_scene, progress=False, log_every=2)
    names = sorted(p.name for p in (run_dir / "renders").iterdir())
    assert len(names) == 3 * tiny_scene.test.num_views and (run_dir / "metrics.json").exists()
    assert not (run_dir / "renders.partial").exists()


def _corrupt(path: Path, how: str) -> None:
    if how == "empty":
        path.write_bytes(b"")
    else:
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _checkpoints(config, dataset, steps):
    """Checkpoints of the initial state labelled with `steps` (no training needed to read them)."""
    state = mx.training.init_train_state(config, dataset)
    for step in steps:
        labelled = eqx.tree_at(lambda s: s.step, state, jnp.asarray(step, jnp.int32))
        mx.runs.save_checkpoint(config.train.run_dir, labelled, config=mx.config.config_to_dict(config))
    (Path(config.train.run_dir) / "config.json").write_text(json.dumps(mx.config.config_to_dict(config)))
    return [mx.runs.latest_checkpoint(config.train.run_dir).parent / f"step_{step:08d}" for step in steps]


def test_a_damaged_latest_checkpoint_falls_back_to_the_previous_one(tiny_config, tiny_scene):
    config = _with(tiny_config, "train", max_steps=6)
    _, newest = _checkpoints(config, tiny_scene, [2, 4])
    intact = (newest / "state.eqx").read_bytes()
    for how in ("empty", "truncated"):
        _corrupt(newest / "state.eqx", how)
        with pytest.warns(RuntimeWarning, match=f"damaged checkpoint.*{newest.name}"):
            run = mx.runs.restore_run(config.train.run_dir, dataset=tiny_scene)
        assert run.step == 2, how
        (newest / "state.eqx").write_bytes(intact)
    _corrupt(newest / "state.eqx", "truncated")
    with pytest.warns(RuntimeWarning, match=newest.name):
        resumed = fit_quietly(config, tiny_scene)
    assert resumed.metrics["step"] == 6
    assert [entry["step"] for entry in resumed.history] == [4, 6]


def test_a_garbage_meta_file_is_named(tiny_config, tiny_scene):
    (checkpoint,) = _checkpoints(tiny_config, tiny_scene, [4])
    (checkpoint / "meta.json").write_text("{not json")
    with pytest.raises(mx.runs.CheckpointError, match="meta.json"):
        mx.runs.read_checkpoint_meta(checkpoint)
    with (
        pytest.warns(RuntimeWarning, match="meta.json"),
        pytest.raises(mx.runs.CheckpointError, match="can be read"),
    ):
        mx.runs.restore_run(tiny_config.train.run_dir, dataset=tiny_scene)


def test_a_checkpoint_of_another_model_is_one_clear_error(tiny_config, tiny_scene):
    (checkpoint,) = _checkpoints(tiny_config, tiny_scene, [2])
    like = mx.training.init_train_state(_with(tiny_config, "mlp", width=48), tiny_scene)
    with pytest.raises(mx.runs.CheckpointError, match="another model or config"):
        mx.runs.load_checkpoint(checkpoint, like)


def test_a_full_disk_leaves_no_staging_folder_and_a_clear_message(tiny_config, tiny_scene, monkeypatch):
    config = _with(tiny_config, "train", max_steps=2)
    state = mx.training.init_train_state(config, tiny_scene)

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(eqx, "tree_serialise_leaves", full)
    with pytest.raises(mx.runs.CheckpointError, match="No space left on device.*previous checkpoint is intact"):
        mx.runs.save_checkpoint(config.train.run_dir, state, config={})
    assert list((Path(config.train.run_dir) / "checkpoints").iterdir()) == []


def test_stale_staging_folders_are_removed_on_the_next_start(tiny_config, tiny_scene):
    config = _with(tiny_config, "train", max_steps=2)
    stale = Path(config.train.run_dir) / "checkpoints" / ".step_00000004.tmp-99999"
    stale.mkdir(parents=True)
    (stale / "state.eqx").write_bytes(b"partial")
    fit_quietly(config, tiny_scene)
    assert not stale.exists()


def test_a_run_dir_that_is_a_file_is_refused_before_loading(tiny_config, monkeypatch, tmp_path):
    target = tmp_path / "a_file"
    target.write_text("x")

    def no_loading(*args, **kwargs):
        raise AssertionError("the dataset was loaded before the run dir was checked")

    monkeypatch.setattr(train_module, "load_dataset", no_loading)
    with pytest.raises(ConfigError, match="is a file"):
        mx.fit(_with(tiny_config, "train", run_dir=str(target)), progress=False)


def test_a_run_dir_that_cannot_be_created_or_written_is_refused(tiny_config, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match="cannot create train.run_dir"):
        mx.fit(_with(tiny_config, "train", run_dir=str(blocker / "run")), progress=False)
    # Permissions as a user without write access sees them (root may write anywhere).
    monkeypatch.setattr(train_module.os, "access", lambda path, mode: False)
    with pytest.raises(ConfigError, match="is not writable"):
        mx.fit(_with(tiny_config, "train", run_dir=str(tmp_path / "run")), progress=False)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root may write anywhere")
def test_an_unwritable_run_dir_is_refused(tiny_config, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(ConfigError, match="not writable|cannot create"):
            mx.fit(_with(tiny_config, "train", run_dir=str(locked / "run")), progress=False)
    finally:
        locked.chmod(0o700)


def test_paths_with_quotes_and_spaces_are_kept_as_given(tiny_scene, tmp_path, monkeypatch):
    from mixnerf_eqx.cli import train as train_cli

    seen = {}

    def record(config, **kwargs):
        seen["run_dir"], seen["data_dir"] = config.train.run_dir, config.data.data_dir
        raise KeyboardInterrupt

    monkeypatch.setattr(train_cli, "fit", record)
    odd = str(tmp_path / 'o\'brien "run" dir')
    code = train_cli.main(["--run-dir", odd, "--data-dir", odd + "/data", "--no-progress"])
    assert code == 130
    assert seen == {"run_dir": odd, "data_dir": odd + "/data"}


def test_options_may_follow_overrides():
    from mixnerf_eqx.cli.eval import parse_args as eval_args
    from mixnerf_eqx.cli.train import parse_args

    args = parse_args(["train.max_steps=3", "--no-progress", "train.eval_every=0", "--run-dir", "x"])
    assert args.no_progress and args.run_dir == "x"
    assert args.overrides == ["train.max_steps=3", "train.eval_every=0"]
    assert eval_args(["somewhere", "--no-lpips"]).no_lpips


@pytest.mark.parametrize(
    "arguments, message",
    [(["--chunk", "0"], "--chunk"), (["--chunk", "-5"], "--chunk"), (["--max-views", "-1"], "--max-views")],
)
def test_eval_refuses_meaningless_numbers(arguments, message, tmp_path, capsys):
    from mixnerf_eqx.cli.eval import main as eval_main

    assert eval_main([str(tmp_path), "--no-progress", *arguments]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error:") and message in error and "Traceback" not in error


def test_a_huge_chunk_is_bounded_by_the_rays(tiny_config, tiny_scene):
    model = mx.build_model(tiny_config, key=jax.random.key(0))
    rays = mx.data.rays_for_views(tiny_scene.test.select([0]), tiny_scene.near, tiny_scene.far)
    rendered = mx.inference.render_rays(model, rays, chunk=10**9)
    count = tiny_scene.test.height * tiny_scene.test.width
    assert rendered.counts.padded_evaluations == count * model.samples_per_ray


@pytest.mark.parametrize(
    "override, key",
    [
        ("train.eval_every=-1", "train.eval_every"),
        ("mlp.skip_layer=99", "mlp.skip_layer"),
        ("optim.warmup_steps=-1", "optim.warmup_steps"),
        ("loss.lambda_depth=-0.5", "loss.lambda_depth"),
        ("train.num_eval_views=-1", "train.num_eval_views"),
        ("mlp.min_deg=20", "mlp.min_deg"),
        ('train.run_dir=""', "train.run_dir"),
        ("train.max_steps=4000000000", "train.max_steps"),
        ("data.near=6.0", "data.near"),
    ],
)
def test_meaningless_settings_are_refused_naming_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        mx.load_config("builtin", [override, "data.far=4.0"] if "near" in override else [override])


def test_the_log_is_on_disk_at_every_checkpoint(tiny_config, tiny_scene, monkeypatch):
    config = _with(tiny_config, "train", max_steps=8, checkpoint_every=4)
    log_path = Path(config.train.run_dir) / "train_log.jsonl"
    seen = []
    original = train_module.save_checkpoint

    def look(run_dir, state, **kwargs):
        path = original(run_dir, state, **kwargs)
        seen.append((int(state.step), [json.loads(x)["step"] for x in log_path.read_text().splitlines()]))
        return path

    monkeypatch.setattr(train_module, "save_checkpoint", look)
    fit_quietly(config, tiny_scene)
    assert seen[0] == (4, [2, 4]) and seen[1][0] == 8


def test_progress_off_a_terminal_is_plain_lines(capsys):
    progress = Progress(100, unit="step", interval=0.0)
    for done in (10, 20):
        progress.update(done, loss="0.1")
    progress.write("step 20: held-out psnr 20")
    progress.close()
    captured = capsys.readouterr()
    assert "\r" not in captured.err
    assert captured.err.splitlines() == ["step 10/100 loss 0.1", "step 20/100 loss 0.1"]
    assert captured.out == "step 20: held-out psnr 20\n"
    silent = Progress(100, unit="step", enabled=False)
    silent.update(50)
    silent.write("still shown")
    assert capsys.readouterr().out == "still shown\n"


def test_a_finished_run_continues_to_more_steps_at_its_final_learning_rate(tiny_config, tiny_scene):
    config = _with(_with(tiny_config, "optim", warmup_steps=2), "train", max_steps=6)
    first = fit_quietly(config, tiny_scene)
    longer = fit_quietly(_with(config, "train", max_steps=10), tiny_scene)
    assert first.metrics["step"] == 6 and longer.metrics["step"] == 10
    rates = [entry["lr"] for entry in longer.history]
    assert rates == pytest.approx([config.optim.lr_final] * len(rates), rel=1e-5)
    stored = json.loads((Path(config.train.run_dir) / "config.json").read_text())
    assert stored["optim"]["decay_steps"] == 6 and stored["train"]["max_steps"] == 10
    with pytest.raises(ConfigError, match="more than train.max_steps"):
        fit_quietly(_with(config, "train", max_steps=4), tiny_scene)


def test_notebook_cells_have_ids():
    for path in Path("notebooks").glob("*.ipynb"):
        cells = json.loads(path.read_text())["cells"]
        ids = [cell.get("id") for cell in cells]
        assert all(ids) and len(set(ids)) == len(ids), path


def test_the_readme_example_does_not_share_the_quick_start_run_dir():
    readme = Path("README.md").read_text()
    section = readme[readme.index("## Using it from Python or Jupyter") :]
    example = section[section.index("```python") :]
    example = example[: example.index("```", 3)]
    # "runs/builtin" also matches the quick start's runs/builtin_grid.
    assert "mx.fit(" in example and "runs/builtin" not in example and "train.run_dir=" in example


def test_interrupts_outside_the_main_thread_are_left_alone():
    import threading

    from mixnerf_eqx._util.interrupt import deferred_interrupts

    before = signal.getsignal(signal.SIGINT)
    result = {}

    def work():
        with deferred_interrupts():
            result["handler"] = signal.getsignal(signal.SIGINT)

    thread = threading.Thread(target=work)
    thread.start()
    thread.join()
    assert result["handler"] is before and signal.getsignal(signal.SIGINT) is before


def test_a_downscale_that_leaves_images_too_small_to_score_is_refused_before_training(tmp_path):
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    if not (shared / "nerf_llff_data" / "fern").is_dir():
        pytest.skip("the shared fern scene is not beside the repository")
    config = mx.load_config(
        "llff3_grid",
        [f'data.data_dir="{shared}"', "data.image_downscale=16", f'train.run_dir="{tmp_path / "run"}"'],
    )
    # fern's 504x378 images divided by 16: 31x23, below the 32 pixels LPIPS and SSIM need.
    with pytest.raises(ConfigError, match=r"data.image_downscale = 16 leaves 31x23 held-out images.*choose a smaller factor"):
        mx.fit(config, progress=False)
    assert not (tmp_path / "run").exists()  # refused before anything was written


@pytest.mark.parametrize("command", ["train", "eval", "render", "sweep", "view", "next_view"])
def test_a_ctrl_c_while_a_command_loads_its_modules_is_status_130_without_a_traceback(
    command, monkeypatch, capsys
):
    # The command's modules raise KeyboardInterrupt as they load (a Ctrl-C in the first
    # seconds, inside an import whose frames Python hides from the traceback).
    import runpy
    import types

    class Interrupted(types.ModuleType):
        def __getattr__(self, name):
            raise KeyboardInterrupt

    monkeypatch.setitem(sys.modules, f"mixnerf_eqx.cli.{command}", Interrupted(f"mixnerf_eqx.cli.{command}"))
    monkeypatch.delitem(sys.modules, f"mixnerf_eqx.{command}", raising=False)
    with pytest.raises(SystemExit) as stopped:
        runpy.run_module(f"mixnerf_eqx.{command}", run_name="__main__")
    assert stopped.value.code == 130
    assert "stopped while loading; nothing was done" in capsys.readouterr().err
    # Imported as a module (not run as the command), the interrupt is the caller's.
    monkeypatch.delitem(sys.modules, f"mixnerf_eqx.{command}", raising=False)
    with pytest.raises(KeyboardInterrupt):
        runpy.run_module(f"mixnerf_eqx.{command}", run_name="not_main")


@pytest.mark.parametrize("dependency", ["jax", "optax"])
def test_a_ctrl_c_while_a_command_is_still_importing_is_one_line(dependency, tmp_path):
    # The Ctrl-C lands while the command imports its dependencies (JAX first, then the rest):
    # a stand-in for one of them (first on the path) raises KeyboardInterrupt as it is
    # imported, as a SIGINT there does. (A real SIGINT timed from outside can also land while
    # JAX's compiled library initialises, where it may crash the interpreter before any Python
    # handler runs.)
    stand_in = tmp_path / "path"
    stand_in.mkdir()
    (stand_in / f"{dependency}.py").write_text("raise KeyboardInterrupt\n")
    run_dir = tmp_path / "run"
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(stand_in), os.environ.get("PYTHONPATH", "")])}
    finished = subprocess.run(
        [sys.executable, "-m", "mixnerf_eqx.train", "--no-progress", f'train.run_dir="{run_dir}"'],
        capture_output=True,
        text=True,
        env=environment,
        cwd=Path(__file__).resolve().parents[1],
        timeout=120,
    )
    assert finished.returncode == 130, finished.stderr
    assert finished.stderr.strip() == "stopped while loading; nothing was done"
    assert not run_dir.exists()
    # Loaded by other code (not started as a command), the interrupt is the caller's.
    finished = subprocess.run(
        [sys.executable, "-c", "import mixnerf_eqx as mx; mx.fit"],
        capture_output=True,
        text=True,
        env=environment,
        timeout=120,
    )
    assert finished.returncode != 0 and "KeyboardInterrupt" in finished.stderr
