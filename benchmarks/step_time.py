"""Seconds per training step, MixNeRF against its mip-NeRF baseline, type checks on and off.

    python benchmarks/step_time.py      # the paper's batch: 4096 rays, 128+128 samples, 8x256 MLP
    python benchmarks/step_time.py --config configs/builtin.toml --repeats 20
    python benchmarks/step_time.py --variants bare-mlp mixnerf mixnerf-colour-only mipnerf mixnerf-bf16

Every variant is compiled first (compile time reported separately), then timed over
`--repeats` steps; all variants run in one process, one after another, so their ratios are
comparable. Runtime shape checks act while JAX traces: with them on, only tracing gets slower
and the compiled step should take the same time as with them off.
"""

import argparse
import json
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping

from mixnerf_eqx import build_model, load_config
from mixnerf_eqx._train import make_optimizer, make_train_step, training_rays
from mixnerf_eqx.data import load_dataset

BASELINE = [
    "loss.lambda_colour_start=0.0",
    "loss.lambda_colour_end=0.0",
    "loss.lambda_depth=0.0",
    "loss.lambda_regen=0.0",
]
# Variants beyond the default: each is MixNeRF with these overrides (a "-nocheck" suffix turns
# the shape checks off). "colour-only" zeroes the depth and regenerated-colour NLL weights, so
# those terms are not computed: its step time shows what skipping zero-weight work saves.
VARIANT_OVERRIDES = {
    "mipnerf": BASELINE,
    "mixnerf-colour-only": ["loss.lambda_depth=0.0", "loss.lambda_regen=0.0"],
    "mixnerf-bf16": ['model.matmul_dtype="bfloat16"'],
}


def time_variant(config, data, repeats: int, typecheck: bool) -> dict:
    jaxtyping.config.update("jaxtyping_disable", not typecheck)
    try:
        model = build_model(config, key=jax.random.key(0))
        optimizer = make_optimizer(config)
        opt_state = optimizer.init(eqx.filter(model, eqx.is_array))
        step_fn = make_train_step(config, optimizer)
        key = jax.random.key(1)
        start = time.perf_counter()
        model, opt_state, metrics = step_fn(model, opt_state, data, jnp.asarray(0, jnp.int32), key)
        jax.block_until_ready(metrics)
        compile_seconds = time.perf_counter() - start
        start = time.perf_counter()
        for step in range(1, repeats + 1):
            model, opt_state, metrics = step_fn(model, opt_state, data, jnp.asarray(step, jnp.int32), key)
        jax.block_until_ready(metrics)
        seconds = (time.perf_counter() - start) / repeats
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)
    rays = config.train.batch_size
    samples = rays * (config.model.num_coarse_samples + config.model.num_fine_samples)
    return {
        "first_step_s": compile_seconds,
        "step_s": seconds,
        "rays_per_s": rays / seconds,
        "samples_per_s": samples / seconds,
    }


def time_bare_mlp(config, repeats: int) -> dict:
    """Forward and backward of the field alone over one step's samples: the ceiling.

    The same number of points as a training step evaluates (batch x (coarse + fine)), with
    random inputs and the sum of every output as the loss, and nothing else: no sampling,
    compositing, mixture or optimiser.
    """
    model = build_model(config, key=jax.random.key(0))
    points = config.train.batch_size * (config.model.num_coarse_samples + config.model.num_fine_samples)
    keys = jax.random.split(jax.random.key(2), 3)
    means = jax.random.normal(keys[0], (points, 3))
    covs = 1e-4 * jnp.abs(jax.random.normal(keys[1], (points, 3)))
    viewdirs = jax.random.normal(keys[2], (points, 3))
    viewdirs = viewdirs / jnp.linalg.norm(viewdirs, axis=-1, keepdims=True)

    @eqx.filter_jit
    def forward_backward(field, means, covs, viewdirs):
        def total(field):
            # With remat the model recomputes the field's activations in the backward pass;
            # the ceiling does the same, so that the two are compared like for like.
            call = jax.checkpoint(type(field).__call__) if config.model.remat else type(field).__call__
            out = jax.vmap(lambda m, c, v: call(field, m, c, v))(means, covs, viewdirs)
            leaves = [x for x in jax.tree_util.tree_leaves(out) if x is not None]
            return sum(jnp.sum(x) for x in leaves)

        return eqx.filter_grad(total)(field)

    start = time.perf_counter()
    jax.block_until_ready(forward_backward(model.field, means, covs, viewdirs))
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(repeats):
        grads = forward_backward(model.field, means, covs, viewdirs)
    jax.block_until_ready(grads)
    seconds = (time.perf_counter() - start) / repeats
    return {
        "first_step_s": compile_seconds,
        "step_s": seconds,
        "rays_per_s": config.train.batch_size / seconds,
        "samples_per_s": points / seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=None, help="TOML config (default: the paper's settings)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--variants", nargs="+", default=["bare-mlp", "mixnerf", "mipnerf", "mixnerf-nocheck"]
    )
    parser.add_argument("--out", default=None)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    config = load_config(args.config, args.overrides)
    dataset = load_dataset(config.data)
    data = training_rays(dataset)
    rows = []
    for variant in args.variants:
        extra = VARIANT_OVERRIDES.get(variant.removesuffix("-nocheck"), [])
        variant_config = load_config(args.config, [*args.overrides, *extra])
        if variant == "bare-mlp":
            timing = time_bare_mlp(variant_config, args.repeats)
        else:
            timing = time_variant(
                variant_config, data, args.repeats, typecheck=not variant.endswith("nocheck")
            )
        row = {"variant": variant, **timing}
        rows.append(row)
        print(json.dumps(row), flush=True)
    machine = {
        "platform": platform.platform(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
    }
    m = config.model
    print(f"\nbatch {config.train.batch_size} rays, {m.num_coarse_samples}+{m.num_fine_samples} samples,")
    print(f"MLP {m.depth}x{m.width}, remat {m.remat}; {machine['devices']}")
    header = ("variant", "first step s", "step s", "rays/s", "samples/s")
    print(" ".join(f"{h:>16s}" for h in header))
    bare = next((row["step_s"] for row in rows if row["variant"] == "bare-mlp"), None)
    for row in rows:
        cells = (row["variant"], row["first_step_s"], row["step_s"], row["rays_per_s"], row["samples_per_s"])
        print(" ".join(f"{c:>16.4g}" if isinstance(c, float) else f"{c:>16s}" for c in cells))
        if bare is not None:
            row["fraction_of_bare_mlp_throughput"] = bare / row["step_s"]
    if bare is not None:
        print("\nthroughput as a fraction of the bare MLP's (target >= 0.80 on the GPU):")
        for row in rows:
            print(f"  {row['variant']:>16s} {row['fraction_of_bare_mlp_throughput']:.3f}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(
            json.dumps(
                {"config": args.config, "overrides": args.overrides, "machine": machine, "rows": rows},
                indent=2,
            )
        )


if __name__ == "__main__":
    main()
