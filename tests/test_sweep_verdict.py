"""`benchmarks/sweep_verdict.py`: two sweep folders paired seed by seed, on synthetic runs
whose answers are worked out by hand."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import sweep_verdict  # noqa: E402


def _sweep(root: Path, psnr: dict[int, float | None], offset: float = 0.0) -> Path:
    for seed, value in psnr.items():
        run = root / "fern" / f"seed_{seed}"
        run.mkdir(parents=True)
        if value is None:  # still running: no metrics.json
            continue
        scores = {"psnr": value, "ssim": 0.5 + value / 100, "lpips": 0.4 - value / 100}
        metrics = {"val": {**scores, "psnr": value + offset}, "test": scores}
        (run / "metrics.json").write_text(json.dumps(metrics))
    return root


def test_paired_verdicts_per_split_collapses_and_unfinished_runs(tmp_path, capsys):
    # Differences +1.0, +1.2, +0.8 on test: mean 1.0, standard error 0.2/sqrt(3) = 0.115, 95%
    # half-width 4.303 x 0.115 = 0.50: ahead.
    mix = _sweep(tmp_path / "mix", {0: 20.0, 1: 20.2, 2: 19.8, 3: None}, offset=-1.0)
    base = _sweep(tmp_path / "base", {0: 19.0, 1: 19.0, 2: 19.0})
    table = sweep_verdict.verdicts(sweep_verdict.read_sweep(mix)[0], sweep_verdict.read_sweep(base)[0])
    test = table["fern"]["test"]["psnr"]["verdict"]
    assert test["seeds"] == [0, 1, 2] and test["verdict"] == "ahead"
    assert test["mean"] == pytest.approx(1.0) and test["stderr"] == pytest.approx(0.2 / 3**0.5)
    # Validation PSNR 1 dB lower for MixNeRF: the same differences minus 1, mean 0: level.
    assert table["fern"]["val"]["psnr"]["verdict"]["verdict"] == "level"
    # LPIPS falls as PSNR rises here: lower is better, so MixNeRF is ahead there too.
    assert table["fern"]["test"]["lpips"]["verdict"]["verdict"] == "ahead"
    assert table["fern"]["test"]["depth_mae"]["verdict"] is None  # no depth: n/a
    assert table["fern"]["failed"] == {"mixnerf": [], "baseline": []}

    out = tmp_path / "out" / "verdict"
    assert sweep_verdict.main([str(mix), str(base), "--title", "t", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "MixNeRF: not finished, left out: fern/seed_3" in printed
    assert "| fern | test | 3 | +1.00 ± 0.50: ahead |" in printed
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["unfinished"]["mixnerf"] == ["fern/seed_3"]
    assert record["title"] == "t"

    # Without --title the title follows --names: a remedy's table is not called MixNeRF's.
    assert sweep_verdict.main([str(mix), str(base), "--names", "no ramp", "MixNeRF", "--out", str(out)]) == 0
    assert out.with_suffix(".md").read_text().startswith("### no ramp against MixNeRF\n")
    assert sweep_verdict.main([str(mix), str(base), "--out", str(out)]) == 0
    assert json.loads(out.with_suffix(".json").read_text())["title"] == "MixNeRF against its baseline"


def test_a_failed_run_and_too_few_seeds(tmp_path):
    mix = _sweep(tmp_path / "mix", {0: 20.0, 1: 20.0, 2: 15.0})
    base = _sweep(tmp_path / "base", {0: 19.0, 1: 19.0})
    table = sweep_verdict.verdicts(sweep_verdict.read_sweep(mix)[0], sweep_verdict.read_sweep(base)[0])
    assert table["fern"]["failed"]["mixnerf"] == [2]  # 4 dB below the baseline's median of 19
    assert table["fern"]["test"]["psnr"]["verdict"]["verdict"] == "2 seeds: no verdict"
    with pytest.raises(SystemExit, match="no such sweep folder"):
        sweep_verdict.read_sweep(tmp_path / "missing")


def test_null_validation_diverged_runs_and_what_the_pairing_leaves_out(tmp_path, capsys):
    """A scene without validation views writes `"val": null`, a diverged run null metrics:
    neither stops the table; the diverged run counts as failed; unpaired runs and pairs of
    different lengths are said."""
    mix = _sweep(tmp_path / "mix", {0: 20.0, 1: 20.2, 2: 19.8, 4: 20.0})
    base = _sweep(tmp_path / "base", {0: 19.0, 1: 19.0, 2: 19.0})
    (base / "fern" / "seed_0" / "notes.txt").write_text("")  # not a run folder: ignored
    (base / "fern" / "seed_x").mkdir()
    for seed in (0, 1, 2):
        path = mix / "fern" / f"seed_{seed}" / "metrics.json"
        metrics = json.loads(path.read_text())
        metrics["val"] = None
        if seed == 2:
            metrics["test"]["psnr"] = None
        metrics["step"] = 900 if seed == 1 else 1000
        path.write_text(json.dumps(metrics))
    for seed in (0, 1, 2):
        path = base / "fern" / f"seed_{seed}" / "metrics.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "step": 1000}))
    (mix / "lego" / "seed_0").mkdir(parents=True)
    (mix / "lego" / "seed_0" / "metrics.json").write_text(json.dumps({"test": {"psnr": 20.0}}))
    assert sweep_verdict.main([str(mix), str(base), "--names", "remedy", "MixNeRF"]) == 0
    printed = capsys.readouterr().out
    assert "lego: only remedy has finished runs, left out" in printed
    assert "fern/seed_4: finished in one sweep only" in printed
    assert "fern/seed_1: paired although trained 900 and 1000 steps" in printed
    # Each row counts the seeds it pairs: no validation figures at all, and the diverged seed 2
    # has no test PSNR (three runs of each sweep are paired).
    assert "| fern | validation | 0 | n/a |" in printed
    assert "| fern | test | 2 | +1.10 ± " in printed
    table = sweep_verdict.verdicts(sweep_verdict.read_sweep(mix)[0], sweep_verdict.read_sweep(base)[0])
    assert table["fern"]["failed"]["mixnerf"] == [2]
    assert table["fern"]["val"]["psnr"]["verdict"] is None
    assert table["fern"]["test"]["psnr"]["verdict"]["seeds"] == [0, 1]
