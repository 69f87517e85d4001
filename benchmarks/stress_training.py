"""Stress training runs on the built-in scene: does anything become non-finite?

    python benchmarks/stress_training.py [--steps 1000]

Two runs of the quick-start model: (1) two training views with a learning rate 10x the
quick start's and no warm-up; (2) the far bound moved from 6 to 30, so most of every ray is
empty space behind the scene. Prints, per run: skipped (non-finite) steps, whether every
logged loss term, every parameter and every rendered pixel, depth and opacity is finite, and
the held-out PSNR.
"""

import argparse
import dataclasses
import json
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from mixnerf_eqx import load_config
from mixnerf_eqx._train import fit, render_views
from mixnerf_eqx.data import load_dataset

RUNS = {
    "aggressive_lr_2_views": (
        ["data.num_train_views=2", "optim.lr_init=2e-2", "optim.lr_final=2e-3", "optim.warmup_steps=0"],
        None,
    ),
    "far_bound_30": ([], 30.0),
}


def stress_run(name: str, overrides: list[str], far: float | None, steps: int, runs_root: str) -> dict:
    config = load_config(
        "configs/builtin.toml",
        [*overrides, f"train.max_steps={steps}", f'train.run_dir="{runs_root}/{name}"', "train.eval_every=0"],
    )
    dataset = load_dataset(config.data)
    if far is not None:
        dataset = dataclasses.replace(dataset, far=far)
    result = fit(config, dataset=dataset, progress=False, write_renders=False, log_every=1)
    params = jax.tree_util.tree_leaves(eqx.filter(result.model, eqx.is_array))
    rgb, depth, acc = render_views(result.model, dataset.test, dataset.near, dataset.far)
    history_finite = all(np.isfinite(v) for entry in result.history for k, v in entry.items() if k != "step")
    return {
        "run": name,
        "steps": steps,
        "skipped_steps": result.metrics["skipped_steps"],
        "losses_finite": bool(history_finite),
        "params_finite": bool(all(np.all(np.isfinite(np.asarray(p))) for p in params)),
        "renders_finite": bool(
            np.all(np.isfinite(rgb)) and np.all(np.isfinite(depth)) and np.all(np.isfinite(acc))
        ),
        "test_psnr": result.metrics["test"]["psnr"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--runs-root", default="runs/stress")
    parser.add_argument("--out", default="benchmarks/results/stress_training_cpu.json")
    args = parser.parse_args()
    rows = [stress_run(name, o, far, args.steps, args.runs_root) for name, (o, far) in RUNS.items()]
    for row in rows:
        print(json.dumps(row))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
