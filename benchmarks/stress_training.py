"""Stress training runs on the built-in scene: does anything become non-finite?

    python benchmarks/stress_training.py [--steps 1000] [section.key=value ...]

Two runs of the quick-start model (`configs/builtin.toml`, or `--config`) with `mx.fit`:
(1) two training views with a learning rate 10x the quick start's and no warm-up; (2) the far
bound moved from 6 to 30, so most of every ray is empty space behind the scene. Prints, per
run: skipped (non-finite) steps, whether every logged loss term, every parameter and every
rendered pixel, depth and opacity is finite, and the held-out PSNR; writes them as JSON
(`benchmarks/results/stress_training_<backend>.json` unless `--out` says otherwise).
"""

import argparse
import dataclasses
import json
from pathlib import Path

import equinox as eqx
import harness
import jax
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset

RUNS = {  # name: (overrides, far bound or None for the scene's)
    "aggressive_lr_2_views": (
        ["data.num_train_views=2", "optim.lr_init=2e-2", "optim.lr_final=2e-3", "optim.warmup_steps=0"],
        None,
    ),
    "far_bound_30": ([], 30.0),
}


def stress_run(args: argparse.Namespace, name: str, overrides: list[str], far: float | None) -> dict:
    run_dir = Path(args.runs_root) / name
    config = mx.load_config(
        args.config,
        [
            *args.overrides,
            *overrides,
            f"train.max_steps={args.steps}",
            f"train.run_dir={json.dumps(str(run_dir))}",
            "train.eval_every=0",
        ],
    )
    dataset = load_dataset(config.data)
    if far is not None:
        dataset = dataclasses.replace(dataset, far=far)
    result = mx.fit(config, dataset=dataset, progress=False, write_renders=False, log_every=1)
    params = jax.tree_util.tree_leaves(eqx.filter(result.model, eqx.is_array))
    rendered = mx.render_views(
        result.model, dataset.test, dataset.near, dataset.far, config.train.render_chunk
    )
    losses_finite = all(np.isfinite(v) for entry in result.history for k, v in entry.items() if k != "step")
    return {
        "run": name,
        "steps": args.steps,
        "far": dataset.far,
        "skipped_steps": result.metrics["skipped_steps"],
        "losses_finite": bool(losses_finite),
        "params_finite": bool(all(np.all(np.isfinite(np.asarray(p))) for p in params)),
        "renders_finite": bool(
            np.all(np.isfinite(rendered.rgb))
            and np.all(np.isfinite(rendered.depth))
            and np.all(np.isfinite(rendered.acc))
        ),
        "test_psnr": result.metrics["test"]["psnr"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="configs/builtin.toml")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--runs", nargs="+", default=list(RUNS), choices=list(RUNS))
    parser.add_argument("--runs-root", default="runs/stress")
    parser.add_argument(
        "--out", default=None, help="JSON path (default: results/stress_training_<backend>.json)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides for every run, section.key=value")
    args = parser.parse_args()
    rows = []
    for name in args.runs:
        overrides, far = RUNS[name]
        rows.append(stress_run(args, name, overrides, far))
        print(json.dumps(rows[-1]), flush=True)
    print()
    harness.print_table(
        (
            "run",
            "steps",
            "skipped steps",
            "losses finite",
            "parameters finite",
            "renders finite",
            "test PSNR",
        ),
        [
            (
                row["run"],
                row["steps"],
                row["skipped_steps"],
                row["losses_finite"],
                row["params_finite"],
                row["renders_finite"],
                row["test_psnr"],
            )
            for row in rows
        ],
    )
    out = Path(args.out) if args.out else harness.RESULTS / f"stress_training_{harness.platform_tag()}.json"
    harness.write_json(out, {"config": args.config, "overrides": args.overrides, "rows": rows})


if __name__ == "__main__":
    main()
