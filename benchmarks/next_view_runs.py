"""Which view to capture next on a real scene: trained runs, continued with the views each
strategy adds.

FisherRF's protocol, with continued training in place of retraining (a fern run takes about
40 minutes on 2 cores; the protocol allows either, with the same budget for every choice):
from each trained run, add 1, 2 and 3 views one at a time, each chosen from the candidates by
the current model, and after each addition continue training for `--steps` steps (past the
run's decay horizon, so at its final learning rate: `optim.decay_steps`); score the test views
after each addition. Strategies, per run:

- `depth`: the candidate with the largest opacity-weighted spread of the termination distance
  under the current model (`mx.next_view`, the command's default, fixed in advance);
- `farthest`: the candidate whose camera centre is farthest from every training camera's;
- `random`: uniformly random candidates (drawn by the run's seed);
- `none`: no view added, the same steps after the first addition (what the continued training
  alone gives; the control, at one addition only).

Candidates: the scene's images that are neither training, validation nor test views (nor left
out for lying near a test view): the validation views of the split with every leftover image
(`data.max_val_views=0`) less the run's own. The test views are never candidates. Validation
views are not scored (nothing is chosen here), to keep the run short.

    python benchmarks/next_view_runs.py runs/fern_pp/seed_2 runs/fern_pp/seed_3 runs/fern_pp/seed_4 \\
        --data-dir ../shared/data --steps 1000 --out benchmarks/results/next_view_cpu_fern

Results: `--out` with `.json` and `.md`.
"""

import argparse
import contextlib
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from fidelity import paired_from_diffs
from harness import machine_info, write_json, write_markdown

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, Views, load_dataset

STRATEGIES = ("depth", "farthest", "random", "none")
BUDGETS = (1, 2, 3)


def joined(base: Views, extra: Views) -> Views:
    """`base` followed by `extra`, with every per-view array."""

    def cat(a, b):
        return None if a is None else np.concatenate([a, b])

    return dataclasses.replace(
        base,
        images=cat(base.images, extra.images),
        camtoworlds=cat(base.camtoworlds, extra.camtoworlds),
        depths=cat(base.depths, extra.depths),
        intrinsics=cat(base.intrinsics, extra.intrinsics),
        masks=cat(base.masks, extra.masks),
        ids=(*base.ids, *extra.ids),
    )


def candidates_of(run: mx.runs.Run) -> Views:
    """The run's scene's images that are no training, validation or test view of it."""
    wide = load_dataset(dataclasses.replace(run.config.data, max_val_views=0))
    if wide.val is None:
        raise SystemExit(f"{run.dataset.name}: no image is left over for candidates")
    taken = set(run.dataset.train.ids) | set(run.dataset.test.ids)
    taken |= set() if run.dataset.val is None else set(run.dataset.val.ids)
    keep = [index for index, view in enumerate(wide.val.ids) if view not in taken]
    return wide.val.select(keep)


class Continuations:
    """Continued runs of one trained run, each kept once per sequence of added views."""

    def __init__(self, run: mx.runs.Run, run_dir: Path, pool: Views, steps: int, work: Path, started: float):
        self.run, self.pool, self.steps, self.work, self.started = run, pool, steps, work, started
        self.done: dict[tuple[int, ...], dict[str, Any]] = {(): {"dir": run_dir, "model": run.model}}

    def scene(self, picks: tuple[int, ...]) -> Dataset:
        train = self.run.dataset.train
        if any(pick >= 0 for pick in picks):
            train = joined(train, self.pool.select([pick for pick in picks if pick >= 0]))
        # No validation views: nothing is chosen on them here, and each costs a render.
        return dataclasses.replace(self.run.dataset, train=train, val=None)

    def after(self, picks: tuple[int, ...]) -> dict[str, Any]:
        """The run continued `steps` steps after each addition in `picks` (-1: none added)."""
        if picks in self.done:
            return self.done[picks]
        parent = self.after(picks[:-1])
        child = self.work / f"run_{len(self.done)}"
        source = mx.runs.latest_checkpoint(parent["dir"])
        shutil.copytree(source, child / "checkpoints" / source.name)
        meta_path = child / "checkpoints" / source.name / "meta.json"
        meta = json.loads(meta_path.read_text())
        if "scene_box" not in meta:
            # A run trained before checkpoints recorded the box its grid spans: its own training
            # rays' box, which a continuation on more views must keep (`init_train_state`).
            meta["scene_box"] = [list(corner) for corner in mx.training.scene_box(self.run.dataset)]
            meta_path.write_text(json.dumps(meta, indent=2))
        start = int(meta["step"])
        config = self.run.config
        config = dataclasses.replace(
            config,
            train=dataclasses.replace(
                config.train, max_steps=start + self.steps, run_dir=str(child), eval_every=0
            ),
        )
        result = mx.fit(config, dataset=self.scene(picks), progress=False, write_renders=False)
        test = result.metrics["test"]
        found = {
            "dir": child,
            "model": result.model,
            "test": {k: float(test[k]) for k in ("psnr", "ssim", "lpips")},
        }
        self.done[picks] = found
        print(
            f"  views +{[self.pool.ids[p] for p in picks if p >= 0]} ({len(picks)} additions): "
            f"test PSNR {found['test']['psnr']:.2f} ({time.perf_counter() - self.started:.0f} s)",
            flush=True,
        )
        return found


def strategy_curve(strategy: str, runs: Continuations, seed: int, budgets: list[int]) -> list[dict[str, Any]]:
    """The test metrics after each addition under one strategy."""
    pool, train = runs.pool, runs.run.dataset.train
    order = [int(i) for i in np.random.default_rng(seed).permutation(pool.num_views)]
    picks: tuple[int, ...] = ()
    curve: list[dict[str, Any]] = []
    for _ in budgets[: 1 if strategy == "none" else None]:
        left = [i for i in range(pool.num_views) if i not in picks]
        if strategy == "none":
            pick = -1
        elif strategy == "random":
            pick = order[len(picks)]
        elif strategy == "farthest":
            chosen = joined(train, pool.select([p for p in picks]))
            pick = left[int(mx.uncertainty.farthest_first(pool.camtoworlds[left], chosen.camtoworlds)[0])]
        else:
            ranking = mx.next_view(
                runs.after(picks)["model"],
                train,
                pool.camtoworlds[left],
                runs.run.dataset.near,
                runs.run.dataset.far,
                score=strategy,
            )
            pick = left[int(ranking.order[0])]
        picks = (*picks, pick)
        found = runs.after(picks)
        curve.append({"views": [pool.ids[p] for p in picks if p >= 0], **found["test"]})
    return curve


def table(results: dict[str, Any], budgets: list[int]) -> str:
    names = list(results)
    lines = [
        "| added views | strategy | test PSNR (mean over runs) | SSIM | LPIPS "
        "| PSNR - random | PSNR - farthest | PSNR - none |",
        "|---|---|---|---|---|---|---|---|",
    ]
    base = [results[n]["base"] for n in names]
    lines.append(
        f"| 0 | (the run as trained) | {np.mean([b['psnr'] for b in base]):.2f} | "
        f"{np.mean([b['ssim'] for b in base]):.3f} | {np.mean([b['lpips'] for b in base]):.3f} | | | |"
    )
    for index, budget in enumerate(budgets):
        for strategy in STRATEGIES:
            if index >= len(results[names[0]]["curves"][strategy]):
                continue
            rows = [results[n]["curves"][strategy][index] for n in names]
            cells = []
            for other in ("random", "farthest", "none"):
                # The control is at one added view only, and is compared with, not against.
                missing = index >= len(results[names[0]]["curves"][other])
                if other == strategy or strategy == "none" or missing:
                    cells.append("")
                    continue
                diffs = [
                    results[n]["curves"][strategy][index]["psnr"] - results[n]["curves"][other][index]["psnr"]
                    for n in names
                ]
                found = paired_from_diffs(list(range(len(names))), diffs, True)
                half = found["half_width_95"]
                cells.append(
                    f"{found['mean']:+.2f}{'' if np.isnan(half) else f' ± {half:.2f}'}: {found['verdict']}"
                )
            lines.append(
                f"| {budget} | {strategy} | {np.mean([r['psnr'] for r in rows]):.2f} | "
                f"{np.mean([r['ssim'] for r in rows]):.3f} | {np.mean([r['lpips'] for r in rows]):.3f} | "
                + " | ".join(cells)
                + " |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", help="trained run folders (one per seed); with --merge, results")
    parser.add_argument(
        "--merge", action="store_true", help="join this command's .json results (one process per run)"
    )
    parser.add_argument("--data-dir", default=None, help="the dataset root, replacing the runs'")
    parser.add_argument("--steps", type=int, default=1000, help="training steps after each addition")
    parser.add_argument("--budgets", type=int, nargs="+", default=list(BUDGETS), help="views added, in turn")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args()
    if args.budgets != list(range(1, len(args.budgets) + 1)):
        raise SystemExit(f"--budgets counts the views added one at a time: 1 2 ..., got {args.budgets}")
    started = time.perf_counter()
    results: dict[str, Any] = {}
    if args.merge:
        parts = [json.loads(Path(path).read_text()) for path in args.runs]
        if len({(part["steps"], tuple(part["budgets"])) for part in parts}) != 1:
            raise SystemExit("the results were made with different --steps or --budgets")
        args.steps, args.budgets = parts[0]["steps"], parts[0]["budgets"]
        names = [name for part in parts for name in part["runs"]]
        if len(set(names)) != len(names):
            raise SystemExit(f"a run appears in more than one of the results: {names}")
        results = {name: found for part in parts for name, found in part["runs"].items()}
    with contextlib.nullcontext() if args.merge else tempfile.TemporaryDirectory() as scratch:
        # Each continuation compiles the same programs again (a new `fit`): load them from disk.
        if scratch is not None:
            mx.runtime.enable_compilation_cache(Path(scratch) / "compiled")
        for number, run_dir in enumerate([] if args.merge else args.runs):
            run = mx.runs.restore_run(run_dir, data_dir=args.data_dir)
            pool = candidates_of(run)
            if pool.num_views < max(args.budgets):
                raise SystemExit(f"{run_dir}: {pool.num_views} candidates, fewer than {max(args.budgets)}")
            seed = run.config.train.seed
            print(f"{run_dir} (seed {seed}): candidates {list(pool.ids)}", flush=True)
            base = mx.evaluate(run.model, run.dataset, split="test").means
            work = Path(scratch) / str(number)
            work.mkdir()
            runs = Continuations(run, Path(run_dir), pool, args.steps, work, started)
            curves = {strategy: strategy_curve(strategy, runs, seed, args.budgets) for strategy in STRATEGIES}
            results[run_dir] = {
                "seed": seed,
                "candidates": list(pool.ids),
                "train_views": list(run.dataset.train.ids),
                "base": {k: float(base[k]) for k in ("psnr", "ssim", "lpips")},
                "curves": curves,
                "continued_runs": len(runs.done) - 1,
            }
            for strategy, curve in curves.items():
                print(
                    f"  {strategy}: " + ", ".join(f"{c['views']} {c['psnr']:.2f}" for c in curve), flush=True
                )
    # Joined results: the processes' seconds added up (they may have run side by side).
    seconds = time.perf_counter() - started + (sum(part["seconds"] for part in parts) if args.merge else 0.0)
    info = machine_info()
    text = (
        f"{len(results)} runs ({', '.join(results)}), {args.steps} steps after each addition; paired "
        "differences over the runs with Student-t 95% intervals.\n\n"
        + table(results, args.budgets)
        + f"\n\nMachine: {info['platform']}, {info['cpu_count']} CPUs; {seconds / 60:.0f} process-minutes.\n"
    )
    out = Path(args.out)
    write_json(
        out.with_suffix(".json"),
        {"steps": args.steps, "budgets": args.budgets, "runs": results, "seconds": seconds},
    )
    write_markdown(out.with_suffix(".md"), text)
    print(text)


if __name__ == "__main__":
    main()
