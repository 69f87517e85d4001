"""Seconds per training step: MixNeRF, its mip-NeRF baseline, the shape checks on and off.

    python benchmarks/step_time.py   # seconds per step at the paper's batch, next to the bare MLP

Every variant is compiled first (compile time reported separately), then timed over
`--repeats` steps, each waited for; all variants run in one process, one after another,
so their ratios are comparable. The shape checks act while JAX traces: with them on only
compiling gets slower, and the compiled step should take the same time as with them off.
`bare-mlp` is the field's forward and backward over the same number of points (the
ceiling); each variant's throughput is printed as a fraction of it.

Takes `--config FILE` (default: the paper's settings, 4096 rays, 128 + 128 samples, 8 x 256
MLP), `section.key=value` overrides and `--out PATH` (default
`benchmarks/results/step_time_<backend>.json`). The JSON records the command and the machine
(`harness.write_json`); the table is printed as markdown.
"""

import argparse
import json
import statistics
import time
from typing import Any

import equinox as eqx
import harness
import jax

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, load_dataset

# Variants beyond the default: each is MixNeRF with these overrides (a "-nocheck" suffix turns
# the shape checks off). "colour-only" zeroes the depth and regenerated-colour NLL weights, so
# those terms are not computed: its step time shows what skipping zero-weight work saves.
STEP_VARIANTS = {
    "mixnerf": [],
    "mipnerf": ["method=mipnerf"],
    "mixnerf-colour-only": ["loss.lambda_depth=0.0", "loss.lambda_regen=0.0"],
    "mixnerf-bf16": ['mlp.matmul_dtype="bfloat16"'],
}


def step_variant(name: str) -> str:
    base = name.removesuffix("-nocheck")
    if base != "bare-mlp" and base not in STEP_VARIANTS:
        known = ", ".join(["bare-mlp", *STEP_VARIANTS])
        raise argparse.ArgumentTypeError(f"unknown variant {name!r} (known: {known}, each with -nocheck)")
    return name


def time_train_steps(config: mx.Config, dataset: Dataset, repeats: int, typecheck: bool) -> dict[str, Any]:
    """The library's step (`harness.TrainingRun`): compiled ahead of time, then `repeats` steps,
    each waited for."""
    with harness.typechecking(typecheck):
        run = harness.TrainingRun(config, dataset)
        compile_s = run.compile()
    times = [run.advance() for _ in range(repeats)]
    return {"compile_s": compile_s, "step_s": statistics.fmean(times), "step_s_each": times}


def time_bare_mlp(config: mx.Config, dataset: Dataset, repeats: int) -> dict[str, Any]:
    """Forward and backward of the field alone over one step's samples: the ceiling.

    The same number of points as a training step evaluates, with random inputs and the sum
    of every output as the loss, and nothing else: no sampling, compositing, mixture or
    optimiser. With `model.remat` the activations are recomputed as in the step.
    """
    model = mx.training.init_train_state(config, dataset).model
    means, covs, viewdirs, _ = harness.field_points(config, jax.random.key(2))
    started = time.perf_counter()
    forward_backward = eqx.filter_jit(eqx.filter_grad(harness.summed_field)).lower(
        model, means, covs, viewdirs
    )
    forward_backward = forward_backward.compile()
    compile_s = time.perf_counter() - started
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(forward_backward(model, means, covs, viewdirs))
        times.append(time.perf_counter() - started)
    return {"compile_s": compile_s, "step_s": statistics.fmean(times), "step_s_each": times}


def run(args: argparse.Namespace) -> None:
    """Times every variant and writes the result (see the module docstring)."""
    config = mx.load_config(args.config, args.overrides)
    dataset = load_dataset(config.data)
    rows = []
    for variant in args.variants:
        base = variant.removesuffix("-nocheck")
        variant_config = mx.load_config(args.config, [*args.overrides, *STEP_VARIANTS.get(base, [])])
        if base == "bare-mlp":
            timing = time_bare_mlp(variant_config, dataset, args.repeats)
        else:
            timing = time_train_steps(
                variant_config, dataset, args.repeats, typecheck=not variant.endswith("-nocheck")
            )
        rays = variant_config.train.batch_size
        samples = rays * (variant_config.model.num_coarse_samples + variant_config.model.num_fine_samples)
        row = {
            "variant": variant,
            **timing,
            "rays_per_s": rays / timing["step_s"],
            "samples_per_s": samples / timing["step_s"],
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    bare = next((row["step_s"] for row in rows if row["variant"] == "bare-mlp"), None)
    for row in rows:
        row["fraction_of_bare_mlp_throughput"] = None if bare is None else bare / row["step_s"]
    m = config.model
    print(f"\nbatch {config.train.batch_size} rays, {m.num_coarse_samples}+{m.num_fine_samples} samples,")
    print(f"MLP {m.depth}x{m.width}, remat {m.remat}; {jax.devices()}\n")
    harness.print_table(
        ("variant", "compile s", "step s", "rays/s", "samples/s", "fraction of the bare MLP's throughput"),
        [
            (
                row["variant"],
                row["compile_s"],
                row["step_s"],
                row["rays_per_s"],
                row["samples_per_s"],
                row["fraction_of_bare_mlp_throughput"],
            )
            for row in rows
        ],
    )
    if bare is not None:
        print("\n(target: a fraction of at least 0.80 on the GPU)")
    payload = {
        "config": args.config,
        "overrides": args.overrides,
        "repeats": args.repeats,
        "model": harness.model_summary(config),
        "rows": rows,
    }
    harness.write_json(harness.default_out(args.out, "step_time"), payload)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    harness.add_common(parser, None, "step_time")
    parser.add_argument("--repeats", type=int, default=2, help="timed steps per variant (default 2)")
    parser.add_argument(
        "--variants",
        nargs="+",
        type=step_variant,
        default=["bare-mlp", "mixnerf", "mipnerf", "mixnerf-nocheck"],
        help="bare-mlp, mixnerf, mipnerf, mixnerf-colour-only, mixnerf-bf16; '-nocheck': shape checks off",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    run(parse_args(argv))


if __name__ == "__main__":
    main()
