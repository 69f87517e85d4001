"""What a training step that skips costs, by buffer size: the dense step against the skipping
step at each rung of buffer shares, in one process.

    python benchmarks/skipping_step.py                                  # the quick start's config
    python benchmarks/skipping_step.py --config configs/blender4.toml   # the paper's model

The occupancy grid is filled as occupied everywhere (every cell evaluated, density far above
the threshold), so every sample is live and the buffers are full: each row is the cost of a
step that evaluates that share of the samples (the share a scene reaches is in its training
log, `field_evaluations`; `benchmarks/train_skipping.py` trains with it). Each step is
compiled first, then timed `--repeats` times, each call waited for; the fastest and the median
are reported with the dense step's median divided by the row's.

Takes `--config` (default: the quick start's), `section.key=value` overrides, `--shares`
(buffer shares, each used for both levels) and `--out` (default
`benchmarks/results/skipping_step_<backend>.json`).
"""

import argparse
import dataclasses
import statistics
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import harness
import jax
import jax.numpy as jnp

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset


def timed(step, state, batch, repeats: int) -> dict[str, Any]:
    started = time.perf_counter()
    jax.block_until_ready(step(state, batch))
    first = time.perf_counter() - started
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(step(state, batch))
        times.append(time.perf_counter() - started)
    return {"first_call_s": first, "min_s": min(times), "median_s": statistics.median(times)}


def run(args: argparse.Namespace) -> dict[str, Any]:
    overrides = [*args.overrides, "occupancy.enabled=true", "occupancy.train_skipping=true"]
    config = mx.load_config(args.config, overrides)
    dataset = load_dataset(config.data)
    state = mx.training.init_train_state(config, dataset)
    # Every cell evaluated and far above the threshold: an update keeps it so, and sets the
    # cells the skipping step reads.
    state = eqx.tree_at(lambda s: s.grid.density, state, jnp.full_like(state.grid.density, 1e6))
    state = mx.training.update_grid(state, config.occupancy)
    assert state.cells is not None
    data = mx.training.training_rays(dataset, config.loss)
    batch = eqx.filter_jit(mx.training.draw_batch)(data, state, config.train.batch_size)
    dense_config = dataclasses.replace(config, occupancy=dataclasses.replace(config.occupancy, train_skipping=False))
    rows = [{"share": 1.0, "mode": "dense", **timed(mx.training.make_train_step(dense_config), dataclasses.replace(state, cells=None), batch, args.repeats)}]
    for share in args.shares:
        step = mx.training.make_train_step(config, budget=(share, share))
        rows.append({"share": share, "mode": "skipping", **timed(step, state, batch, args.repeats)})
        print(f"share {share:.3f}: {rows[-1]['median_s'] * 1000:.1f} ms", flush=True)
    dense = rows[0]["median_s"]
    for row in rows:
        row["speed_up"] = dense / row["median_s"]
    samples = config.train.batch_size * (config.model.num_coarse_samples + config.model.num_fine_samples)
    return {"config": args.config, "overrides": args.overrides, "samples_per_step": samples, "rows": rows}


def table(result: dict[str, Any]) -> str:
    lines = [
        "| step | buffer share (each level) | field evaluations | ms (min) | ms (median) | dense / this | first call s |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        evaluations = round(row["share"] * result["samples_per_step"])
        lines.append(
            f"| {row['mode']} | {row['share']:.3f} | {evaluations:,} | {row['min_s'] * 1000:.1f} | "
            f"{row['median_s'] * 1000:.1f} | {row['speed_up']:.2f}x | {row['first_call_s']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="builtin_grid", help="packaged config or file (default: builtin_grid)")
    parser.add_argument("overrides", nargs="*", help="section.key=value")
    parser.add_argument("--shares", nargs="+", type=float, default=[1.0, 2**-0.5, 0.5, 2**-1.5, 0.25])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default=None)
    args = parser.parse_intermixed_args(argv)
    result = run(args)
    text = table(result)
    print(text, end="")
    out = harness.RESULTS / f"skipping_step_{harness.platform_tag()}.json" if args.out is None else args.out
    harness.write_json(Path(out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
