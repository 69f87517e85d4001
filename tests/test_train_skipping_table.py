"""`benchmarks/train_skipping.py`'s table on synthetic runs whose figures are worked out by hand."""

import json
import sys
from pathlib import Path

import pytest

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


def _folder(root, name, evaluations, val, test, *, seed=3, skipping=None):
    """A finished run folder: 4 logged steps of 512 rays x (16 + 16) samples, the first two dense
    (no sample counts), then the given counts."""
    folder = root / name
    folder.mkdir()
    log = [{"step": 10 * (i + 1), "psnr": 20.0, "steps_per_s": 5.0} for i in range(4)]
    for entry, count in zip(log[2:], evaluations, strict=True):
        entry["field_evaluations"] = count
    (folder / "train_log.jsonl").write_text("".join(json.dumps(e) + "\n" for e in log))
    (folder / "metrics.json").write_text(json.dumps({"val": {"psnr": val}, "test": {"psnr": test}}))
    config = {
        "train": {"batch_size": 512, "seed": seed},
        "model": {"num_coarse_samples": 16, "num_fine_samples": 16},
        "occupancy": {"train_skipping": name == "skip" if skipping is None else skipping},
    }
    (folder / "config.json").write_text(json.dumps(config))
    return folder


def test_existing_runs_are_tabulated_without_times(tmp_path):
    dense = _folder(tmp_path, "dense", [16384, 16384], 18.0, 17.5)
    skipping = _folder(tmp_path, "skip", [4096, 2048], 17.5, 17.25)
    out = tmp_path / "out"
    assert train_skipping.main(["--existing", "3", str(dense), str(skipping), "--out", str(out)]) == 0
    text = out.with_suffix(".md").read_text()
    # Dense steps count 16,384 each; the skipping run's mean is (2 x 16,384 + 4,096 + 2,048) / 4 = 9,728.
    assert "| 3 | skipping | 9,728 | not timed | not timed | 17.50 | 17.25 |" in text
    assert "| field evaluations per step | 1.68x |" in text
    assert "| wall time | not timed |" in text
    assert "| val PSNR, skipping - dense | -0.50: 1 seed: no verdict |" in text
    (skipping / "metrics.json").unlink()
    with pytest.raises(SystemExit, match="no metrics.json"):
        train_skipping.main(["--existing", "3", str(dense), str(skipping), "--out", str(out)])


def test_existing_runs_must_be_what_they_are_given_as(tmp_path):
    dense = _folder(tmp_path, "dense", [16384, 16384], 18.0, 17.5)
    skipping = _folder(tmp_path, "skip", [4096, 2048], 17.5, 17.25)
    out = str(tmp_path / "out")
    swapped = "seed 3 with occupancy.train_skipping = true; given as the dense run of seed 3"
    with pytest.raises(SystemExit, match=swapped):
        train_skipping.main(["--existing", "3", str(skipping), str(dense), "--out", out])
    with pytest.raises(SystemExit, match="given as the dense run of seed 4"):
        train_skipping.main(["--existing", "4", str(dense), str(skipping), "--out", out])
    for wrong in (["--out", out, "--seeds", "1"], ["--out", out, "--config", "blender4_grid"], []):
        with pytest.raises(SystemExit):
            train_skipping.main(["--existing", "3", str(dense), str(skipping), *wrong])
    with pytest.raises(SystemExit):  # a seed given twice
        train_skipping.main(["--existing", "3", str(dense), str(skipping), "--existing", "3", str(dense),
                             str(skipping), "--out", out])
