"""`benchmarks/verdict_table.py`: one row per scene and regime, from the two kinds of result
file, on synthetic records whose cells are worked out by hand; and the committed table is
the one the committed results make."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import verdict_table  # noqa: E402


def _verdict(diffs: list[float], verdict: str) -> dict:
    mean = sum(diffs) / len(diffs)
    spread = (sum((d - mean) ** 2 for d in diffs) / (len(diffs) - 1)) ** 0.5 / len(diffs) ** 0.5
    return {
        "seeds": list(range(len(diffs))),
        "diffs": diffs,
        "mean": mean,
        "stderr": spread,
        "verdict": verdict,
    }


def test_rows_from_a_protocol_summary_and_a_sweep_verdict_and_a_missing_file(tmp_path):
    # Differences 1, 2, 3: mean 2, standard error 1/sqrt(3) = 0.577, 95% half-width 4.303 x
    # 0.577 = 2.48: level. The stored verdicts (written by an older rule) are not trusted: the
    # table re-derives them from the differences.
    psnr = _verdict([1.0, 2.0, 3.0], "ahead")
    ssim = _verdict([0.01, 0.01, 0.04], "level")
    summary = {
        "verdict": {
            "builtin": {
                "psnr": psnr,
                "ssim": ssim,
                "lpips": None,
                "depth_mae": None,
                "failed": {"mixnerf": [], "mipnerf": [1]},
                "seeds": [0, 1, 2],
            }
        }
    }
    (tmp_path / "fidelity_cpu_triplane_summary.json").write_text(json.dumps(summary))
    # The sweep's validation row differs from its test row, so reading the wrong split shows.
    val = {
        m: {"verdict": _verdict([-1.0, -1.0, -1.3], "behind")} for m in ("psnr", "ssim", "lpips", "depth_mae")
    }
    # MixNeRF's seed 2 lies 5 dB below the baseline's median (19): failed; the baseline's
    # seed 3 has no test PSNR (it diverged): failed too.
    per_seed = {"mixnerf": {"0": 20.0, "1": 21.0, "2": 14.0}, "baseline": {"0": 19.0, "1": 19.0, "2": 19.0}}
    test = {"psnr": {"verdict": psnr, **per_seed}, "ssim": {"verdict": ssim}, "lpips": {"verdict": None}}
    sweep = {
        "names": ["MixNeRF", "baseline"],
        "scenes": {
            "builtin": {
                "seeds": [0, 1, 2],
                "val": val,
                "test": {**test, "depth_mae": {"verdict": None}},
                # The baseline finished a fourth, unpaired seed: its count is its own.
                "runs": {"mixnerf": [0, 1, 2], "baseline": [0, 1, 2, 3]},
            }
        },
    }
    (tmp_path / "quickstart5_verdict_cpu.json").write_text(json.dumps(sweep))

    lines = verdict_table.markdown(tmp_path).splitlines()
    assert len(lines) == 2 + len(verdict_table.ROWS)
    quick, protocol = lines[2], lines[3]
    assert quick.startswith("| built-in | 4 x 64x64 | quick start")
    assert "| 3 | +2.00 ± 2.48: level | +0.020 ± 0.043: level | n/a | n/a | 1 of 3 / 1 of 4 |" in quick
    assert "| 3 | +2.00 ± 2.48: level | +0.020 ± 0.043: level | n/a | n/a | 0 of 3 / 1 of 3 |" in protocol
    # The protocol's file has no fern; the ladder's and the full-resolution files are absent.
    fern = next(line for line in lines if line.startswith("| fern | 3 x 56x42 |"))
    assert "not made (no fern in `results/fidelity_cpu_triplane_summary.json`)" in fern
    assert "not made (`results/fidelity_cpu_hash_summary.json`)" in lines[4]
    assert "not made (`results/fidelity_cpu_ladder_4x64_summary.json`)" in lines[5]
    assert "not made (`results/fidelity_cpu_ladder_4x128_summary.json`)" in lines[6]
    assert "not made (`results/full_res_lego_baseline_newval.json`)" in lines[-1]

    # A sweep record of something else against MixNeRF is refused, not shown as MixNeRF's.
    sweep["names"] = ["background", "MixNeRF"]
    (tmp_path / "quickstart5_verdict_cpu.json").write_text(json.dumps(sweep))
    with pytest.raises(SystemExit, match="compares background with MixNeRF"):
        verdict_table.markdown(tmp_path)
    # A setting a config adopted after its sweep was made is read only by a row that names it.
    sweep["names"] = ["no ramp", "baseline"]
    assert verdict_table.row_verdicts(sweep, "builtin", "x", first="no ramp").seeds == [0, 1, 2]
    with pytest.raises(SystemExit, match="compares no ramp with baseline, not MixNeRF with the baseline"):
        verdict_table.row_verdicts(sweep, "builtin", "x")
    adopted = [row for row in verdict_table.ROWS if row.first != "MixNeRF"]
    assert adopted and all("default since" in row.training for row in adopted)


def test_the_committed_table_is_the_one_the_committed_results_make():
    committed = (verdict_table.RESULTS / "verdict_cpu.md").read_text()
    assert committed == verdict_table.markdown()
    # benchmarks/README.md opens its fidelity section with the same table.
    readme = (verdict_table.RESULTS.parent / "README.md").read_text()
    assert committed in readme
