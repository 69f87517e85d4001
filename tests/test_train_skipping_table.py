"""`benchmarks/train_skipping.py`'s table on synthetic runs whose figures are worked out by hand."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import train_skipping  # noqa: E402


def _run(seed, mode, evaluations, step_s, wall, val, test):
    return {
        "seed": seed,
        "mode": mode,
        "wall_s": wall,
        "median_step_s": step_s,
        "mean_evaluations_per_step": evaluations,
        "val_psnr": val,
        "test_psnr": test,
    }


def test_ratios_and_paired_differences_per_seed():
    runs = []
    for seed, (skip_evals, val_gain) in enumerate([(16384.0, 0.1), (8192.0, 0.2), (10922.0, 0.3)]):
        runs.append(_run(seed, "dense", 32768.0, 0.06, 120.0, 19.0, 19.5))
        runs.append(_run(seed, "skipping", skip_evals, 0.03, 60.0, 19.0 + val_gain, 19.5 - val_gain))
    text = train_skipping.table(runs)
    assert "| field evaluations per step | 2.00x / 4.00x / 3.00x |" in text
    assert "| median seconds per step | 2.00x / 2.00x / 2.00x |" in text
    # +0.1, +0.2, +0.3: mean 0.2, standard error 0.0577, half-width 4.303 x 0.0577 = 0.25.
    assert "| val PSNR, skipping - dense | +0.20 ± 0.25: level |" in text
    assert "| test PSNR, skipping - dense | -0.20 ± 0.25: level |" in text
