"""Rendering that skips, as a user gets it: `python -m mixnerf_eqx.eval` of trained runs with
`--skipping off` and `--skipping on`, in fresh processes, one after the other.

    python benchmarks/render_skipping.py runs/ts_lego/seed_0_dense runs/builtin_grid
    python benchmarks/render_skipping.py RUN_DIR --max-views 4 --out benchmarks/results/NAME

For each run: the wall time of each command (no compilation cache: what a first evaluation
costs), the grid's seconds (its refresh and the threshold choice on validation pixels, or
training pixels where a scene has none: never a test view), the chosen threshold, field
evaluations per frame made and needed against dense, seconds per frame, and the test PSNR,
SSIM and LPIPS of both, with the largest per-view PSNR change; and every threshold the choice
tried, with its bound on the PSNR lost on its pixels, the PSNR it did lose there (recorded
since the choice could be made by it) and its savings there (why it stopped where it did).

Output: `--out` (default `benchmarks/results/render_skipping_<backend>`) `.json` and `.md`.
"""

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import harness


def evaluate(run_dir: Path, mode: str, out: Path, max_views: int, data_dir: str | None) -> dict[str, Any]:
    """One `eval` in a fresh process; its metrics and wall time."""
    command = [sys.executable, "-m", "mixnerf_eqx.eval", str(run_dir), "--skipping", mode, "--no-renders"]
    command += ["--no-progress", "--no-compilation-cache", "--out", str(out), "--max-views", str(max_views)]
    if data_dir:
        command += ["--data-dir", data_dir]
    start = time.perf_counter()
    finished = subprocess.run(command, cwd=harness.REPO, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if finished.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{finished.stderr[-3000:]}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"wall_s": wall, "metrics": metrics}


def summary(run_dir: Path, dense: dict[str, Any], skipping: dict[str, Any]) -> dict[str, Any]:
    d, s = dense["metrics"], skipping["metrics"]
    render = s["render"]
    changes = [b["psnr"] - a["psnr"] for a, b in zip(d["per_view"], s["per_view"], strict=True)]
    return {
        "run": str(run_dir),
        "scene": d["scene"],
        "views": d["num_views"],
        "wall_dense_s": dense["wall_s"],
        "wall_skipping_s": skipping["wall_s"],
        "grid_s": render["grid_seconds"],
        "threshold": render["density_threshold"],
        "occupied": render["occupied_fraction"],
        "dense_per_frame": render["dense_evaluations_per_frame"],
        "made_per_frame": render["field_evaluations_per_frame"],
        "needed_per_frame": render["needed_evaluations_per_frame"],
        "reduction": render["evaluation_reduction"],
        "seconds_per_frame_dense": d["render"]["seconds_per_frame"],
        "seconds_per_frame_skipping": render["seconds_per_frame"],
        "dense": {k: d["mean"].get(k) for k in ("psnr", "ssim", "lpips")},
        "skipping": {k: s["mean"].get(k) for k in ("psnr", "ssim", "lpips")},
        "largest_view_psnr_change": max(changes, key=abs),
        # Every threshold the choice rendered on its pixels: why it stopped where it did.
        "trials": (render.get("threshold_choice") or {}).get("trials", []),
        # The views those pixels came from (choices recorded before it was said: training).
        "threshold_views": (render.get("threshold_choice") or {"views": None}).get("views", "train"),
    }


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| run | views | wall s, dense / skipping | grid s | threshold | evaluations per frame, made (needed) of dense | fewer | s per frame, dense / skipping | PSNR, dense / skipping (largest view change) | SSIM | LPIPS |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lpips = "n/a" if r["dense"]["lpips"] is None else f"{r['dense']['lpips']:.4f} / {r['skipping']['lpips']:.4f}"
        lines.append(
            f"| {r['run']} ({r['scene']}) | {r['views']} | {r['wall_dense_s']:.0f} / {r['wall_skipping_s']:.0f} | "
            f"{r['grid_s']:.1f} | {r['threshold']:.3g} | {r['made_per_frame']:,.0f} ({r['needed_per_frame']:,.0f}) of "
            f"{r['dense_per_frame']:,.0f} | {r['reduction']:.2f}x | {r['seconds_per_frame_dense']:.2f} / "
            f"{r['seconds_per_frame_skipping']:.2f} | {r['dense']['psnr']:.3f} / {r['skipping']['psnr']:.3f} "
            f"({r['largest_view_psnr_change']:+.3f}) | {r['dense']['ssim']:.4f} / {r['skipping']['ssim']:.4f} | {lpips} |"
        )
    return "\n".join(lines) + "\n"


def trials_table(rows: list[dict[str, Any]]) -> str:
    """The thresholds each choice tried on its pixels (validation or training views), sorted by
    threshold: the bound on the PSNR it could lose and how many fewer evaluations it made."""
    lines = [
        "| run | chosen on | thresholds tried (bound on the PSNR lost / PSNR lost, dB; fewer evaluations) |",
        "|---|---|---|",
    ]

    def cell(t: dict[str, Any]) -> str:
        # Choices recorded before the loss itself was measured have only the bound.
        lost = t.get("psnr_drop_db")
        measured = "" if lost is None or math.isnan(lost) else f" / {lost:+.3f}"
        return f"{t['threshold']:.3g} ({t['bound_db']:.3f}{measured}; {t['reduction']:.2f}x)"

    for r in rows:
        tried = "; ".join(cell(t) for t in sorted(r.get("trials", []), key=lambda t: t["threshold"]))
        # Rows written before the views were recorded were chosen on training pixels.
        recorded = r.get("threshold_views", "train" if r.get("trials") else None)
        views = {"val": "validation pixels", "train": "training pixels"}.get(recorded, "-")
        lines.append(f"| {r['run']} | {views} | {tried or 'none (no threshold chosen)'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", type=Path, help="trained run folders")
    parser.add_argument("--max-views", type=int, default=0, help="test views, evenly spaced (0: all)")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--tables-from",
        type=Path,
        default=None,
        help="write the tables of this script's earlier .json again (no evaluation; the runs are ignored)",
    )
    args = parser.parse_args(argv)
    if args.tables_from is None and not args.runs:
        parser.error("name at least one run folder (or --tables-from an earlier result)")
    if args.tables_from is not None:
        earlier = json.loads(args.tables_from.read_text())
        rows = earlier["rows"]
        text = table(rows) + "\n" + trials_table(rows)
        print(text, end="")
        if args.out:
            made = f"{earlier.get('command', '?')} (tables written again by: {harness.command_line()})"
            args.out.with_suffix(".md").write_text(f"<!-- made by: {made} -->\n\n" + text)
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for index, run_dir in enumerate(args.runs):
            outputs = {mode: Path(scratch) / f"{index}_{mode}" for mode in ("off", "on")}
            dense = evaluate(run_dir, "off", outputs["off"], args.max_views, args.data_dir)
            skipping = evaluate(run_dir, "on", outputs["on"], args.max_views, args.data_dir)
            rows.append(summary(run_dir, dense, skipping))
            print(table(rows[-1:]), end="", flush=True)
    out = args.out or harness.RESULTS / f"render_skipping_{harness.platform_tag()}"
    payload = {"command": harness.command_line(), "machine": harness.machine_info(), "rows": rows}
    harness.write_json(out.with_suffix(".json"), payload)
    text = table(rows) + "\n" + trials_table(rows)
    out.with_suffix(".md").write_text(f"<!-- made by: {harness.command_line()} -->\n\n" + text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
