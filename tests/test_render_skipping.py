"""`benchmarks/render_skipping.py`: its record keeps every threshold the choice tried."""

import dataclasses
import json
import sys
from pathlib import Path

from mixnerf_eqx._inference.threshold import ThresholdChoice, ThresholdTrial

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import render_skipping  # noqa: E402


def _metrics(psnrs, render):
    return {
        "scene": "fern",
        "num_views": len(psnrs),
        "per_view": [{"psnr": p} for p in psnrs],
        "mean": {"psnr": sum(psnrs) / len(psnrs), "ssim": 0.5, "lpips": 0.4},
        "render": render,
    }


def _render(choice):
    return {
        "grid_seconds": 2.0,
        "density_threshold": 0.04,
        "occupied_fraction": 0.98,
        "dense_evaluations_per_frame": 100.0,
        "field_evaluations_per_frame": 99.0,
        "needed_evaluations_per_frame": 98.0,
        "evaluation_reduction": 100 / 99,
        "seconds_per_frame": 1.0,
        "threshold_choice": choice,
    }


def _choice(tried, kept, **recorded):
    """The choice that kept trial `kept` of `tried`, chosen on validation pixels."""
    return ThresholdChoice(
        threshold=kept.threshold,
        bound_db=kept.bound_db,
        reduction=kept.reduction,
        within_tolerance=True,
        tolerance_db=0.1,
        trials=tried,
        views="val",
        **recorded,
    )


def _row(run, dense_psnrs, skipping_psnrs, choice):
    """`summary` of a dense and a skipping eval, the choice as `eval` writes it (`asdict`)."""
    dense = {"wall_s": 10.0, "metrics": _metrics(dense_psnrs, {"seconds_per_frame": 1.0})}
    render = _render(None if choice is None else dataclasses.asdict(choice))
    skipping = {"wall_s": 12.0, "metrics": _metrics(skipping_psnrs, render)}
    return render_skipping.summary(Path(run), dense, skipping)


def test_the_trials_are_kept_and_listed_by_threshold():
    # The choice as `eval` writes it into metrics.json (`dataclasses.asdict`), trials in the order tried.
    tried = (
        ThresholdTrial(1.28, 1.82, 1.16),
        ThresholdTrial(0.08, 0.155, 1.0),
        ThresholdTrial(0.02, 0.016, 1.0),
    )
    row = _row("runs/x", [20.0, 19.0], [20.0, 18.9], _choice(tried, tried[2]))
    assert [t["threshold"] for t in row["trials"]] == [1.28, 0.08, 0.02]
    assert abs(row["largest_view_psnr_change"] + 0.1) < 1e-9
    line = render_skipping.trials_table([row]).splitlines()[-1]
    tried_cell = "0.02 (0.016; 1.00x); 0.08 (0.155; 1.00x); 1.28 (1.820; 1.16x)"
    assert line == f"| runs/x | validation pixels | {tried_cell} |"


def test_a_run_without_a_chosen_threshold_says_so():
    row = _row("runs/y", [20.0], [20.0], None)
    assert row["trials"] == []
    line = render_skipping.trials_table([row]).splitlines()[-1]
    assert line == "| runs/y | - | none (no threshold chosen) |"


def test_the_trials_show_the_measured_loss_where_it_was_recorded_and_tables_can_be_written_again(tmp_path):
    tried = (ThresholdTrial(1.28, 1.82, 4.2, 0.25), ThresholdTrial(0.08, 0.9, 3.0, -0.031))
    row = _row("runs/z", [20.0], [20.03], _choice(tried, tried[1], measure="psnr", psnr_drop_db=-0.031))
    line = render_skipping.trials_table([row]).splitlines()[-1]
    tried_cell = "0.08 (0.900 / -0.031; 3.00x); 1.28 (1.820 / +0.250; 4.20x)"
    assert line == f"| runs/z | validation pixels | {tried_cell} |"
    # A row written before the views were recorded reads as training pixels, as it was.
    old = {k: v for k, v in row.items() if k != "threshold_views"}
    assert "| training pixels |" in render_skipping.trials_table([old]).splitlines()[-1]
    # --tables-from writes the tables of an earlier .json again, keeping its command.
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"command": "python benchmarks/render_skipping.py runs/z", "rows": [row]}))
    assert render_skipping.main(["--tables-from", str(earlier), "--out", str(tmp_path / "again")]) == 0
    text = (tmp_path / "again.md").read_text()
    assert text.startswith("<!-- made by: python benchmarks/render_skipping.py runs/z (tables written again")
    assert line in text
