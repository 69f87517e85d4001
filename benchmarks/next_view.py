"""Which view to capture next: MixNeRF's predictive spread against random and farthest choices.

FisherRF's protocol on the built-in scene: start from the quick start's 4 training views,
add 1, 2 and 3 views one at a time, each chosen from a pool of candidate cameras, retrain
from scratch after each addition with the same budget (the quick start's config and steps),
and score the final model on the validation views (which choose between the two spreads) and
the test views (the record). Strategies, per seed:

- `depth` and `colour`: the candidate where the current model's mean predictive spread is
  largest (`mx.next_view`, 48 pixels across), the termination distance's or the colour's;
- `farthest`: the candidate whose camera centre is farthest from every training camera's;
- `random`: a uniformly random candidate (drawn by the seed).

The pool: 16 cameras on the built-in scene's orbit, azimuths every 22.5 degrees at
alternating elevations of 12 and 55 degrees (`mixnerf_eqx.data.procedural.builtin_views_at`),
none of them a test or validation camera. A set of training views met before (two strategies
choosing alike) is trained once.

    python benchmarks/next_view.py --seeds 0 1 2

Results: `results/next_view_cpu.json` and `results/next_view_cpu.md`.
"""

import argparse
import dataclasses
import tempfile
import time
from typing import Any

import numpy as np
from harness import RESULTS, machine_info, platform_tag, write_json, write_markdown

import mixnerf_eqx as mx
from fidelity import paired_from_diffs
from mixnerf_eqx.data import Views, builtin_views_at, load_dataset

STRATEGIES = ("depth", "colour", "farthest", "random")
BUDGETS = (1, 2, 3)


def candidate_pool(resolution: int) -> Views:
    azimuths = np.arange(16) * 22.5
    elevations = np.where(np.arange(16) % 2 == 0, 12.0, 55.0)
    return builtin_views_at(azimuths, elevations, resolution=resolution, first_id=100)


def joined(base: Views, pool: Views, picks: list[int]) -> Views:
    if not picks:
        return base
    extra = pool.select(picks)
    return dataclasses.replace(
        base,
        images=np.concatenate([base.images, extra.images]),
        camtoworlds=np.concatenate([base.camtoworlds, extra.camtoworlds]),
        depths=np.concatenate([base.depths, extra.depths]),
        ids=(*base.ids, *extra.ids),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--config", default="builtin_grid")
    parser.add_argument("--steps", type=int, default=0, help="training steps (0: the config's)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()
    runs: dict[str, Any] = {}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        for seed in args.seeds:
            overrides = [f"train.seed={seed}", "train.eval_every=0", f"train.run_dir={work}/run"]
            if args.steps:
                overrides.append(f"train.max_steps={args.steps}")
            config = mx.load_config(args.config, overrides)
            dataset = load_dataset(config.data)
            pool = candidate_pool(dataset.train.width)
            trained: dict[tuple[int, ...], dict[str, Any]] = {}

            def train(picks: list[int]) -> dict[str, Any]:
                key = tuple(sorted(picks))
                if key not in trained:
                    scene = dataclasses.replace(dataset, train=joined(dataset.train, pool, list(key)))
                    result = mx.fit(
                        dataclasses.replace(
                            config, train=dataclasses.replace(config.train, run_dir=f"{work}/run_{seed}_{len(trained)}")
                        ),
                        dataset=scene,
                        progress=False,
                        write_renders=False,
                    )
                    val = mx.evaluate(result.model, scene, with_lpips=False, split="val").means
                    test = mx.evaluate(result.model, scene, with_lpips=False, split="test").means
                    trained[key] = {"model": result.model, "val_psnr": val["psnr"], "test_psnr": test["psnr"]}
                    print(
                        f"seed {seed} views +{list(key)}: val {val['psnr']:.2f} test {test['psnr']:.2f} "
                        f"({time.perf_counter() - started:.0f} s)",
                        flush=True,
                    )
                return trained[key]

            base = train([])
            rng = np.random.default_rng(seed)
            random_order = [int(i) for i in rng.permutation(pool.num_views)]
            farthest_order = []
            for _ in BUDGETS:
                chosen = joined(dataset.train, pool, farthest_order)
                left = [i for i in range(pool.num_views) if i not in farthest_order]
                order = mx.uncertainty.farthest_first(pool.camtoworlds[left], chosen.camtoworlds)
                farthest_order.append(left[int(order[0])])
            seed_runs = {"base": {k: v for k, v in base.items() if k != "model"}}
            for strategy in STRATEGIES:
                picks: list[int] = []
                curve = []
                for budget in BUDGETS:
                    if strategy == "random":
                        picks = random_order[:budget]
                    elif strategy == "farthest":
                        picks = farthest_order[:budget]
                    else:
                        model = train(picks)["model"]
                        left = [i for i in range(pool.num_views) if i not in picks]
                        ranking = mx.next_view(
                            model, dataset.train, pool.camtoworlds[left], dataset.near, dataset.far, score=strategy
                        )
                        picks = [*picks, left[int(ranking.order[0])]]
                    found = train(picks)
                    curve.append({"budget": budget, "picks": list(picks), "val_psnr": found["val_psnr"], "test_psnr": found["test_psnr"]})
                seed_runs[strategy] = curve
            runs[str(seed)] = seed_runs
    write_results(runs, args, time.perf_counter() - started)


def write_results(runs: dict[str, Any], args: argparse.Namespace, seconds: float) -> None:
    seeds = sorted(runs, key=int)
    lines = [
        "| added views | strategy | val PSNR (mean over seeds) | test PSNR (mean) | test - random | test - farthest |",
        "|---|---|---|---|---|---|",
    ]
    verdicts: dict[str, Any] = {}
    base_val = np.mean([runs[s]["base"]["val_psnr"] for s in seeds])
    base_test = np.mean([runs[s]["base"]["test_psnr"] for s in seeds])
    lines.append(f"| 0 | (the 4 views) | {base_val:.2f} | {base_test:.2f} | | |")
    for index, budget in enumerate(BUDGETS):
        for strategy in STRATEGIES:
            values = {split: [runs[s][strategy][index][f"{split}_psnr"] for s in seeds] for split in ("val", "test")}
            cells = []
            for other in ("random", "farthest"):
                if other == strategy:
                    cells.append("")
                    continue
                diffs = [runs[s][strategy][index]["test_psnr"] - runs[s][other][index]["test_psnr"] for s in seeds]
                found = paired_from_diffs([int(s) for s in seeds], diffs, True)
                verdicts[f"{budget}/{strategy}-{other}/test"] = found
                val_diffs = [runs[s][strategy][index]["val_psnr"] - runs[s][other][index]["val_psnr"] for s in seeds]
                verdicts[f"{budget}/{strategy}-{other}/val"] = paired_from_diffs([int(s) for s in seeds], val_diffs, True)
                half = found["half_width_95"]
                spread = "" if np.isnan(half) else f" ± {half:.2f}"
                cells.append(f"{found['mean']:+.2f}{spread}: {found['verdict']}")
            lines.append(
                f"| {budget} | {strategy} | {np.mean(values['val']):.2f} | {np.mean(values['test']):.2f} | "
                + " | ".join(cells)
                + " |"
            )
    stem = f"next_view_{platform_tag()}{'_' + args.tag if args.tag else ''}"
    write_json(RESULTS / f"{stem}.json", {"seeds": seeds, "runs": runs, "verdicts": verdicts, "seconds": seconds})
    text = (
        f"Built-in scene, {args.config}, seeds {', '.join(seeds)}; paired differences with Student-t 95% "
        "intervals over the seeds.\n\n" + "\n".join(lines) + f"\n\nMachine: {machine_info()['platform']}, "
        f"{machine_info()['cpu_count']} CPUs; {seconds / 60:.0f} minutes.\n"
    )
    write_markdown(RESULTS / f"{stem}.md", text)
    print(text)


if __name__ == "__main__":
    main()
