"""Failed runs are told from slow ones during training: the rule against hand-worked figures,
the blank image against a float64 computation, and the warning, the log entry and the
`metrics.json` field of a run whose figures say it failed."""

import dataclasses
import json
import warnings

import numpy as np
import pytest

from mixnerf_eqx import fit
from mixnerf_eqx._runs import failure as failure_module
from mixnerf_eqx._runs import loop
from mixnerf_eqx._runs.failure import Blank, FailedRunWarning, blank_image, failure, recent_train_psnr
from mixnerf_eqx.data import Dataset, Views


def _views(images):
    images = np.asarray(images, np.float32)
    return Views(images=images, camtoworlds=np.tile(np.eye(4)[:3], (len(images), 1, 1)).astype(np.float32), focal=1.0)


def test_blank_image_is_the_best_constant_against_float64():
    rng = np.random.default_rng(0)
    train = rng.uniform(0.0, 1.0, (2, 4, 4, 3))
    val = np.ones((3, 4, 4, 3))
    val[:, :2] = rng.uniform(0.0, 1.0, (3, 2, 4, 3))  # half of each view is white background
    dataset = Dataset(
        name="toy", train=_views(train), test=_views(val), near=2.0, far=6.0, white_background=True, val=_views(val)
    )

    def mean_psnr(images, colour):
        return np.mean([-10 * np.log10(np.mean((image - colour) ** 2)) for image in images])

    white, mean = mean_psnr(val[[0, 2]], np.ones(3)), mean_psnr(val[[0, 2]], train.reshape(-1, 3).mean(0))
    found = blank_image(dataset, [0, 2])
    assert found.psnr == pytest.approx(max(white, mean), abs=1e-4)
    assert found.what == ("the white background" if white > mean else "the mean training colour")
    # Without a background colour only the mean colour is a candidate.
    dark = dataclasses.replace(dataset, white_background=False)
    assert blank_image(dark, [0, 2]).psnr == pytest.approx(mean, abs=1e-4)


def test_the_rule_on_hand_worked_figures():
    blank = Blank(psnr=12.0, what="the white background")
    # The lego failure: 10.7 dB on held-out views, training views at 34.3 dB.
    assert "step 500" in failure(500, 10.7, 34.3, blank)
    assert failure(500, 12.9, 34.3, blank) is not None  # within 1 dB of the blank image
    assert failure(500, 13.0, 34.3, blank) is None  # 1 dB above it: not failed
    # Early in training nothing is fitted yet: held-out and training PSNR are both near blank.
    assert failure(100, 11.0, 16.9, blank) is None
    assert failure(100, 11.0, 17.0, blank) is not None  # 6 dB of fit on the training views
    assert failure(100, None, 30.0, blank) is None and failure(100, float("nan"), 30.0, blank) is None
    assert failure(100, 11.0, None, blank) is None
    assert recent_train_psnr([]) is None
    assert recent_train_psnr([{"psnr": 10.0}, {"eval": {}}, {"psnr": 20.0}]) == pytest.approx(15.0)
    assert recent_train_psnr([{"psnr": float(v)} for v in range(10)], count=5) == pytest.approx(7.0)


def test_a_run_whose_figures_say_failed_warns_logs_and_records_it(tiny_config, tiny_scene, monkeypatch):
    # An untrained model's validation PSNR sits near the blank image's; a training PSNR of 40
    # dB (patched in: a real failure takes minutes to grow) makes it a failed run's figures.
    config = dataclasses.replace(
        tiny_config, train=dataclasses.replace(tiny_config.train, max_steps=4, eval_every=2)
    )
    blank = blank_image(tiny_scene, loop._evaluation_ids(config, tiny_scene))
    monkeypatch.setattr(loop, "blank_image", lambda *_: Blank(blank.psnr + 50.0, blank.what))
    monkeypatch.setattr(loop, "recent_train_psnr", lambda history: 99.0)
    with pytest.warns(FailedRunWarning, match="looks failed at step 2"):
        result = fit(config, dataset=tiny_scene, progress=False, write_renders=False, log_every=1)
    run = result.run_dir
    warned = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert [entry["step"] for entry in warned if "warning" in entry] == [2]
    recorded = json.loads((run / "metrics.json").read_text())
    assert recorded["failure"].startswith("the run looks failed at step")
    assert result.metrics["failure"] == recorded["failure"]


def test_a_healthy_run_records_no_failure(tiny_config, tiny_scene):
    config = dataclasses.replace(
        tiny_config, train=dataclasses.replace(tiny_config.train, max_steps=4, eval_every=2)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", FailedRunWarning)
        result = fit(config, dataset=tiny_scene, progress=False, write_renders=False, log_every=1)
    assert json.loads((result.run_dir / "metrics.json").read_text())["failure"] is None
    assert failure_module.MARGIN_DB == 1.0 and failure_module.FIT_GAP_DB == 6.0


def test_a_run_with_non_finite_metrics_or_many_skipped_steps_is_not_a_result():
    finite = {"psnr": 20.0, "ssim": 0.8, "lpips": None}
    assert loop._unusable({"test": finite, "skipped_steps": 5}, 100) is None  # 5% is allowed
    assert "6 of the 100 steps" in loop._unusable({"test": finite, "skipped_steps": 6}, 100)
    assert "psnr, ssim are not finite" in loop._unusable(
        {"test": {"psnr": float("nan"), "ssim": float("inf"), "lpips": None}, "skipped_steps": 0}, 100
    )


def test_the_train_command_exits_1_on_an_unusable_run(tmp_path, monkeypatch, capsys):
    from types import SimpleNamespace

    from mixnerf_eqx.cli import train as train_command

    metrics = {
        "step": 3,
        "scene": "builtin",
        "per_view": [],
        "test": {"psnr": float("nan")},
        "render": {},
        "unusable": "the test psnr is not finite: the model diverged",
    }
    monkeypatch.setattr(train_command, "fit", lambda *a, **k: SimpleNamespace(metrics=metrics, run_dir=tmp_path))
    monkeypatch.setattr(train_command, "_print_report", lambda *a: None)
    assert train_command.main(["--no-progress", f"train.run_dir={str(tmp_path)!r}"]) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert error == ["error: the run's results are not usable: the test psnr is not finite: the model diverged"]
