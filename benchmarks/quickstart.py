"""The README's first command, `python -m mixnerf_eqx.train --no-progress`, timed end to end
(install excluded) in this working tree and at each `--against` git revision, seed by seed.

Every run is a fresh process with a fresh run folder under `--runs-root`, one after another
in the order working tree, revisions, for each seed in turn, so that the machine's state
drifts alike for all; with `--repeat-cached` each tree runs the first seed once more with
the compilation cache its first run filled (`JAX_COMPILATION_CACHE_DIR`); other runs have
no cache. The table gives wall time, the
median step time (from `train_log.jsonl`, steps after the 20th), the step-time ratio to the
first revision, and the test metrics; `section.key=value` overrides apply to every run.

    python benchmarks/quickstart.py --against e53e00d --seeds 0 1 2

Output: `--out`, default `benchmarks/results/quickstart_<backend>.json`, with the command that
made it and the machine (`harness.write_json`); the table is printed as markdown.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import harness
import jax

QUICKSTART_COMMAND = ("-m", "mixnerf_eqx.train", "--no-progress")


def quickstart_trees(revisions: list[str], scratch: Path) -> list[tuple[str, Path]]:
    """`(label, source tree)` for this working tree and each git revision, checked out into
    `scratch` with `git worktree` (removed again by `remove_trees`)."""
    repo = harness.REPO
    trees = [("working tree", repo)]
    for revision in revisions:
        commit = subprocess.run(
            ["git", "-C", str(repo), "rev-parse", "--short", revision],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        tree = scratch / f"tree-{commit}"
        if not tree.exists():
            subprocess.run(
                ["git", "-C", str(repo), "worktree", "add", "--detach", str(tree), commit],
                capture_output=True,
                check=True,
            )
        trees.append((commit, tree))
    return trees


def remove_trees(trees: list[tuple[str, Path]]) -> None:
    repo = harness.REPO
    for _, tree in trees[1:]:
        subprocess.run(["git", "-C", str(repo), "worktree", "remove", "--force", str(tree)], check=False)


def time_quickstart(
    tree: Path, run_dir: Path, overrides: list[str], cache_dir: Path | None
) -> dict[str, Any]:
    """`python -m mixnerf_eqx.train --no-progress` on `tree`'s package (its own configs), in a
    fresh process and run folder: wall time, step rate from the run's log, test metrics."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    # No cache unless one is given (the commands otherwise use one of their own).
    env["MIXNERF_COMPILATION_CACHE"] = "off"
    if cache_dir is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = str(cache_dir)
    command = [sys.executable, *QUICKSTART_COMMAND, f"train.run_dir={json.dumps(str(run_dir))}", *overrides]
    started = time.perf_counter()
    finished = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    wall_s = time.perf_counter() - started
    if finished.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed in {tree}:\n{finished.stderr[-3000:]}")
    entries = [json.loads(line) for line in (run_dir / "train_log.jsonl").read_text().splitlines()]
    # Steps per second logged every 10 steps; the first entries include compilation.
    rates = [e["steps_per_s"] for e in entries if "steps_per_s" in e and e["step"] > 20]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    return {
        "wall_s": wall_s,
        "steps": metrics["step"],
        "median_step_s": 1.0 / statistics.median(rates) if rates else None,
        **{key: metrics["test"].get(key) for key in ("psnr", "ssim", "lpips", "depth_mae")},
    }


def run(args: argparse.Namespace) -> None:
    """Runs the quick start in every tree, seed by seed, and writes the result (see the module
    docstring)."""
    scratch = Path(tempfile.mkdtemp(prefix="quickstart-"))
    runs_root = Path(args.runs_root) if args.runs_root else scratch / "runs"
    trees = quickstart_trees(args.against, scratch)
    rows = []
    try:
        for seed in args.seeds:
            for label, tree in trees:
                tag = label.replace(" ", "-")
                cache = scratch / f"cache-{tag}"
                cached = args.repeat_cached and seed == args.seeds[0]
                passes = [("cold", None)] + ([("cached", cache)] if cached else [])
                for cache_label, cache_dir in passes:
                    if cache_label == "cold" and cached:
                        cache_dir = cache  # the cold run fills the cache the second one reads
                        shutil.rmtree(cache, ignore_errors=True)
                    run_dir = runs_root / f"{tag}-seed{seed}-{cache_label}"
                    shutil.rmtree(run_dir, ignore_errors=True)
                    overrides = [*args.overrides, f"train.seed={seed}"]
                    row = {"tree": label, "seed": seed, "cache": cache_label}
                    row.update(time_quickstart(tree, run_dir, overrides, cache_dir))
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    finally:
        remove_trees(trees)
    reference = {
        (row["seed"], row["cache"]): row["median_step_s"] for row in rows if row["tree"] == trees[-1][0]
    }
    for row in rows:
        base = reference.get((row["seed"], row["cache"]))
        row["step_speedup_vs_last_revision"] = (
            base / row["median_step_s"] if base and row["median_step_s"] else None
        )
    print(f"\n{jax.devices()}; revisions against: {', '.join(label for label, _ in trees[1:]) or 'none'}\n")
    harness.print_table(
        (
            "tree",
            "seed",
            "cache",
            "wall s",
            "steps",
            "step ms",
            "step speed-up",
            "PSNR",
            "SSIM",
            "LPIPS",
            "depth MAE",
        ),
        [
            (
                row["tree"],
                row["seed"],
                row["cache"],
                row["wall_s"],
                row["steps"],
                None if row["median_step_s"] is None else 1e3 * row["median_step_s"],
                row["step_speedup_vs_last_revision"],
                row["psnr"],
                row["ssim"],
                row["lpips"],
                row["depth_mae"],
            )
            for row in rows
        ],
    )
    payload = {"against": args.against, "seeds": args.seeds, "overrides": args.overrides, "rows": rows}
    harness.write_json(harness.default_out(args.out, "quickstart"), payload)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--against", nargs="*", default=[], help="git revisions to time alongside")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="train.seed of each run")
    parser.add_argument("--repeat-cached", action="store_true", help="also run with a filled compile cache")
    parser.add_argument("--runs-root", default=None, help="run folders (default: a temporary folder)")
    parser.add_argument("--out", default=None, help="JSON path (default: results/quickstart_<backend>.json)")
    parser.add_argument("overrides", nargs="*", help="config overrides for every run, section.key=value")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    run(parse_args(argv))


if __name__ == "__main__":
    main()
