"""The fidelity benchmark's table: means and spreads over seeds, best points, overfitting and
the verdict, on synthetic run records whose answers are known."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import fidelity  # noqa: E402


def _run(scene, method, seed, test_curve, train_curve):
    curve = [
        {"step": 100 * (i + 1), "test": {"psnr": test, "ssim": 0.5, "lpips": None}, "train_psnr": train}
        for i, (test, train) in enumerate(zip(test_curve, train_curve, strict=True))
    ]
    return {
        "scene": scene,
        "method": method,
        "seed": seed,
        "steps": 100 * len(curve),
        "epochs": 100,
        "curve": curve,
        "final": curve[-1],
    }


def test_summary_reports_mean_spread_best_point_and_overfitting():
    runs = [
        # The baseline peaks at step 200 and falls while its training PSNR rises: overfitting.
        _run("fern", "mipnerf", 0, [18.0, 19.0, 18.5], [20.0, 22.0, 24.0]),
        _run("fern", "mipnerf", 1, [18.0, 19.0, 18.7], [20.0, 22.0, 24.0]),
        # MixNeRF keeps improving.
        _run("fern", "mixnerf", 0, [18.0, 19.0, 19.5], [20.0, 21.0, 21.5]),
        _run("fern", "mixnerf", 1, [18.0, 19.0, 19.7], [20.0, 21.0, 21.5]),
    ]
    table, summary = fidelity.summarise(runs)
    base, mix = summary["fern/mipnerf"], summary["fern/mixnerf"]
    assert base["end_psnr"] == pytest.approx((18.6, 0.1414213562), rel=1e-6)
    assert base["best_psnr"][0] == pytest.approx(19.0) and base["best_steps"] == [200, 200]
    assert base["overfits"] == [True, True] and mix["overfits"] == [False, False]
    gap = summary["fern/gap"]
    assert gap["end_psnr_gap"] == pytest.approx(1.0)
    assert gap["verdict"] == "MixNeRF ahead by more than the spread"
    assert "| fern | mipnerf | 2 | 300 (100) | 18.60 ± 0.14 |" in table


def test_a_gap_within_the_spread_or_from_one_seed_is_not_called_a_win():
    close = [
        _run("lego", "mipnerf", 0, [18.0], [20.0]),
        _run("lego", "mipnerf", 1, [19.0], [20.0]),
        _run("lego", "mixnerf", 0, [18.6], [20.0]),
        _run("lego", "mixnerf", 1, [18.8], [20.0]),
    ]
    assert fidelity.summarise(close)[1]["lego/gap"]["verdict"] == "MixNeRF ahead, within the spread"
    one_seed = [_run("lego", "mipnerf", 0, [18.0], [20.0]), _run("lego", "mixnerf", 0, [19.0], [20.0])]
    assert fidelity.summarise(one_seed)[1]["lego/gap"]["verdict"] == "one seed: no spread yet"
