"""`benchmarks/remedy_table.py` on synthetic runs whose figures are worked out by hand."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import remedy_table  # noqa: E402


def _run(method, seed, psnr, scene="lego"):
    return {"scene": scene, "method": method, "seed": seed, "key": f"{scene}/{method}/seed{seed}", "final": {"test": {"psnr": psnr}}}


def test_a_remedy_made_apart_is_paired_by_seed_with_failures_counted(tmp_path, capsys):
    remedy = [_run("mixnerf-x", s, p) for s, p in enumerate([20.0, 20.5, 21.0])]
    reference = [_run("mixnerf", s, p) for s, p in enumerate([21.0, 10.7, 11.0])]
    reference += [_run("mipnerf", s, p) for s, p in enumerate([19.0, 19.4, 19.5])]
    reference.append(_run("mipnerf", 0, 5.0, scene="fern"))  # another scene: not read
    for name, runs in (("remedy.jsonl", remedy), ("reference.jsonl", reference)):
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in runs))
    assert remedy_table.main([str(tmp_path / "remedy.jsonl"), str(tmp_path / "reference.jsonl"), "--remedy", "mixnerf-x", "--scene", "lego"]) == 0
    printed = capsys.readouterr().out
    # The baseline's median is 19.4: the line is 16.4; MixNeRF's seeds 1 and 2 fail.
    assert "| mixnerf | 0: 21.00, 1: 10.70, 2: 11.00 | 2 of 3 |" in printed
    assert "| mixnerf-x | 0: 20.00, 1: 20.50, 2: 21.00 | 0 of 3 |" in printed
    # Remedy - baseline: +1.0, +1.1, +1.5: mean 1.2, sd 0.2646, se 0.1528, half-width 4.303 x 0.1528.
    assert "| mixnerf-x - mipnerf | +1.20 ± 0.66: ahead |" in printed
    # Remedy - MixNeRF: -1.0, +9.8, +10.0: mean 6.27, se 3.634, half-width 4.303 x 3.634 = 15.63: level.
    assert "| mixnerf-x - mixnerf | +6.27 ± 15.63: level |" in printed
