"""Training that skips against dense training, seed by seed, in one run of this script.

For each seed, the same config trains twice in fresh processes, one after the other: dense
(the config as given, `occupancy.train_skipping=false`: what a user trains without skipping;
the quick start keeps no occupancy grid) and skipping (`occupancy.enabled=true
occupancy.train_skipping=true` and any `--skip-set` overrides: the grid's upkeep, its final
threshold choice and the skipping renders count against skipping). The table gives,
per seed and mode: field evaluations per step (the mean over the logged steps of
`train_log.jsonl`, the steps before the grid's warm-up counted as dense), the median seconds
per step (steps after the 20th), the wall time of the whole command, and the final validation
and test PSNR (`metrics.json`); then the paired ratios (dense / skipping) and the paired PSNR
differences (skipping - dense, Student-t 95%).

`--existing SEED DENSE_DIR SKIPPING_DIR` (repeatable) tabulates run folders trained earlier
instead of training: evaluations and PSNRs only, since their seconds were not measured side by
side (the time columns say `not timed`).

    python benchmarks/train_skipping.py --seeds 0 1 2                      # the quick start
    python benchmarks/train_skipping.py --no-compilation-cache             # what a first run costs
    python benchmarks/train_skipping.py --config blender4_grid --seeds 0 --set data.data_dir='"../shared/data"'
    python benchmarks/train_skipping.py --existing 2 runs/a/seed_2 runs/b/seed_2 --out OUT

Output: `--out` (default `benchmarks/results/train_skipping_<backend>`) `.json` and `.md`.
"""

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import harness
from fidelity import paired_verdict, verdict_cell

MODES = {
    "dense": ("occupancy.train_skipping=false",),
    "skipping": ("occupancy.enabled=true", "occupancy.train_skipping=true"),
}


def train(
    config: str | None, seed: int, mode: str, run_dir: Path, overrides: list[str], cache: bool = True
) -> dict[str, Any]:
    """One training in a fresh process; its figures."""
    shutil.rmtree(run_dir, ignore_errors=True)
    command = [sys.executable, "-m", "mixnerf_eqx.train", "--no-progress"]
    if not cache:
        command.append("--no-compilation-cache")
    if config:
        command += ["--config", config]
    command += [f"train.seed={seed}", f'train.run_dir="{run_dir}"', *MODES[mode], *overrides]
    start = time.perf_counter()
    finished = subprocess.run(command, cwd=harness.REPO, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if finished.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{finished.stderr[-3000:]}")
    return figures(run_dir, seed, mode, wall)


def figures(run_dir: Path, seed: int, mode: str, wall: float | None) -> dict[str, Any]:
    """A finished run folder's figures; `wall` `None` for a run whose seconds are not compared
    (its median step time is then left out as well)."""
    for name in ("train_log.jsonl", "metrics.json", "config.json"):
        if not (run_dir / name).is_file():
            raise SystemExit(f"{run_dir} has no {name}: not a finished training run")
    log = [json.loads(line) for line in (run_dir / "train_log.jsonl").read_text().splitlines()]
    steps = [e for e in log if "psnr" in e]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    config = json.loads((run_dir / "config.json").read_text())
    if "psnr" not in (metrics.get("test") or {}):
        raise SystemExit(f"{run_dir}/metrics.json has no test PSNR: not a finished training run")
    trained = (config["train"]["seed"], bool(config.get("occupancy", {}).get("train_skipping", False)))
    if trained != (seed, mode == "skipping"):
        raise SystemExit(
            f"{run_dir} trained seed {trained[0]} with occupancy.train_skipping = {str(trained[1]).lower()}; "
            f"given as the {mode} run of seed {seed}"
        )
    dense = config["train"]["batch_size"] * (config["model"]["num_coarse_samples"] + config["model"]["num_fine_samples"])
    # Dense steps log no sample counts: every sample of every ray is evaluated.
    evaluations = [e.get("field_evaluations", dense) for e in steps]
    skipped_phase = [e for e in steps if e.get("field_evaluations", dense) < dense]
    return {
        "seed": seed,
        "mode": mode,
        "wall_s": wall,
        "median_step_s": (
            None if wall is None else statistics.median(1.0 / e["steps_per_s"] for e in steps if e["step"] > 20)
        ),
        "dense_evaluations_per_step": dense,
        "mean_evaluations_per_step": statistics.fmean(evaluations),
        "first_skipping_step": skipped_phase[0]["step"] if skipped_phase else None,
        "dropped_samples": sum(e.get("dropped_samples", 0.0) for e in steps),
        "val_psnr": (metrics.get("val") or {}).get("psnr"),
        "test_psnr": metrics["test"]["psnr"],
        "failure": metrics.get("failure"),
    }


def table(runs: list[dict[str, Any]]) -> str:
    lines = [
        "| seed | mode | field evaluations per step (mean) | median s per step | wall s | val PSNR | test PSNR |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        step = "not timed" if run["median_step_s"] is None else f"{run['median_step_s'] * 1000:.1f} ms"
        wall = "not timed" if run["wall_s"] is None else f"{run['wall_s']:.0f}"
        lines.append(
            f"| {run['seed']} | {run['mode']} | {run['mean_evaluations_per_step']:,.0f} | "
            f"{step} | {wall} | {run['val_psnr']:.2f} | {run['test_psnr']:.2f} |"
        )
    by = {(r["seed"], r["mode"]): r for r in runs}
    seeds = sorted({r["seed"] for r in runs if (r["seed"], "dense") in by and (r["seed"], "skipping") in by})
    lines += ["", "| paired over seeds | dense / skipping, or skipping - dense |", "|---|---|"]
    for key, label in (
        ("mean_evaluations_per_step", "field evaluations per step"),
        ("median_step_s", "median seconds per step"),
        ("wall_s", "wall time"),
    ):
        pairs = [(by[(s, "dense")][key], by[(s, "skipping")][key]) for s in seeds]
        cells = ["not timed" if None in pair else f"{pair[0] / pair[1]:.2f}x" for pair in pairs]
        lines.append(f"| {label} | " + " / ".join(cells) + " |")
    for split in ("val", "test"):
        key = f"{split}_psnr"
        found = paired_verdict(
            {s: by[(s, "skipping")][key] for s in seeds}, {s: by[(s, "dense")][key] for s in seeds}, True
        )
        lines.append(f"| {split} PSNR, skipping - dense | {verdict_cell(found)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None, help="packaged config or file (default: the quick start's)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--set", nargs="*", default=[], help="overrides for both modes")
    parser.add_argument("--skip-set", nargs="*", default=[], help="overrides for the skipping runs only")
    parser.add_argument("--runs-root", type=Path, default=harness.REPO / "runs" / "train_skipping")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--no-compilation-cache",
        action="store_true",
        help="every run compiles its programs (what a first run costs); default: the commands' cache",
    )
    parser.add_argument(
        "--existing",
        nargs=3,
        action="append",
        metavar=("SEED", "DENSE_DIR", "SKIPPING_DIR"),
        help="tabulate finished run folders instead of training (repeatable; not timed)",
    )
    args = parser.parse_args(argv)
    if args.existing:
        names = ("seeds", "config", "set", "skip_set", "runs_root")
        training_options = [
            f"--{name.replace('_', '-')}" for name in names if getattr(args, name) != parser.get_default(name)
        ]
        if args.no_compilation_cache:
            training_options.append("--no-compilation-cache")
        if training_options:
            parser.error(f"--existing trains nothing: drop {', '.join(training_options)}")
        if args.out is None:
            parser.error("--existing needs --out (the default file holds a timed comparison)")
        seeds = [entry[0] for entry in args.existing]
        if not all(seed.lstrip("-").isdigit() for seed in seeds) or len(set(seeds)) != len(seeds):
            parser.error(f"--existing takes one whole-number SEED per pair, each once; got {seeds}")
    out = args.out or harness.RESULTS / f"train_skipping_{harness.platform_tag()}"
    runs = []
    for seed, dense_dir, skipping_dir in args.existing or []:
        for mode, run_dir in (("dense", dense_dir), ("skipping", skipping_dir)):
            runs.append(figures(Path(run_dir), int(seed), mode, None))
    for seed in [] if args.existing else args.seeds:
        for mode in MODES:
            extra = [*args.set, *(args.skip_set if mode == "skipping" else [])]
            run_dir = args.runs_root / f"seed_{seed}_{mode}"
            run = train(args.config, seed, mode, run_dir, extra, cache=not args.no_compilation_cache)
            print(json.dumps(run), flush=True)
            runs.append(run)
    text = table(runs)
    print(text, end="")
    harness.write_json(out.with_suffix(".json"), {
            "config": args.config,
            "set": args.set,
            "skip_set": args.skip_set,
            "compilation_cache": not args.no_compilation_cache,
            "existing": args.existing,
            "runs": runs,
        })
    harness.write_markdown(out.with_suffix(".md"), text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
