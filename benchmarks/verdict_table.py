"""One verdict table per scene and regime: MixNeRF - baseline on the test views, paired by seed.

    python benchmarks/verdict_table.py            # prints it and writes results/verdict_cpu.md

Gathers the rows from the result files the fidelity section of `benchmarks/README.md` is made
of (each names the command that makes it): the 500-epoch protocol's summary
(`fidelity.py --report`) and the sweeps' verdicts (`sweep_verdict.py --out`). Every cell is
MixNeRF - baseline over the seeds both methods finished, mean ± the half-width of its Student-t
95% interval (n - 1 degrees of freedom), "ahead" or "behind" only when the interval excludes
zero; the last column counts the runs that failed (test PSNR more than 3 dB below the median of
the baseline's runs on the scene). A row whose result file is
missing is listed as not made, so the table never drops a row silently.
"""

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fidelity import VERDICT_METRICS, failed, paired_from_diffs, verdict_cell  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


@dataclass(frozen=True)
class Row:
    scene: str
    images: str
    training: str
    chosen_on: str  # which views chose the settings
    source: str  # a file under results/
    key: str  # the scene's key in that file
    # What the sweep record calls the first method: MixNeRF, or the setting a config adopted
    # after the record was made (the row's training says which).
    first: str = "MixNeRF"


ROWS = (
    Row(
        "built-in",
        "4 x 64x64",
        "quick start (tri-plane), 1,800 steps",
        "validation away from test (steps, priors, ramp; 5 seeds); its test views, earlier (grid)",
        "quickstart5_verdict_cpu.json",
        "builtin",
    ),
    Row(
        "built-in",
        "4 x 32x32",
        "protocol, tri-plane, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_triplane_summary.json",
        "builtin",
    ),
    Row(
        "built-in",
        "4 x 32x32",
        "protocol, hash grid, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_hash_summary.json",
        "builtin",
    ),
    Row(
        "built-in",
        "4 x 32x32",
        "protocol, MLP 4x64, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_ladder_4x64_summary.json",
        "builtin",
    ),
    Row(
        "built-in",
        "4 x 32x32",
        "protocol, MLP 4x128, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_ladder_4x128_summary.json",
        "builtin",
    ),
    Row(
        "fern",
        "3 x 56x42",
        "protocol, tri-plane, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_triplane_summary.json",
        "fern",
    ),
    Row(
        "fern",
        "3 x 56x42",
        "protocol, hash grid, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_hash_summary.json",
        "fern",
    ),
    Row(
        "fern",
        "3 x 504x378",
        "llff3_grid with the paper's lambda_C ramp (its default until 2026-12-06), "
        "512 rays, 32 + 32 samples, 14,000 steps (12.5 epochs)",
        "built-in's and fern's test views, earlier (grid)",
        "full_res_fern_cpu.json",
        "fern",
    ),
    Row(
        "fern",
        "3 x 504x378",
        "llff3_grid without the ramp (its default since 2026-12-06; before the distortion loss), "
        "512 rays, 32 + 32 samples, 14,000 steps",
        "fern's validation views away from test (ramp; 5 seeds); "
        "built-in's and fern's test views, earlier (grid)",
        "full_res_fern_noramp_baseline_newval.json",
        "fern",
        first="no ramp",
    ),
    Row(
        "fern",
        "3 x 504x378",
        "llff3_grid as it ships: no ramp, distortion loss 0.01 (its default since 2026-12-06; "
        "the baseline without it), 512 rays, 32 + 32 samples, 14,000 steps",
        "fern's validation views away from test (ramp, distortion loss; 5 seeds each); "
        "built-in's and fern's test views, earlier (grid)",
        "full_res_fern_distortion_baseline_newval.json",
        "fern",
        first="distortion",
    ),
    Row(
        "lego",
        "4 x 40x40",
        "protocol, tri-plane, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_triplane_summary.json",
        "lego",
    ),
    Row(
        "lego",
        "4 x 40x40",
        "protocol, hash grid, 500 epochs",
        "fixed in advance",
        "fidelity_cpu_hash_summary.json",
        "lego",
    ),
    Row(
        "lego",
        "4 x 400x400",
        "blender4_grid (the paper's lambda_C ramp), 512 rays, 32 + 32 samples, 7,800 steps (6.2 epochs)",
        "lego's validation views away from test (ramp kept; 5 seeds); built-in's test views, earlier (grid)",
        "full_res_lego_baseline_newval.json",
        "lego",
    ),
)


@dataclass(frozen=True)
class Found:
    cells: dict[str, Any]  # metric -> paired verdict on the test views (None: not scored)
    seeds: list[int]  # the seeds both methods finished (the pairs)
    failed: tuple[list[int], list[int]]  # MixNeRF's failed seeds, the baseline's
    runs: tuple[int, int]  # how many runs each method finished


def _interval(found: dict[str, Any] | None, higher: bool) -> dict[str, Any] | None:
    """A stored paired verdict re-derived from its per-seed differences, so that every row
    uses the same interval and rule whenever its file was written."""
    return None if found is None else paired_from_diffs(found["seeds"], found["diffs"], higher)


def row_verdicts(
    record: dict[str, Any], key: str, source: str = "", first: str = "MixNeRF"
) -> Found | None:
    """The verdicts of scene `key` in a result file: a `fidelity.py` summary (the test views at
    the end of training) or a `sweep_verdict.py` record (its test row); `None` without the
    scene. A sweep record must compare `first` (MixNeRF, or a setting a config adopted since)
    with the baseline (second)."""
    if "verdict" in record:
        found = record["verdict"].get(key)
        if found is None:
            return None
        runs = len(found["seeds"])  # the protocol trains both methods on every seed
        cells = {m: _interval(found.get(m), higher) for _, m, higher, _ in VERDICT_METRICS}
        if "failed" not in found:
            raise SystemExit(f"{source}: written before failed runs were counted; re-make it (fidelity.py --report)")
        fell = (found["failed"]["mixnerf"], found["failed"]["mipnerf"])
        return Found(cells, found["seeds"], fell, (runs, runs))
    if "scenes" not in record:
        raise SystemExit(f"{source}: neither a fidelity.py summary nor a sweep_verdict.py record")
    names = record.get("names", ["MixNeRF", "baseline"])
    if names != [first, "baseline"]:
        raise SystemExit(f"{source}: compares {names[0]} with {names[1]}, not {first} with the baseline")
    found = record["scenes"].get(key)
    if found is None:
        return None
    cells = {m: _interval(found["test"][m]["verdict"], higher) for _, m, higher, _ in VERDICT_METRICS}
    psnr = {name: {int(s): v for s, v in found["test"]["psnr"][name].items()} for name in ("mixnerf", "baseline")}
    missing = {name: [s for s in found["runs"][name] if s not in psnr[name]] for name in psnr}
    fell = tuple(sorted(failed(psnr[name], psnr["baseline"]) + missing[name]) for name in ("mixnerf", "baseline"))
    runs = (len(found["runs"]["mixnerf"]), len(found["runs"]["baseline"]))
    return Found(cells, found["seeds"], fell, runs)


def markdown(results: Path = RESULTS) -> str:
    metrics = " | ".join(name for name, *_ in VERDICT_METRICS)
    lines = [
        "| scene | images | training | settings chosen on | seeds | "
        + metrics
        + " | failed (MixNeRF / baseline) |",
        "|---|---|---|---|---|" + "---|" * len(VERDICT_METRICS) + "---|",
    ]
    digits = {m: d for _, m, _, d in VERDICT_METRICS}
    blanks = " | ".join("" for _ in VERDICT_METRICS)
    for row in ROWS:
        head = f"| {row.scene} | {row.images} | {row.training} | {row.chosen_on} | "
        path = results / row.source
        if not path.is_file():
            lines.append(head + f"not made (`results/{row.source}`) | {blanks} | |")
            continue
        found = row_verdicts(json.loads(path.read_text()), row.key, f"results/{row.source}", row.first)
        if found is None:
            lines.append(head + f"not made (no {row.key} in `results/{row.source}`) | {blanks} | |")
            continue
        body = " | ".join(verdict_cell(found.cells[m], digits[m]) for _, m, _, _ in VERDICT_METRICS)
        fell = " / ".join(f"{len(c)} of {n}" for c, n in zip(found.failed, found.runs, strict=True))
        lines.append(head + f"{len(found.seeds)} | {body} | {fell} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", type=Path, default=RESULTS, help="the result files' folder")
    parser.add_argument(
        "--out", type=Path, default=None, help="markdown file (default: RESULTS/verdict_cpu.md)"
    )
    args = parser.parse_args(argv)
    text = markdown(args.results)
    print(text, end="")
    out = args.out or args.results / "verdict_cpu.md"
    out.write_text(text)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
