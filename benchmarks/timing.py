"""Time and memory of the training step and of rendering, in four subcommands.

    python benchmarks/timing.py step       # seconds per step at the paper's batch, next to the bare MLP
    python benchmarks/timing.py profile    # where a step's time goes, part by part
    python benchmarks/timing.py typecheck  # what the runtime shape checks cost (configs/builtin.toml)
    python benchmarks/timing.py memory     # peak memory of a step and of rendering frames
    python benchmarks/timing.py quickstart # the README's first command, timed, here and at a git revision

Every subcommand takes `--config FILE` (default: the paper's settings, 4096 rays, 128 + 128
samples, 8 x 256 MLP; `typecheck`: configs/builtin.toml), `section.key=value` overrides and
`--out PATH` (default `benchmarks/results/<name>_<backend>.json`). The JSON records the
command and the machine (`harness.write_json`); the tables are printed as markdown. Each
subcommand's own options are in its `--help` and in the docstring of its function below.
"""

import argparse
import contextlib
import dataclasses
import hashlib
import inspect
import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import harness
import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, Views, load_dataset

SCRIPT = str(Path(__file__).resolve())
MIB = 2**20


def default_out(out: str | None, name: str, backend: str | None = None) -> Path:
    return Path(out) if out else harness.RESULTS / f"{name}_{backend or harness.platform_tag()}.json"


def add_common(parser: argparse.ArgumentParser, default_config: str | None, out_name: str) -> None:
    parser.add_argument(
        "--config", default=default_config, help=f"TOML config (default: {default_config or 'the paper'})"
    )
    parser.add_argument("--out", default=None, help=f"JSON path (default: results/{out_name}_<backend>.json)")
    parser.add_argument("overrides", nargs="*", help="config overrides, section.key=value")


def field_points(config: mx.Config, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Random Gaussians, unit view directions and noise keys, as many as a training step
    evaluates (batch x (coarse + fine))."""
    count = config.train.batch_size * (config.model.num_coarse_samples + config.model.num_fine_samples)
    keys = jax.random.split(key, 4)
    means = jax.random.normal(keys[0], (count, 3))
    covs = 1e-4 * jnp.abs(jax.random.normal(keys[1], (count, 3)))
    viewdirs = jax.random.normal(keys[2], (count, 3))
    viewdirs = viewdirs / jnp.linalg.norm(viewdirs, axis=-1, keepdims=True)
    return means, covs, viewdirs, jax.random.split(keys[3], count)


def summed_field(model: mx.MixNeRF, means, covs, viewdirs, keys=None) -> jax.Array:
    """The field (as the model calls it: flat points, remat if configured), outputs summed."""
    outputs = model.query_points(means, covs, viewdirs, keys)
    return sum(jnp.sum(leaf) for leaf in jax.tree_util.tree_leaves(outputs))


# ============================================================================ step


# Variants beyond the default: each is MixNeRF with these overrides (a "-nocheck" suffix turns
# the shape checks off). "colour-only" zeroes the depth and regenerated-colour NLL weights, so
# those terms are not computed: its step time shows what skipping zero-weight work saves.
STEP_VARIANTS = {
    "mixnerf": [],
    "mipnerf": ["method=mipnerf"],
    "mixnerf-colour-only": ["loss.lambda_depth=0.0", "loss.lambda_regen=0.0"],
    "mixnerf-bf16": ['model.matmul_dtype="bfloat16"'],
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
    model = mx.init_train_state(config, dataset).model
    means, covs, viewdirs, _ = field_points(config, jax.random.key(2))
    started = time.perf_counter()
    forward_backward = eqx.filter_jit(eqx.filter_grad(summed_field)).lower(model, means, covs, viewdirs)
    forward_backward = forward_backward.compile()
    compile_s = time.perf_counter() - started
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(forward_backward(model, means, covs, viewdirs))
        times.append(time.perf_counter() - started)
    return {"compile_s": compile_s, "step_s": statistics.fmean(times), "step_s_each": times}


def run_step(args: argparse.Namespace) -> None:
    """Seconds per training step: MixNeRF, its mip-NeRF baseline, the shape checks on and off.

    Every variant is compiled first (compile time reported separately), then timed over
    `--repeats` steps, each waited for; all variants run in one process, one after another,
    so their ratios are comparable. The shape checks act while JAX traces: with them on only
    compiling gets slower, and the compiled step should take the same time as with them off.
    `bare-mlp` is the field's forward and backward over the same number of points (the
    ceiling); each variant's throughput is printed as a fraction of it.
    """
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
    harness.write_json(default_out(args.out, "step_time"), payload)


# ============================================================================ profile


def timed(fn: Callable, *args, repeats: int) -> dict[str, Any]:
    """The first call (compilation) and the median of `repeats` further calls, each waited for."""
    started = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - started
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - started)
    return {
        "first_call_s": first,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "times_s": times,
    }


def step_rows(config: mx.Config, dataset: Dataset, repeats: int, *, loss: bool = True) -> dict[str, dict]:
    """The whole step (with its batch draw, as `fit` takes a step) and, with `loss`, the loss
    and its gradient, and the loss alone."""
    state = mx.init_train_state(config, dataset)
    data = mx.training_rays(dataset)
    batch_size = config.train.batch_size
    step_fn = mx.make_train_step(config)

    @eqx.filter_jit
    def draw_and_step(data, state):
        return step_fn(state, mx.draw_batch(data, state, batch_size))

    rows = {"step": timed(draw_and_step, data, state, repeats=repeats)}
    if not loss:
        return rows
    batch = eqx.filter_jit(mx.draw_batch)(data, state, batch_size)
    weights = mx.LossWeights.from_config(config.loss, config.method)
    lambda_colour, key = jnp.asarray(0.5), jax.random.key(1)

    def total(model, rays, rgb, lambda_colour, key):
        return mx.loss_fn(model, rays, rgb, lambda_colour, weights, key=key)[0]

    args = (state.model, batch.rays, batch.rgb, lambda_colour, key)
    rows["loss + gradient"] = timed(eqx.filter_jit(eqx.filter_value_and_grad(total)), *args, repeats=repeats)
    rows["loss forward"] = timed(eqx.filter_jit(total), *args, repeats=repeats)
    return rows


def summed_encoding(field: mx.GridField, points: jax.Array) -> jax.Array:
    """A grid field's encoding alone at points of `[-1, 1]^3`, as the field reads it (per point
    under `jax.vmap`, or batched: `grid.lookup`), its features summed."""
    if field.lookup == "batched":
        rows = field.encoding.encode_batch(points)
    else:
        rows = jax.vmap(field.encoding)(points)
    # Materialised first, as the decoder's product materialises them: fused into the sum, the
    # lookups would be recomputed in a reduction loop that the field never runs.
    return jnp.sum(jax.lax.optimization_barrier(rows))


def field_rows(config: mx.Config, model: mx.MixNeRF, repeats: int) -> dict[str, dict]:
    """The field's forward and forward + backward over a step's points; for a grid field, its
    encoding alone too (the decoder and heads are the difference)."""
    points = field_points(config, jax.random.key(2))
    rows = {
        "field forward + backward": timed(
            eqx.filter_jit(eqx.filter_grad(summed_field)), model, *points, repeats=repeats
        ),
        "field forward": timed(eqx.filter_jit(summed_field), model, *points, repeats=repeats),
    }
    if isinstance(model.field, mx.GridField):
        unit = jnp.clip(points[0] / 2.0, -1.0, 1.0)
        rows["encoding forward + backward"] = timed(
            eqx.filter_jit(eqx.filter_grad(summed_encoding)), model.field, unit, repeats=repeats
        )
        rows["encoding forward"] = timed(eqx.filter_jit(summed_encoding), model.field, unit, repeats=repeats)
    return rows


def random_field_outputs(model: mx.MixNeRF, key: jax.Array, batch: int, samples: int) -> mx.FieldOutputs:
    keys = jax.random.split(key, 4)
    mixture = model.mixture is not None
    return mx.FieldOutputs(
        density=jax.random.exponential(keys[0], (batch, samples)),
        rgb=jax.random.uniform(keys[1], (batch, samples, 3)),
        beta=jax.random.uniform(keys[2], (batch, samples, 3), minval=0.01, maxval=1.0) if mixture else None,
        ray_depth=jax.random.uniform(keys[3], (batch, samples), minval=1.0, maxval=6.0) if mixture else None,
    )


def part_rows(config: mx.Config, dataset: Dataset, repeats: int) -> dict[str, dict]:
    """The parts of a step outside the field, each on inputs of the step's shapes."""
    state = mx.init_train_state(config, dataset)
    model = state.model
    data = mx.training_rays(dataset)
    batch_size = config.train.batch_size
    n_coarse, n_fine = config.model.num_coarse_samples, config.model.num_fine_samples
    batch = eqx.filter_jit(mx.draw_batch)(data, state, batch_size)
    rays, target = batch.rays, batch.rgb
    keys = jax.random.split(jax.random.key(5), 8)
    rows = {}

    @eqx.filter_jit
    def random_numbers(key):
        # As the model draws them: four keys per ray (coarse sampler, coarse density noise,
        # fine sampler, fine density noise), one noise key per sample.
        def per_ray(ray_key):
            parts = jax.random.split(ray_key, 4)
            coarse_jitter = jax.random.uniform(parts[0], (n_coarse + 1,))
            fine_jitter = jax.random.uniform(parts[2], (n_fine + 1,))
            noise = [
                jax.vmap(lambda k: jax.random.normal(k, ()))(jax.random.split(parts[i], n))
                for i, n in ((1, n_coarse), (3, n_fine))
            ]
            return coarse_jitter, fine_jitter, *noise

        return jax.vmap(per_ray)(jax.random.split(key, batch_size))

    rows["random numbers"] = timed(random_numbers, keys[0], repeats=repeats)

    ray_keys = jax.random.split(keys[1], batch_size)
    coarse = eqx.filter_jit(lambda model, rays, keys: model.sample_coarse(rays, keys))
    rows["coarse samples"] = timed(coarse, model, rays, ray_keys, repeats=repeats)
    coarse_samples = coarse(model, rays, ray_keys)
    coarse_outputs = random_field_outputs(model, keys[2], batch_size, n_coarse)
    composite = eqx.filter_jit(lambda model, outputs, samples, rays: model.composite(outputs, samples, rays))
    coarse_level = composite(model, coarse_outputs, coarse_samples, rays)

    fine = eqx.filter_jit(lambda model, rays, level, keys: model.sample_fine(rays, level, keys))
    rows["fine samples"] = timed(fine, model, rays, coarse_level, ray_keys, repeats=repeats)
    fine_samples = fine(model, rays, coarse_level, ray_keys)
    fine_outputs = random_field_outputs(model, keys[3], batch_size, n_fine)
    fine_level = composite(model, fine_outputs, fine_samples, rays)

    def composite_loss(levels, model, rays, target):
        total = 0.0
        for outputs, samples in levels:
            level = model.composite(outputs, samples, rays)
            total = total + jnp.mean((level.rgb - target) ** 2) + jnp.mean(level.depth) + jnp.mean(level.acc)
        return total

    levels = ((coarse_outputs, coarse_samples), (fine_outputs, fine_samples))
    rows["compositing (forward + backward)"] = timed(
        eqx.filter_jit(eqx.filter_grad(composite_loss)), levels, model, rays, target, repeats=repeats
    )

    # The loss terms on rendered levels, forward and backward (to the field outputs), with
    # the terms switched on one at a time through the static weights (a zero weight is not
    # computed): the MSE alone, then each NLL added alone, then the config's weights.
    outputs = mx.RenderOutputs(coarse=coarse_level, fine=fine_level)
    weights = mx.LossWeights.from_config(config.loss, config.method)
    nlls = {"nll_colour": "colour NLL", "nll_depth": "depth NLL", "nll_regen": "regenerated colour NLL"}
    mse_only = weights.replace(**dict.fromkeys(nlls, 0.0))
    weight_rows = {"loss terms: MSE only": mse_only}
    if weights.uses_mixture:
        for name, label in nlls.items():
            if weights[name] > 0:
                weight_rows[f"loss terms: MSE + {label}"] = mse_only.replace(**{name: weights[name]})
        weight_rows["loss terms: the config's (MSE + mixture NLLs)"] = weights
    lambda_colour = jnp.asarray(0.5)
    for name, row_weights in weight_rows.items():

        def total(outputs, model, rays, target, lambda_colour, row_weights=row_weights):
            return mx.loss_terms(outputs, model, rays, target, lambda_colour, row_weights).total

        rows[f"{name} (forward + backward)"] = timed(
            eqx.filter_jit(eqx.filter_grad(total)),
            outputs,
            model,
            rays,
            target,
            lambda_colour,
            repeats=repeats,
        )

    params = eqx.filter(model, eqx.is_array)

    @eqx.filter_jit
    def optimiser_step(grads, state):
        updates, opt_state = state.optimizer.update(
            grads, state.opt_state, eqx.filter(state.model, eqx.is_array)
        )
        return eqx.apply_updates(state.model, updates), opt_state

    grads = jax.tree_util.tree_map(lambda x: 1e-3 * jnp.ones_like(x), params)
    rows["optimiser"] = timed(optimiser_step, grads, state, repeats=repeats)

    @eqx.filter_jit
    def batch_draw(data, state):
        batch = mx.draw_batch(data, state, batch_size)
        train = config.train
        rays = mx.anneal_sample_space(batch.rays, 7, train.anneal_steps, train.anneal_start, train.anneal_mid)
        return rays, batch.rgb

    rows["batch draw"] = timed(batch_draw, data, state, repeats=repeats)
    return rows


def run_profile(args: argparse.Namespace) -> None:
    """Where a training step's time goes: the step against its parts, each compiled and timed alone.

    Every row is one jitted function on the step's own shapes, compiled first and then timed
    `--repeats` times, each waited for; the fastest call and the median are reported, with the
    fastest call's share of the full step. All rows run in one process, one after another, so
    their ratios are comparable:

    - `step`: the batch draw and the library's training step (`make_train_step`: sample-space
      annealing, render, loss, gradient, optimiser, non-finite guard) in one function.
    - `loss + gradient`: `loss_fn` and its gradient, without optimiser and guard.
    - `loss forward`: the render and the loss, no gradient.
    - `field forward + backward`: the MLP (with its encodings) alone over the step's points,
      its outputs summed: the ceiling of `timing.py step`; `field forward`: without gradient.
      For a grid field, `encoding forward (+ backward)`: the grid lookups alone at as many
      points, as the field reads them (`grid.lookup`); the decoder is the difference.
    - `step, width-N field`: the whole step with the MLP shrunk to `--narrow-width`
      (encodings, layer count and everything else unchanged): what the step costs besides
      the dense layers' products.
    - the parts outside the field, on random inputs of the step's shapes: `random numbers`
      (per-ray and per-sample keys, jitter and density noise as the model draws them),
      `coarse samples`, `fine samples` (resampling from coarse weights), `compositing`
      (both levels, forward + backward), the `loss terms` (`mx.loss_terms` on rendered levels,
      forward + backward: the MSE alone, each NLL the config weights added alone, then all of
      them), `optimiser` (clipping and Adam), `batch draw` (with the annealing).
    """
    config = mx.load_config(args.config, args.overrides)
    dataset = load_dataset(config.data)
    rows = step_rows(config, dataset, args.repeats)
    rows.update(field_rows(config, mx.init_train_state(config, dataset).model, args.repeats))
    width = args.narrow_width
    widths = (
        [f"grid.decoder_width={width}", f"grid.view_width={width}"]
        if config.model.field == "grid"
        else [f"model.width={width}", f"model.view_width={width}"]
    )
    narrow = mx.load_config(args.config, [*args.overrides, *widths])
    rows[f"step, width-{width} field"] = step_rows(narrow, dataset, args.repeats, loss=False)["step"]
    narrow_model = mx.init_train_state(narrow, dataset).model
    rows[f"field forward + backward, width {width}"] = field_rows(narrow, narrow_model, args.repeats)[
        "field forward + backward"
    ]
    rows.update(part_rows(config, dataset, args.repeats))

    # Shares from the fastest call of each row: on a shared machine the other processes only
    # ever add time, so the minimum is the steadiest estimate (the medians are kept too).
    step_s = rows["step"]["min_s"]
    for row in rows.values():
        row["share_of_step"] = row["min_s"] / step_s
    m = config.model
    if m.field == "grid":
        g = config.grid
        lookup = mx.init_train_state(config, dataset).model.field.lookup
        field_text = (
            f"grid {g.encoding} {g.levels} levels {g.min_resolution}-{g.max_resolution} x {g.features}, "
            f"decoder {g.decoder_width}/{g.view_width}, lookup {lookup}"
        )
    else:
        field_text = f"MLP {m.depth}x{m.width}, matmul {m.matmul_dtype}"
    print(
        f"\n{config.train.batch_size} rays, {m.num_coarse_samples}+{m.num_fine_samples} samples, "
        f"{field_text}, remat {m.remat}; {jax.devices()}\n"
    )
    harness.print_table(
        ("part", "ms (min)", "ms (median)", "share of the step (min)", "first call s"),
        [
            (name, 1e3 * row["min_s"], 1e3 * row["median_s"], row["share_of_step"], row["first_call_s"])
            for name, row in rows.items()
        ],
    )
    ceiling = rows["field forward + backward"]["min_s"]
    print(f"\nstep throughput as a fraction of the field's forward + backward: {ceiling / step_s:.3f}")
    payload = {
        "config": args.config,
        "overrides": args.overrides,
        "repeats": args.repeats,
        "model": dataclasses.asdict(config.model),
        "batch_size": config.train.batch_size,
        "rows": rows,
        "fraction_of_field_forward_backward": ceiling / step_s,
    }
    harness.write_json(default_out(args.out, "profile_step"), payload)


# ============================================================================ typecheck


TYPECHECK_MARKER = "TYPECHECK-OVERHEAD-RESULT "
RETRACES = 5
# A fresh interpreter with JAX, Equinox and jaxtyping already loaded times `import mixnerf_eqx`
# (the package installs jaxtyping's import hook for its modules as it is imported) and lists
# the package's modules loaded by the import and those loaded later, outside the hook.
IMPORT_PROBE = """
import json, sys, time
import equinox, jax, jaxtyping
before = set(sys.modules)
started = time.perf_counter()
import mixnerf_eqx
import_s = time.perf_counter() - started
hooked = sorted(m for m in set(sys.modules) - before if m.startswith("mixnerf_eqx"))
import mixnerf_eqx.eval, mixnerf_eqx.train
later = sorted(m for m in set(sys.modules) - before if m.startswith("mixnerf_eqx") and m not in hooked)
print(json.dumps({"import_s": import_s, "hooked_modules": hooked, "modules_imported_after_the_hook": later}))
"""


def probe_call(call: Callable[[], Any]) -> dict[str, Any]:
    """What `call()` did: the exception it raised, or what it returned (dtype and shape of an array)."""
    import jaxtyping

    try:
        out = call()
    except Exception as error:  # whatever happens is recorded
        kind = type(error)
        return {
            "raised": f"{kind.__module__}.{kind.__qualname__}",
            "type_check_error": isinstance(error, jaxtyping.TypeCheckError),
            "message": str(error).splitlines()[:2],
        }
    returned = f"{out.dtype}{list(out.shape)}" if hasattr(out, "shape") else type(out).__name__
    return {"raised": None, "type_check_error": False, "returned": returned}


def compile_phases(events: list[tuple[str, float]]) -> dict[str, float | None]:
    """Seconds of tracing, lowering and compiling among JAX's monitoring events.

    Tracing takes the longest trace event (a jit traced inside another is part of it); the
    others are summed.
    """
    names = {
        "trace_s": "/jax/core/compile/jaxpr_trace_duration",
        "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "compile_s": "/jax/core/compile/backend_compile_duration",
    }
    phases: dict[str, float | None] = {}
    for key, name in names.items():
        seconds = [d for event, d in events if event == name]
        phases[key] = None if not seconds else (max(seconds) if key == "trace_s" else sum(seconds))
    return phases


def measure_typecheck(setting: str, config_path: str, overrides: list[str], steps: int) -> dict[str, Any]:
    """One setting's measurements, in a fresh process (`--one on|off`)."""
    on = setting == "on"
    mx.set_typecheck(on)

    # One density but five edges: the annotations tie the edges to `num_samples+1` = 2.
    # Unchecked, the arithmetic broadcasts and returns four weights where one is due.
    def wrong_call():
        return mx.blend_weights(jnp.ones((1,)), jnp.linspace(2.0, 6.0, 5), jnp.asarray(1.0))

    probe = probe_call(wrong_call)
    # The switch acts on the next call: flipped, the same call must do the opposite.
    with harness.typechecking(not on):
        probe_flipped = probe_call(wrong_call)

    config = mx.load_config(config_path, overrides)
    batch_size = config.train.batch_size
    started = time.perf_counter()
    dataset = load_dataset(config.data)
    data = mx.training_rays(dataset)
    state = mx.init_train_state(config, dataset)
    jax.block_until_ready((data, state))
    setup_s = time.perf_counter() - started

    # JAX reports how long each phase of a jit's first call took: tracing to a jaxpr (where
    # the checks run), lowering to StableHLO, and XLA's compilation.
    events: list[tuple[str, float]] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: events.append((event, seconds))
    )
    initial = state
    step_fn, draw = mx.make_train_step(config), eqx.filter_jit(mx.draw_batch)
    # The first step: the batch draw and the step, each traced, lowered, compiled and run.
    events.clear()
    started = time.perf_counter()
    state, metrics = jax.block_until_ready(step_fn(state, draw(data, state, batch_size)))
    first_step_s = time.perf_counter() - started
    first_phases = compile_phases(events)
    step_times = []
    for _ in range(steps):
        started = time.perf_counter()
        state, metrics = jax.block_until_ready(step_fn(state, draw(data, state, batch_size)))
        step_times.append(time.perf_counter() - started)
    final_loss = float(metrics.terms.total)

    # Fresh step functions (new closures, so nothing of the first is reused) are traced and
    # lowered again, `RETRACES` times (one alone swings with the garbage collector), and the
    # StableHLO of the last kept: the program XLA is given.
    batch = draw(data, initial, batch_size)
    retrace_times = []
    for _ in range(RETRACES):
        events.clear()
        lowered = mx.make_train_step(config).lower(initial, batch)
        retrace_times.append(compile_phases(events)["trace_s"])
    retrace_s = None if None in retrace_times else statistics.median(retrace_times)
    stablehlo = lowered.as_text()

    # The checks inside the step: colours as 8-bit integers (an easy mistake with images) reach
    # `loss_fn`, whose `target_rgb` is annotated `Float[...]`. Checked, tracing stops there;
    # unchecked, the integers are promoted and the step traces and lowers as if all were well.
    uint8_batch = eqx.tree_at(lambda b: b.rgb, batch, (255 * batch.rgb).astype(jnp.uint8))
    probe_step = probe_call(lambda: mx.make_train_step(config).lower(initial, uint8_batch))

    return {
        "typecheck_enabled": mx.typecheck_enabled(),
        "wrong_shape_call": probe,
        "wrong_shape_call_switch_flipped": probe_flipped,
        "uint8_colours_step_lowering": probe_step,
        "setup_s": setup_s,
        "first_step_s": first_step_s,
        "first_step_trace_s": first_phases["trace_s"],
        "first_step_lower_s": first_phases["lower_s"],
        "first_step_compile_s": first_phases["compile_s"],
        "retrace_s": retrace_s,
        "retrace_s_each": retrace_times,
        "step_s_median": statistics.median(step_times),
        "step_s_min": min(step_times),
        "step_s_mean": statistics.fmean(step_times),
        "step_s": step_times,
        "final_loss": final_loss,
        "stablehlo_sha256": hashlib.sha256(stablehlo.encode()).hexdigest(),
        "stablehlo_chars": len(stablehlo),
        "model": harness.model_summary(config),
        "machine": harness.machine_info(),
    }


def spawn_typecheck(setting: str, round_index: int, args: argparse.Namespace) -> dict[str, Any]:
    command = [sys.executable, SCRIPT, "typecheck", "--one", setting, "--steps", str(args.steps)]
    command += ["--config", args.config, *args.overrides]
    # Each process starts from the default (checks on) and sets its own setting.
    env = {k: v for k, v in os.environ.items() if k != "JAXTYPING_DISABLE"}
    started = time.perf_counter()
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, text=True)  # stderr passes through
    row = {"checks": setting, "round": round_index, "wall_s": time.perf_counter() - started}
    lines = [line for line in done.stdout.splitlines() if line.startswith(TYPECHECK_MARKER)]
    if done.returncode != 0 or not lines:
        return {**row, "error": f"subprocess exited with {done.returncode}"}
    return {**row, **json.loads(lines[-1][len(TYPECHECK_MARKER) :])}


def import_probe() -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if k != "JAXTYPING_DISABLE"}
    done = subprocess.run([sys.executable, "-c", IMPORT_PROBE], env=env, stdout=subprocess.PIPE, text=True)
    if done.returncode != 0:
        return {"error": f"subprocess exited with {done.returncode}"}
    return json.loads(done.stdout.splitlines()[-1])


def on_off_ratio(rows: list[dict], key: str) -> float | None:
    on = [row[key] for row in rows if row["checks"] == "on" and row.get(key) is not None]
    off = [row[key] for row in rows if row["checks"] == "off" and row.get(key) is not None]
    if not on or not off:
        return None
    return statistics.median(on) / statistics.median(off)


def outcome(probe: dict | None) -> str:
    if probe is None:
        return "n/a"
    if probe["raised"] is None:
        return f"returned {probe['returned']}"
    return f"raised {probe['raised'].rsplit('.', 1)[-1]}"


def checks_as_expected(row: dict) -> bool:
    """On: the wrong call raises TypeCheckError, and does not once the switch is flipped off;
    tracing the step with uint8 colours raises too. Off: the reverse."""
    if "error" in row:
        return False
    on = row["checks"] == "on"
    return (
        row["typecheck_enabled"] == on
        and row["wrong_shape_call"]["type_check_error"] == on
        and row["wrong_shape_call_switch_flipped"]["type_check_error"] != on
        and row["uint8_colours_step_lowering"]["type_check_error"] == on
    )


TYPECHECK_COLUMNS = (  # (header, key, scale)
    ("setup s", "setup_s", 1.0),
    ("first step s", "first_step_s", 1.0),
    ("of which trace s", "first_step_trace_s", 1.0),
    ("lower s", "first_step_lower_s", 1.0),
    ("XLA compile s", "first_step_compile_s", 1.0),
    ("re-trace s (median)", "retrace_s", 1.0),
    ("compiled step ms (median)", "step_s_median", 1e3),
    ("min ms", "step_s_min", 1e3),
)


def run_typecheck(args: argparse.Namespace) -> None:
    """What the runtime shape checks cost: the tracing first step and the compiled step, on and off.

    The checks are jaxtyping's with beartype, installed for the package's modules as it is
    imported and switched with `mx.set_typecheck`, which every checked call reads when it
    runs. Each setting runs in a fresh Python process (`--one on|off`), so that neither
    inherits the other's caches; each process

    - sets the switch, calls a public annotated function wrongly (`mx.blend_weights` with one
      density and five interval edges; it needs two) and records what happens: with the
      checks on it must raise jaxtyping's `TypeCheckError`, with them off it returns a
      wrongly shaped result; then calls it again with the switch flipped, which must do the
      opposite;
    - times the setup (scene, ray table, `mx.init_train_state`);
    - times the first batch draw and step of `mx.make_train_step` (trace, lower, compile and
      one run: the checks act in the trace alone), split into its phases by JAX's own
      monitoring events, then `--steps` further steps one by one, each waited for, and
      reports their median: the compiled step;
    - traces and lowers fresh step functions five times ("re-trace", the median) and hashes
      the StableHLO text: equal hashes on and off mean that XLA is given the same program.
      The loss after the last timed step is recorded too;
    - lowers the step once more with the batch's colours as uint8: `loss_fn`'s `target_rgb`
      is annotated `Float`, so with the checks on the trace must stop with `TypeCheckError`,
      while without them it lowers silently.

    The processes run one after another, `--rounds` of each setting (on first in even rounds,
    off first in odd ones); the ratios on / off are medians over the on processes divided by
    medians over the off ones. A fresh interpreter per round also times `import mixnerf_eqx`
    (the same with the checks on or off: the switch acts at call time). Exits with status 1
    when the checks were not active as expected.
    """
    if args.steps < 1 or args.rounds < 1:
        raise SystemExit("--steps and --rounds must be at least 1")
    if args.one is not None:
        result = measure_typecheck(args.one, args.config, args.overrides, args.steps)
        print(TYPECHECK_MARKER + json.dumps(result), flush=True)
        return

    rows, imports = [], []
    for round_index in range(args.rounds):
        imports.append(import_probe())
        order = ("on", "off") if round_index % 2 == 0 else ("off", "on")
        for setting in order:
            row = spawn_typecheck(setting, round_index, args)
            rows.append(row)
            brief = {k: row.get(k) for k in ("checks", "round", "error", "first_step_s", "step_s_median")}
            print(json.dumps({k: v for k, v in brief.items() if v is not None}), flush=True)

    good = [row for row in rows if "error" not in row]
    import_times = [probe["import_s"] for probe in imports if "import_s" in probe]
    summary = {
        "import_s_median": statistics.median(import_times) if import_times else None,
        "first_step_ratio_on_off": on_off_ratio(rows, "first_step_s"),
        "first_step_trace_ratio_on_off": on_off_ratio(rows, "first_step_trace_s"),
        "first_step_compile_ratio_on_off": on_off_ratio(rows, "first_step_compile_s"),
        "retrace_ratio_on_off": on_off_ratio(rows, "retrace_s"),
        "compiled_step_ratio_on_off": on_off_ratio(rows, "step_s_median"),
        "compiled_step_min_ratio_on_off": on_off_ratio(rows, "step_s_min"),
        "same_stablehlo_on_off": len({row["stablehlo_sha256"] for row in good}) == 1 if good else None,
        "same_final_loss_on_off": len({row["final_loss"] for row in good}) == 1 if good else None,
        "checks_as_expected": all(checks_as_expected(row) for row in rows),
    }

    model = good[0]["model"] if good else {}
    overrides = " ".join(args.overrides) or "none"
    print(f"\n{args.config} (overrides: {overrides}): batch {model.get('batch_size')} rays,")
    print(
        f"{'+'.join(map(str, model.get('samples', [])))} samples, MLP {model.get('mlp')}; "
        f"{args.steps} timed steps per process\n"
    )
    table = []
    for row in rows:
        if "error" in row:
            table.append((row["checks"], row["round"], row["error"]))
            continue
        cells = [None if row.get(key) is None else scale * row[key] for _, key, scale in TYPECHECK_COLUMNS]
        outcomes = (
            outcome(row["wrong_shape_call"]),
            outcome(row["wrong_shape_call_switch_flipped"]),
            outcome(row["uint8_colours_step_lowering"]),
        )
        table.append((row["checks"], row["round"], *cells, *outcomes))
    header = ["checks", "round", *(c[0] for c in TYPECHECK_COLUMNS)]
    header += ["wrong-shape call", "switch flipped", "step, uint8 colours"]
    harness.print_table(header, table)
    print()

    def show(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.2f}"

    lines = [
        ("import mixnerf_eqx, s", show(summary["import_s_median"])),
        ("first step, on / off", show(summary["first_step_ratio_on_off"])),
        ("  its trace, on / off", show(summary["first_step_trace_ratio_on_off"])),
        ("  its XLA compile, on / off", show(summary["first_step_compile_ratio_on_off"])),
        ("re-trace, on / off", show(summary["retrace_ratio_on_off"])),
        ("compiled step, on / off", f"{show(summary['compiled_step_ratio_on_off'])}  (expected about 1.00)"),
        ("  its fastest, on / off", show(summary["compiled_step_min_ratio_on_off"])),
        ("same StableHLO on and off", summary["same_stablehlo_on_off"]),
        (f"same loss after {args.steps + 1} steps", summary["same_final_loss_on_off"]),
        ("checks active as expected", summary["checks_as_expected"]),
    ]
    for label, value in lines:
        print(f"{label + ':':<30s}{value}")
    hooked = next((probe for probe in imports if "hooked_modules" in probe), None)
    if hooked is not None:
        later = ", ".join(
            name.removeprefix("mixnerf_eqx.") for name in hooked["modules_imported_after_the_hook"]
        )
        print(
            f"modules under the hook: {len(hooked['hooked_modules'])}; imported after it, so unchecked: "
            f"{len(hooked['modules_imported_after_the_hook'])} ({later or 'none'})"
        )

    backend = good[0]["machine"]["backend"] if good else None
    payload = {
        "config": args.config,
        "overrides": args.overrides,
        "steps": args.steps,
        "rounds": args.rounds,
        "machine": good[0]["machine"] if good else None,
        "load_average_at_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "summary": summary,
        "imports": imports,
        "rows": rows,
    }
    if payload["machine"] is None:
        del payload["machine"]
    harness.write_json(default_out(args.out, "typecheck_overhead", backend), payload)
    if not summary["checks_as_expected"]:
        print("the checks were not active as expected", file=sys.stderr)
        sys.exit(1)


# ============================================================================ memory


MEMORY_MARKER = "MEMORY-RESULT "
NEAR, FAR = 2.0, 6.0  # Blender-like bounds around a scene at the origin
CAMERA_DISTANCE = 4.0
FOCAL_PER_PIXEL = 1.3888  # Blender's 555.6 px focal length at 400 px: a 39.6 degree field of view
MEMORY_FIELDS = (
    "argument_size_in_bytes",
    "output_size_in_bytes",
    "alias_size_in_bytes",
    "temp_size_in_bytes",
    "generated_code_size_in_bytes",
    "peak_memory_in_bytes",
    "host_argument_size_in_bytes",
    "host_output_size_in_bytes",
    "host_alias_size_in_bytes",
    "host_temp_size_in_bytes",
)


def proc_status_bytes(field: str) -> int | None:
    """A `kB` line of /proc/self/status (Linux) in bytes, or None elsewhere."""
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return None


def ru_maxrss_bytes(usage) -> int:
    # ru_maxrss is in kilobytes on Linux and in bytes on macOS.
    return usage.ru_maxrss if sys.platform == "darwin" else usage.ru_maxrss * 1024


def host_peak_bytes() -> int | None:
    """This process' resident-set high-water mark (reset by `reset_host_peak`, where it works)."""
    peak = proc_status_bytes("VmHWM")
    if peak is not None:
        return peak
    try:
        import resource
    except ImportError:
        return None
    return ru_maxrss_bytes(resource.getrusage(resource.RUSAGE_SELF))


def reset_host_peak() -> bool:
    """Resets the resident-set high-water mark to the current RSS (Linux 4.0+); False if not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def device_memory() -> dict | None:
    """The first device's allocator statistics; None where the backend keeps none (the CPU)."""
    stats = jax.devices()[0].memory_stats()
    if not stats:
        return None
    return {k: int(stats[k]) for k in ("bytes_in_use", "peak_bytes_in_use", "bytes_limit") if k in stats}


def compiled_memory(compiled) -> dict | None:
    """XLA's memory analysis of a compiled function (jax's or equinox's `Compiled`), or None."""
    inner = getattr(compiled, "compiled", compiled)  # equinox's Compiled wraps jax's
    try:
        stats = inner.memory_analysis()
    except (NotImplementedError, RuntimeError):
        return None
    if isinstance(stats, list | tuple):  # some versions answer one entry per device
        stats = stats[0] if stats else None
    if stats is None:
        return None
    fields = {name: int(getattr(stats, name)) for name in MEMORY_FIELDS if hasattr(stats, name)}
    total = sum(fields.get(f"{part}_size_in_bytes", 0) for part in ("argument", "output", "temp"))
    # Everything the executable holds while it runs: its arguments and outputs (no donation here)
    # and its one temporary allocation, whose size XLA's buffer assignment has already packed.
    # (XLA's own `peak_memory_in_bytes` is kept as reported; on the CPU it leaves temporaries out.)
    fields["xla_total_bytes"] = total - fields.get("alias_size_in_bytes", 0)
    return fields


def tree_bytes(tree) -> int:
    return int(sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))))


def measured(work: Callable[[], Any]) -> dict[str, Any]:
    """Runs `work()` and reports the device and host memory around it."""
    before = device_memory()
    rss_start = proc_status_bytes("VmRSS")
    reset = reset_host_peak()
    started = time.perf_counter()
    work()
    return {
        "seconds": time.perf_counter() - started,
        "device_before": before,
        "device_after": device_memory(),
        "host_rss_start_bytes": rss_start,
        "host_rss_peak_bytes": host_peak_bytes() if reset else None,
    }


def synthetic_poses(count: int) -> np.ndarray:
    """`count` camera-to-world matrices (3 x 4) on a circle 30 degrees above the origin, facing it."""
    poses = []
    elevation = math.radians(30.0)
    for index in range(count):
        azimuth = 2 * math.pi * index / count
        centre = CAMERA_DISTANCE * np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        back = centre / np.linalg.norm(centre)  # the camera looks along its -z axis
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        poses.append(np.stack([right, up, back, centre], axis=1))
    return np.stack(poses).astype(np.float32)


def synthetic_dataset(views: int, size: int) -> Dataset:
    """Random images from synthetic cameras: the memory does not depend on the pixels' values."""
    rng = np.random.default_rng(0)

    def split(count: int) -> Views:
        images = rng.uniform(0.0, 1.0, (count, size, size, 3)).astype(np.float32)
        return Views(images=images, camtoworlds=synthetic_poses(count), focal=FOCAL_PER_PIXEL * size)

    return Dataset(name="synthetic", train=split(views), test=split(1), near=NEAR, far=FAR)


def frame_rays(size: int) -> mx.RayBundle:
    return mx.camera_rays(synthetic_poses(1), FOCAL_PER_PIXEL * size, size, size, NEAR, FAR)


def measure_machine(config: mx.Config) -> dict[str, Any]:
    cpu_model = None
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    try:
        host_memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        host_memory = None
    stats = device_memory() or {}
    return {
        "machine": {
            **harness.machine_info(),
            "cpu_model": cpu_model,
            "host_memory_bytes": host_memory,
            "device_bytes_limit": stats.get("bytes_limit"),
            "xla_env": {k: v for k, v in os.environ.items() if k.startswith(("XLA_", "JAX_"))},
        },
        "config": {
            **harness.model_summary(config),
            "view_width": config.model.view_width,
            "remat": config.model.remat,
            "render_chunk": config.train.render_chunk,
        },
    }


def measure_train(config: mx.Config, views: int, image_size: int, execute: bool) -> dict[str, Any]:
    """The batch draw and the training step compiled as one function over the ray table (so
    that the table counts, as it is held while training), on a synthetic scene."""
    dataset = synthetic_dataset(views, image_size)
    state = mx.init_train_state(config, dataset)
    data = mx.training_rays(dataset)
    step_fn, batch_size = mx.make_train_step(config), config.train.batch_size

    @eqx.filter_jit
    def draw_and_step(data, state):
        return step_fn(state, mx.draw_batch(data, state, batch_size))

    started = time.perf_counter()
    compiled = draw_and_step.lower(data, state).compile()
    row = {
        "compile_s": time.perf_counter() - started,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(state.model),
        "opt_state_bytes": tree_bytes(state.opt_state),
        "data_bytes": tree_bytes(data),
        "executed": execute,
    }
    if execute:
        row["measured"] = measured(lambda: jax.block_until_ready(compiled(data, state)))
    return row


def pad_to(rays: mx.RayBundle, count: int) -> mx.RayBundle:
    """The first `count` rays, the last one repeated where there are fewer (as `render_rays` pads)."""
    piece = rays[:count]
    missing = count - piece.origins.shape[0]
    if missing > 0:
        piece = jax.tree_util.tree_map(
            lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], missing, axis=0)]), piece
        )
    return piece


def measure_render(config: mx.Config, size: int, chunk: int, execute: bool) -> dict[str, Any]:
    """One chunk's compiled figures (the dense render `model(rays).fine` of `chunk` rays, the
    program `mx.render_rays` runs per chunk) and, when executed, a whole frame through
    `mx.render_rays`."""
    model = mx.build_model(config, key=jax.random.key(0))
    # Without rendering, only one chunk's rays are needed for the compiled figures.
    rays = frame_rays(size if execute else math.isqrt(chunk - 1) + 1)
    piece = pad_to(rays.reshape(-1), chunk)
    started = time.perf_counter()
    compiled = eqx.filter_jit(lambda model, rays: model(rays).fine).lower(model, piece).compile()
    row = {
        "compile_s": time.perf_counter() - started,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(model),
        "executed": execute,
    }
    del compiled
    if execute:
        # One chunk through `render_rays` first, so that the measured frame compiles nothing.
        mx.render_rays(model, piece, chunk)
        del piece
        row["ray_table_bytes"] = tree_bytes(rays)
        row["measured"] = measured(lambda: mx.render_rays(model, rays, chunk))
    return row


def run_memory_one(spec: dict, args: argparse.Namespace) -> dict[str, Any]:
    kind = spec["kind"]
    if kind == "train":
        remat = str(spec["remat"]).lower()
        config = mx.load_config(args.config, [*args.overrides, f"model.remat={remat}"])
        return measure_train(config, spec["views"], spec["image_size"], spec["execute"])
    config = mx.load_config(args.config, args.overrides)
    if kind == "machine":
        return measure_machine(config)
    if kind == "render":
        return measure_render(config, spec["size"], spec["chunk"], spec["execute"])
    raise ValueError(f"unknown measurement {kind!r}")


def spawn_memory(spec: dict, args: argparse.Namespace) -> dict[str, Any]:
    """Runs one measurement in a fresh Python process; adds its lifetime peak RSS (wait4)."""
    command = [sys.executable, SCRIPT, "memory", "--one", json.dumps(spec)]
    if args.config:
        command += ["--config", args.config]
    command += args.overrides
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)  # stderr passes through
    output = process.stdout.read()
    process.stdout.close()
    process_peak = None
    if hasattr(os, "wait4"):  # this child's own rusage, not the running maximum over all children
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        process_peak = ru_maxrss_bytes(usage)
    else:
        process.wait()
    lines = [line for line in output.splitlines() if line.startswith(MEMORY_MARKER)]
    wall_s = time.perf_counter() - started
    if process.returncode != 0 or not lines:
        return {**spec, "error": f"subprocess exited with {process.returncode}", "wall_s": wall_s}
    result = json.loads(lines[-1][len(MEMORY_MARKER) :])
    return {**spec, **result, "host_rss_process_peak_bytes": process_peak, "wall_s": wall_s}


def mib(value: int | None) -> str:
    return "n/a" if value is None else f"{value / MIB:,.0f}"


def nested(row: dict, *path: str) -> Any:
    for key in path:
        if not isinstance(row, dict) or row.get(key) is None:
            return None
        row = row[key]
    return row


def train_table(rows: list[dict]) -> None:
    header = [
        "remat",
        "run",
        "XLA arguments MiB",
        "XLA outputs MiB",
        "XLA temporaries MiB",
        "XLA total MiB (compiled)",
        "device peak MiB (measured)",
        "host RSS peak MiB, step",
        "host RSS peak MiB, process",
        "compile s",
        "step s",
    ]
    cells = []
    for row in rows:
        if "error" in row:
            cells.append([str(row["remat"]).lower(), row["error"]] + ["n/a"] * (len(header) - 2))
            continue
        seconds = nested(row, "measured", "seconds")
        cells.append(
            [
                str(row["remat"]).lower(),
                "executed" if row["executed"] else "compiled only",
                mib(nested(row, "compiled", "argument_size_in_bytes")),
                mib(nested(row, "compiled", "output_size_in_bytes")),
                mib(nested(row, "compiled", "temp_size_in_bytes")),
                mib(nested(row, "compiled", "xla_total_bytes")),
                mib(nested(row, "measured", "device_after", "peak_bytes_in_use")),
                mib(nested(row, "measured", "host_rss_peak_bytes")),
                mib(row["host_rss_process_peak_bytes"]),
                f"{row['compile_s']:.1f}",
                "n/a" if seconds is None else f"{seconds:.1f}",
            ]
        )
    harness.print_table(header, cells)


def render_table(rows: list[dict]) -> None:
    header = [
        "sweep",
        "frame",
        "rays",
        "chunk",
        "calls",
        "XLA chunk total MiB (compiled)",
        "ray table MiB",
        "frame estimate MiB (compiled)",
        "device peak MiB (measured)",
        "host RSS MiB before",
        "host RSS peak MiB, render",
        "host RSS peak MiB, process",
        "render s",
    ]
    cells = []
    for row in rows:
        measured_row = {} if "error" in row else row.get("measured") or {}
        seconds = measured_row.get("seconds")
        cells.append(
            [
                row["sweep"],
                f"{row['size']}x{row['size']}",
                f"{row['rays']:,}",
                str(row["chunk"]),
                str(row["calls"]),
                mib(nested(row, "compiled", "xla_total_bytes")),
                f"{row['ray_table_bytes'] / MIB:,.1f}",
                mib(row.get("estimate_bytes")),
                mib(nested(measured_row, "device_after", "peak_bytes_in_use")),
                mib(measured_row.get("host_rss_start_bytes")),
                mib(measured_row.get("host_rss_peak_bytes")),
                mib(row.get("host_rss_process_peak_bytes")) if row["executed"] else "n/a",
                row["error"] if "error" in row else ("n/a" if seconds is None else f"{seconds:.1f}"),
            ]
        )
    harness.print_table(header, cells)


def run_memory(args: argparse.Namespace) -> None:
    """Peak memory of one training step (remat off and on) and of rendering whole frames in chunks.

    (a) One training step at the config's batch with `model.remat` false and true: the batch
    draw and `mx.make_train_step`'s step compiled as one function over the ray table, on a
    synthetic scene (`--train-views` views of `--train-image-size` pixels square). (b) One
    frame rendered with `mx.render_rays`, for several square frame sizes at one chunk
    (`--frame-chunk`, default the config's `train.render_chunk`) and for several chunks at one
    frame size (`--chunk-frame`); the rays come from a synthetic camera, the model is freshly
    initialised (its values do not change the memory).

    Three kinds of figure, each labelled in the table and the JSON:

    - compiled (XLA): `memory_analysis()` of the compiled step or render chunk (the dense
      render `model(rays).fine` that `render_rays` runs per chunk), known before anything
      runs: arguments + outputs + temporaries - aliases (the "total"; nothing is donated).
      A frame's compiled estimate is the chunk's total plus the frame's ray table twice: the
      rays as built, and the padded copy that `render_rays` makes of them.
    - device peak (GPU only): `memory_stats()["peak_bytes_in_use"]` after the measured work.
      The peak cannot be reset, so every measurement runs in a fresh subprocess (`--one`),
      and the peak also covers that process's setup (model, rays, compilation).
    - host RSS: the subprocess's resident memory on the host: its peak during the measured
      work (Linux: VmHWM, reset after setup and compilation) and over its whole life (wait4).
      On the CPU, device buffers live in host memory, so this is the only measured figure
      there; it is host memory with the interpreter and the JAX runtime in it.

    The training step runs on a GPU and is only compiled on the CPU (`--execute-train`); a
    frame is rendered when it has at most `--max-execute-rays` rays (default: every frame on a
    GPU, 16384 rays on the CPU) and otherwise has its compiled estimate alone. The main
    process never touches the accelerator while the measurements run (a first subprocess
    reports the machine).
    """
    if args.one is not None:
        result = run_memory_one(json.loads(args.one), args)
        print(MEMORY_MARKER + json.dumps(result), flush=True)
        return

    probe = spawn_memory({"kind": "machine"}, args)
    if "error" in probe:
        raise SystemExit(f"the machine probe failed: {probe['error']}")
    machine, config = probe["machine"], probe["config"]
    on_gpu = machine["backend"] != "cpu"
    execute_train = args.execute_train == "yes" or (args.execute_train == "auto" and on_gpu)
    max_rays = args.max_execute_rays
    if max_rays is None:
        max_rays = sys.maxsize if on_gpu else 16384
    frame_chunk = args.frame_chunk or config["render_chunk"]

    train_rows = []
    if not args.skip_train:
        for remat in (False, True):
            spec = {
                "kind": "train",
                "remat": remat,
                "views": args.train_views,
                "image_size": args.train_image_size,
                "execute": execute_train,
            }
            row = spawn_memory(spec, args)
            train_rows.append(row)
            print(json.dumps(row), flush=True)

    # The (sweep, size, chunk) cells; a frame in both sweeps is measured once.
    cells = [("size", size, frame_chunk) for size in args.sizes]
    cells += [("chunk", args.chunk_frame, chunk) for chunk in args.chunks]
    results: dict[tuple[int, int], dict] = {}
    chunk_figures: dict[int, dict | None] = {}
    for _, size, chunk in cells:
        execute = size * size <= max_rays
        if (size, chunk) in results or (not execute and chunk in chunk_figures):
            continue
        row = spawn_memory({"kind": "render", "size": size, "chunk": chunk, "execute": execute}, args)
        print(json.dumps(row), flush=True)
        chunk_figures.setdefault(chunk, row.get("compiled"))
        if execute:
            results[(size, chunk)] = row
    render_rows = []
    for sweep, size, chunk in cells:
        rays = size * size
        row = dict(results.get((size, chunk), {"executed": False}))
        compiled = row.get("compiled") or chunk_figures.get(chunk)
        ray_table = rays * 12 * 4  # origins, directions, viewdirs (3 each), radii, near, far: float32
        row.update(
            sweep=sweep,
            size=size,
            chunk=chunk,
            rays=rays,
            calls=-(-rays // chunk),
            compiled=compiled,
            ray_table_bytes=row.get("ray_table_bytes", ray_table),
        )
        if compiled is not None:
            row["estimate_bytes"] = compiled["xla_total_bytes"] + 2 * row["ray_table_bytes"]
        render_rows.append(row)

    where = f"{machine['device_kind']} ({machine['backend']})"
    print(f"\n{where}, {machine['cpu_count']} CPUs, jax {machine['jax']}")
    print(
        f"MLP {config['mlp']}, {'+'.join(map(str, config['samples']))} samples; MiB = 2^20 bytes; "
        "'n/a': not measured (compiled only) or not available on this platform"
    )
    if train_rows:
        print(
            f"\n(a) one training step, {config['batch_size']} rays, ray table of {args.train_views} "
            f"synthetic {args.train_image_size}x{args.train_image_size} views\n"
        )
        train_table(train_rows)
    print("\n(b) one frame with render_rays; frame estimate = XLA chunk total + 2 x ray table")
    if max_rays < sys.maxsize:
        print(f"frames over {max_rays:,} rays compiled only")
    print()
    render_table(render_rows)
    print()

    payload = {
        "args": {k: v for k, v in vars(args).items() if k not in ("handler", "one")},
        "machine": machine,
        "config": config,
        "max_execute_rays": None if max_rays == sys.maxsize else max_rays,
        "figures": {
            "compiled": "XLA memory_analysis() of the compiled function; an estimate, nothing run",
            "compiled.xla_total_bytes": "arguments + outputs + temporaries - aliases, from memory_analysis()",
            "estimate_bytes": "a frame: the render chunk's XLA total + 2 x the frame's ray table",
            "measured.device_after.peak_bytes_in_use": "device allocator peak over the subprocess' life",
            "measured.host_rss_peak_bytes": "host RSS high-water mark during the measured work (Linux)",
            "host_rss_process_peak_bytes": "host RSS high-water mark over the subprocess' life (wait4)",
        },
        "train": train_rows,
        "render": render_rows,
    }
    harness.write_json(default_out(args.out, "memory", "gpu" if on_gpu else machine["backend"]), payload)


# ============================================================================ command line


# ============================================================================ quickstart


QUICKSTART_COMMAND = ("-m", "mixnerf_eqx.train", "--no-progress")


def quickstart_trees(revisions: list[str], scratch: Path) -> list[tuple[str, Path]]:
    """`(label, source tree)` for this working tree and each git revision, checked out into
    `scratch` with `git worktree` (removed again by `remove_trees`)."""
    repo = Path(SCRIPT).parent.parent
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
    repo = Path(SCRIPT).parent.parent
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


def run_quickstart(args: argparse.Namespace) -> None:
    """The README's first command, `python -m mixnerf_eqx.train --no-progress`, timed end to end
    (install excluded) in this working tree and at each `--against` git revision, seed by seed.

    Every run is a fresh process with a fresh run folder under `--runs-root`, one after another
    in the order working tree, revisions, for each seed in turn, so that the machine's state
    drifts alike for all; with `--repeat-cached` each tree runs the first seed once more with
    the compilation cache its first run filled (`JAX_COMPILATION_CACHE_DIR`); other runs have
    no cache. The table gives wall time, the
    median step time (from `train_log.jsonl`, steps after the 20th), the step-time ratio to the
    first revision, and the test metrics; `section.key=value` overrides apply to every run.
    """
    import shutil
    import tempfile

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
    harness.write_json(default_out(args.out, "quickstart"), payload)


def main() -> None:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    commands = parser.add_subparsers(dest="command", required=True)

    step = commands.add_parser(
        "step",
        help="seconds per training step",
        description=inspect.cleandoc(run_step.__doc__),
        formatter_class=raw,
    )
    add_common(step, None, "step_time")
    step.add_argument("--repeats", type=int, default=2, help="timed steps per variant (default 2)")
    step.add_argument(
        "--variants",
        nargs="+",
        type=step_variant,
        default=["bare-mlp", "mixnerf", "mipnerf", "mixnerf-nocheck"],
        help="bare-mlp, mixnerf, mipnerf, mixnerf-colour-only, mixnerf-bf16; '-nocheck': shape checks off",
    )
    step.set_defaults(handler=run_step)

    profile = commands.add_parser(
        "profile",
        help="a step's time, part by part",
        description=inspect.cleandoc(run_profile.__doc__),
        formatter_class=raw,
    )
    add_common(profile, None, "profile_step")
    profile.add_argument("--repeats", type=int, default=5, help="timed calls per row (default 5)")
    profile.add_argument("--narrow-width", type=int, default=8, help="MLP width of the 'width-N field' rows")
    profile.set_defaults(handler=run_profile)

    typecheck = commands.add_parser(
        "typecheck",
        help="what the runtime shape checks cost",
        description=inspect.cleandoc(run_typecheck.__doc__),
        formatter_class=raw,
    )
    add_common(typecheck, "configs/builtin.toml", "typecheck_overhead")
    typecheck.add_argument("--steps", type=int, default=20, help="timed steps after the first (default 20)")
    typecheck.add_argument("--rounds", type=int, default=2, help="processes per setting (default 2)")
    typecheck.add_argument("--one", choices=["on", "off"], help=argparse.SUPPRESS)
    typecheck.set_defaults(handler=run_typecheck)

    memory = commands.add_parser(
        "memory",
        help="peak memory of a step and of rendering",
        description=inspect.cleandoc(run_memory.__doc__),
        formatter_class=raw,
    )
    add_common(memory, None, "memory")
    memory.add_argument("--sizes", type=int, nargs="+", default=[100, 400, 800, 1600], help="square frames")
    memory.add_argument("--frame-chunk", type=int, default=None, help="chunk of the size sweep")
    memory.add_argument("--chunks", type=int, nargs="+", default=[1024, 4096, 16384])
    memory.add_argument("--chunk-frame", type=int, default=400, help="frame size of the chunk sweep")
    memory.add_argument("--max-execute-rays", type=int, default=None, help="larger frames: compiled only")
    memory.add_argument("--execute-train", choices=["auto", "yes", "no"], default="auto")
    memory.add_argument("--skip-train", action="store_true")
    memory.add_argument("--train-views", type=int, default=4, help="synthetic training views")
    memory.add_argument("--train-image-size", type=int, default=400, help="their size in pixels, square")
    memory.add_argument("--one", default=None, help=argparse.SUPPRESS)  # one measurement, in a subprocess
    memory.set_defaults(handler=run_memory)

    quickstart = commands.add_parser(
        "quickstart",
        help="the README's first command, timed, here and at git revisions",
        description=inspect.cleandoc(run_quickstart.__doc__),
        formatter_class=raw,
    )
    quickstart.add_argument("--against", nargs="*", default=[], help="git revisions to time alongside")
    quickstart.add_argument("--seeds", type=int, nargs="+", default=[0], help="train.seed of each run")
    quickstart.add_argument(
        "--repeat-cached", action="store_true", help="also run with a filled compile cache"
    )
    quickstart.add_argument("--runs-root", default=None, help="run folders (default: a temporary folder)")
    quickstart.add_argument(
        "--out", default=None, help="JSON path (default: results/quickstart_<backend>.json)"
    )
    quickstart.add_argument("overrides", nargs="*", help="config overrides for every run, section.key=value")
    quickstart.set_defaults(handler=run_quickstart)

    args = parser.parse_args()
    args.handler(args)


if __name__ == "__main__":
    main()
