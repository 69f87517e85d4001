"""The paired verdict of two sweeps: MixNeRF against its baseline, seed by seed.

    python benchmarks/sweep_verdict.py runs/full_fern/mixnerf runs/full_fern/mipnerf \
        --title "fern 3-view, 504x378, 14,000 steps" --out benchmarks/results/full_res_fern

Each argument is a folder written by `python -m mixnerf_eqx.sweep` (`SCENE/seed_N/metrics.json`
per finished run). For every scene both sweeps finished, and for the validation and the test
views, the table gives MixNeRF - baseline paired by seed (mean ± the half-width of its
Student-t 95% interval, "ahead" or "behind" only when the interval excludes zero,
`fidelity.paired_verdict`) for PSNR, SSIM, LPIPS and depth error where the scene knows its
depth, and the runs that failed (test PSNR more than 3 dB below the median of the second
sweep's runs on the scene, or no test PSNR at all). Validation views are where settings are
chosen; the test row is the record. Runs still in progress (no `metrics.json`) are listed and
left out. `--out STEM` writes `STEM.json` and `STEM.md`.
"""

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fidelity import FAIL_DB, VERDICT_METRICS, failed, paired_verdict, verdict_cell  # noqa: E402

SPLITS = ("val", "test")


def read_sweep(folder: Path) -> tuple[dict[str, dict[int, dict[str, Any]]], list[str]]:
    """`{scene: {seed: metrics}}` of the finished runs under `folder`, and the unfinished runs."""
    if not folder.is_dir():
        raise SystemExit(f"{folder}: no such sweep folder")
    finished: dict[str, dict[int, dict[str, Any]]] = {}
    unfinished = []
    for run in sorted(folder.glob("*/seed_*")):
        if not run.is_dir() or not run.name.removeprefix("seed_").isdigit():
            continue
        scene, seed = run.parent.name, int(run.name.removeprefix("seed_"))
        metrics = run / "metrics.json"
        if not metrics.is_file():
            unfinished.append(f"{scene}/seed_{seed}")
            continue
        finished.setdefault(scene, {})[seed] = json.loads(metrics.read_text())
    return finished, unfinished


def pairing_notes(
    mix: dict[str, dict[int, dict[str, Any]]],
    base: dict[str, dict[int, dict[str, Any]]],
    names: tuple[str, str],
) -> list[str]:
    """What the pairing leaves out or pairs although it differs: scenes and seeds that one
    sweep finished and the other did not, and pairs trained for different numbers of steps."""
    notes = []
    for scene in sorted(set(mix) ^ set(base)):
        notes.append(f"{scene}: only {names[0] if scene in mix else names[1]} has finished runs, left out")
    for scene in sorted(set(mix) & set(base)):
        for seed in sorted(set(mix[scene]) ^ set(base[scene])):
            notes.append(f"{scene}/seed_{seed}: finished in one sweep only, left out of the pairs")
        for seed in sorted(set(mix[scene]) & set(base[scene])):
            steps = (mix[scene][seed].get("step"), base[scene][seed].get("step"))
            if steps[0] != steps[1]:
                notes.append(f"{scene}/seed_{seed}: paired although trained {steps[0]} and {steps[1]} steps")
    return notes


def _values(runs: dict[int, dict[str, Any]], split: str, key: str) -> dict[int, float]:
    """`{seed: metric}` of the runs that scored `key` on `split`."""
    # A scene without validation views has `"val": null`; a diverged run has null metrics.
    return {seed: m[split][key] for seed, m in runs.items() if (m.get(split) or {}).get(key) is not None}


def verdicts(
    mix: dict[str, dict[int, dict[str, Any]]], base: dict[str, dict[int, dict[str, Any]]]
) -> dict[str, Any]:
    """Per scene both sweeps have: per split and metric the paired verdict, the per-seed
    figures of each method, and the failed seeds of each method (on the test views)."""
    table: dict[str, Any] = {}
    for scene in sorted(set(mix) & set(base)):
        row: dict[str, Any] = {"seeds": sorted(set(mix[scene]) & set(base[scene]))}
        for split in SPLITS:
            row[split] = {}
            for _, key, higher, _ in VERDICT_METRICS:
                mix_values = _values(mix[scene], split, key)
                base_values = _values(base[scene], split, key)
                row[split][key] = {
                    "verdict": paired_verdict(mix_values, base_values, higher),
                    "mixnerf": mix_values,
                    "baseline": base_values,
                }
        # A run without a test PSNR (it diverged: NaN is written as null) counts as failed.
        reference = _values(base[scene], "test", "psnr")
        row["failed"] = {
            name: sorted(
                failed(_values(runs, "test", "psnr"), reference)
                + [seed for seed in runs if seed not in _values(runs, "test", "psnr")]
            )
            for name, runs in (("mixnerf", mix[scene]), ("baseline", base[scene]))
        }
        row["runs"] = {"mixnerf": sorted(mix[scene]), "baseline": sorted(base[scene])}
        table[scene] = row
    return table


def runs_from_record(record: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The per-seed metrics a written record holds, as `read_sweep` gives them, so that its
    verdicts can be re-made after the run folders are gone (`--remake`)."""
    sweeps: tuple[dict[str, Any], dict[str, Any]] = ({}, {})
    for scene, row in record["scenes"].items():
        for sweep, name in zip(sweeps, ("mixnerf", "baseline"), strict=True):
            runs = {int(seed): {"val": {}, "test": {}} for seed in row["runs"][name]}
            for split in SPLITS:
                for _, key, _, _ in VERDICT_METRICS:
                    for seed, value in row[split][key][name].items():
                        runs[int(seed)][split][key] = value
            sweep[scene] = runs
    return sweeps


def markdown(table: dict[str, Any], title: str, names: tuple[str, str] = ("MixNeRF", "baseline")) -> str:
    first, second = names
    lines = [
        f"### {title}",
        "",
        "| scene | views | seeds | "
        + " | ".join(f"{name} ({first} - {second})" for name, *_ in VERDICT_METRICS)
        + f" | failed ({first} / {second}) |",
        "|---|---|---|" + "---|" * len(VERDICT_METRICS) + "---|",
    ]
    for scene, row in table.items():
        for split in SPLITS:
            cells = [
                verdict_cell(row[split][key]["verdict"], digits) for _, key, _, digits in VERDICT_METRICS
            ]
            falls = (
                " / ".join(
                    f"{len(row['failed'][m])} of {len(row['runs'][m])}" for m in ("mixnerf", "baseline")
                )
                if split == "test"
                else ""
            )
            label = "validation" if split == "val" else "test"
            # The seeds this split pairs: a run may have no validation figures (a scene without
            # validation views, or a run scored on another split, left out of its record).
            paired = row[split]["psnr"]["verdict"]
            head = f"| {scene} | {label} | {len(paired['seeds']) if paired else 0} | "
            lines.append(head + " | ".join(cells) + f" | {falls} |")
    lines.append("")
    for scene, row in table.items():
        per_seed = row["test"]["psnr"]
        for name, label in zip(("mixnerf", "baseline"), names, strict=True):
            figures = ", ".join(f"seed {s}: {v:.2f}" for s, v in sorted(per_seed[name].items()))
            lines.append(f"- {scene}, {label} test PSNR: {figures}")
    lines.append("")
    lines.append(
        f"{first} - {second} paired by seed, mean ± the half-width of its Student-t 95% interval "
        "(n - 1 degrees of freedom); 'ahead' or 'behind' only when the interval excludes zero. A run "
        f"failed when its test PSNR is more than {FAIL_DB:g} dB below the median of {second}'s runs "
        "on the scene, or missing."
    )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("mixnerf", type=Path, nargs="?", help="the MixNeRF sweep's folder (first)")
    parser.add_argument(
        "baseline", type=Path, nargs="?", help="the baseline sweep's folder (second; same scenes and seeds)"
    )
    parser.add_argument(
        "--remake",
        type=Path,
        metavar="STEM",
        help="re-make STEM.json and STEM.md from the per-seed figures STEM.json holds (no folders needed)",
    )
    parser.add_argument(
        "--title", help="the table's title (default: FIRST against SECOND, or MixNeRF against its baseline)"
    )
    parser.add_argument(
        "--names",
        nargs=2,
        default=("MixNeRF", "baseline"),
        metavar=("FIRST", "SECOND"),
        help="what the two sweeps are called in the table (e.g. a remedy against MixNeRF)",
    )
    parser.add_argument("--out", type=Path, help="write STEM.json and STEM.md")
    args = parser.parse_args(argv)
    if args.remake is not None:
        return remake(args.remake)
    if args.mixnerf is None or args.baseline is None:
        parser.error("give the two sweep folders, or --remake STEM")
    if args.title is None:
        first, second = args.names
        args.title = (
            "MixNeRF against its baseline"
            if (first, second) == ("MixNeRF", "baseline")
            else f"{first} against {second}"
        )

    mix, mix_open = read_sweep(args.mixnerf)
    base, base_open = read_sweep(args.baseline)
    for name, left in zip(args.names, (mix_open, base_open), strict=True):
        if left:
            print(f"{name}: not finished, left out: {', '.join(left)}")
    for note in pairing_notes(mix, base, tuple(args.names)):
        print(note)
    table = verdicts(mix, base)
    if not table:
        raise SystemExit("no scene has finished runs in both sweeps")
    text = markdown(table, args.title, tuple(args.names))
    print(text, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        record = {
            "title": args.title,
            "mixnerf": str(args.mixnerf),
            "baseline": str(args.baseline),
            "names": list(args.names),
            "unfinished": {"mixnerf": mix_open, "baseline": base_open},
            "scenes": table,
        }
        args.out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
        args.out.with_suffix(".md").write_text(text)
        print(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.md')}")
    return 0


def remake(stem: Path) -> int:
    """Re-makes a written record's verdicts and table from its per-seed figures."""
    path = stem.with_suffix(".json")
    if not path.is_file():
        raise SystemExit(f"{path}: no such record")
    record = json.loads(path.read_text())
    mix, base = runs_from_record(record)
    record["scenes"] = verdicts(mix, base)
    text = markdown(record["scenes"], record["title"], tuple(record.get("names", ("MixNeRF", "baseline"))))
    print(text, end="")
    path.write_text(json.dumps(record, indent=1) + "\n")
    stem.with_suffix(".md").write_text(text)
    print(f"re-made {path} and {stem.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
