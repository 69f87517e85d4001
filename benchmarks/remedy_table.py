"""A remedy's runs of the fidelity protocol against MixNeRF's and the baseline's, made apart.

    python benchmarks/remedy_table.py results/fidelity_cpu_triplane_nopaint.jsonl \
        results/fidelity_cpu_triplane.jsonl --remedy mixnerf-no-paint --scene lego

`fidelity.py` pairs a remedy with MixNeRF within one result file. A remedy run later, into a
file of its own (`--tag`), is paired here with the runs of another file, seed by seed, on
the test views at the end of training (which the validation split does not touch; the
validation views differ between the files when they were made on either side of a change to
the split, so no validation figure is paired). Per method: the test PSNR per seed and the
failed runs (more than 3 dB below the baseline's median); then the remedy - MixNeRF and
remedy - baseline differences with their Student-t 95% intervals (`fidelity.paired_verdict`).
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fidelity import FAIL_DB, failed, paired_verdict, read_runs, verdict_cell  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def end_psnr(runs: list[dict], scene: str, method: str) -> dict[int, float]:
    """`{seed: test PSNR at the end}` of one method's runs on `scene`."""
    return {r["seed"]: r["final"]["test"]["psnr"] for r in runs if r["scene"] == scene and r["method"] == method}


def table(remedy_runs: list[dict], reference_runs: list[dict], remedy: str, scene: str) -> str:
    values = {
        remedy: end_psnr(remedy_runs, scene, remedy),
        "mixnerf": end_psnr(reference_runs, scene, "mixnerf"),
        "mipnerf": end_psnr(reference_runs, scene, "mipnerf"),
    }
    lines = [
        f"| {scene}, test PSNR at the end | per seed | failed |",
        "|---|---|---|",
    ]
    for method, found in values.items():
        seeds = ", ".join(f"{s}: {v:.2f}" for s, v in sorted(found.items()))
        lines.append(f"| {method} | {seeds} | {len(failed(found, values['mipnerf']))} of {len(found)} |")
    lines += ["", "| paired by seed | test PSNR |", "|---|---|"]
    for other in ("mixnerf", "mipnerf"):
        lines.append(f"| {remedy} - {other} | {verdict_cell(paired_verdict(values[remedy], values[other], True))} |")
    lines += [
        "",
        f"A run failed when its test PSNR lies more than {FAIL_DB:g} dB below the baseline's median; "
        "differences: mean ± the half-width of the Student-t 95% interval over the seeds both have.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("remedy_file", type=Path)
    parser.add_argument("reference_file", type=Path)
    parser.add_argument("--remedy", required=True, help="the remedy's method name, e.g. mixnerf-no-paint")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--out", type=Path, default=None, help="write the table here too")
    args = parser.parse_args(argv)
    paths = [p if p.is_absolute() or p.exists() else RESULTS.parent / p for p in (args.remedy_file, args.reference_file)]
    text = table(read_runs(paths[0]), read_runs(paths[1]), args.remedy, args.scene)
    print(text, end="")
    if args.out is not None:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
