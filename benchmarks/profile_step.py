"""Where a training step's time goes: the step against its parts, each compiled and timed alone.

    python benchmarks/profile_step.py   # where a step's time goes, part by part

Every row is one jitted function on the step's own shapes, compiled first and then timed
`--repeats` times, each waited for; the fastest call and the median are reported, with the
fastest call's share of the full step. All rows run in one process, one after another, so
their ratios are comparable:

- `step`: the batch draw and the library's training step (`make_train_step`: sample-space
  annealing, render, loss, gradient, optimiser, non-finite guard) in one function.
- `loss + gradient`: `loss_fn` and its gradient, without optimiser and guard.
- `loss forward`: the render and the loss, no gradient.
- `field forward + backward`: the MLP (with its encodings) alone over the step's points,
  its outputs summed: the ceiling of `step_time.py`; `field forward`: without gradient.
  For a grid field, `encoding forward (+ backward)`: the grid lookups alone at as many
  points, as the field reads them (`grid.lookup`); the decoder is the difference.
- `step, width-N field`: the whole step with the MLP shrunk to `--narrow-width`
  (encodings, layer count and everything else unchanged): what the step costs besides
  the dense layers' products.
- the parts outside the field, on random inputs of the step's shapes: `random numbers`
  (per-ray and per-sample keys, jitter and density noise as the model draws them),
  `coarse samples`, `fine samples` (resampling from coarse weights), `compositing`
  (both levels, forward + backward), the `loss terms` (`mx.training.loss_terms` on rendered levels,
  forward + backward: the MSE alone, each NLL the config weights added alone, then all of
  them), `optimiser` (clipping and Adam), `batch draw` (with the annealing).

Takes `--config FILE` (default: the paper's settings, 4096 rays, 128 + 128 samples, 8 x 256
MLP), `section.key=value` overrides and `--out PATH` (default
`benchmarks/results/profile_step_<backend>.json`). The JSON records the command and the
machine (`harness.write_json`); the table is printed as markdown.
"""

import argparse
import dataclasses
import statistics
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import harness
import jax
import jax.numpy as jnp

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, load_dataset


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
    state = mx.training.init_train_state(config, dataset)
    data = mx.training.training_rays(dataset)
    batch_size = config.train.batch_size
    step_fn = mx.training.make_train_step(config)

    @eqx.filter_jit
    def draw_and_step(data, state):
        return step_fn(state, mx.training.draw_batch(data, state, batch_size))

    rows = {"step": timed(draw_and_step, data, state, repeats=repeats)}
    if not loss:
        return rows
    batch = eqx.filter_jit(mx.training.draw_batch)(data, state, batch_size)
    weights = mx.training.LossWeights.from_config(config.loss, config.method)
    lambda_colour, key = jnp.asarray(0.5), jax.random.key(1)

    def total(model, rays, rgb, lambda_colour, key):
        return mx.training.loss_fn(model, rays, rgb, lambda_colour, weights, key=key)[0]

    args = (state.model, batch.rays, batch.rgb, lambda_colour, key)
    rows["loss + gradient"] = timed(eqx.filter_jit(eqx.filter_value_and_grad(total)), *args, repeats=repeats)
    rows["loss forward"] = timed(eqx.filter_jit(total), *args, repeats=repeats)
    return rows


def summed_encoding(field: mx.nn.GridField, points: jax.Array) -> jax.Array:
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
    points = harness.field_points(config, jax.random.key(2))
    rows = {
        "field forward + backward": timed(
            eqx.filter_jit(eqx.filter_grad(harness.summed_field)), model, *points, repeats=repeats
        ),
        "field forward": timed(eqx.filter_jit(harness.summed_field), model, *points, repeats=repeats),
    }
    if isinstance(model.field, mx.nn.GridField):
        unit = jnp.clip(points[0] / 2.0, -1.0, 1.0)
        rows["encoding forward + backward"] = timed(
            eqx.filter_jit(eqx.filter_grad(summed_encoding)), model.field, unit, repeats=repeats
        )
        rows["encoding forward"] = timed(eqx.filter_jit(summed_encoding), model.field, unit, repeats=repeats)
    return rows


def random_field_outputs(model: mx.MixNeRF, key: jax.Array, batch: int, samples: int) -> mx.nn.FieldOutputs:
    keys = jax.random.split(key, 4)
    mixture = model.mixture is not None
    return mx.nn.FieldOutputs(
        density=jax.random.exponential(keys[0], (batch, samples)),
        rgb=jax.random.uniform(keys[1], (batch, samples, 3)),
        beta=jax.random.uniform(keys[2], (batch, samples, 3), minval=0.01, maxval=1.0) if mixture else None,
        ray_depth=jax.random.uniform(keys[3], (batch, samples), minval=1.0, maxval=6.0) if mixture else None,
    )


def part_rows(config: mx.Config, dataset: Dataset, repeats: int) -> dict[str, dict]:
    """The parts of a step outside the field, each on inputs of the step's shapes."""
    state = mx.training.init_train_state(config, dataset)
    model = state.model
    data = mx.training.training_rays(dataset)
    batch_size = config.train.batch_size
    n_coarse, n_fine = config.model.num_coarse_samples, config.model.num_fine_samples
    batch = eqx.filter_jit(mx.training.draw_batch)(data, state, batch_size)
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
    outputs = mx.nn.RenderOutputs(coarse=coarse_level, fine=fine_level)
    weights = mx.training.LossWeights.from_config(config.loss, config.method)
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
            return mx.training.loss_terms(outputs, model, rays, target, lambda_colour, row_weights).total

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
        batch = mx.training.draw_batch(data, state, batch_size)
        train = config.train
        rays = mx.training.anneal_sample_space(batch.rays, 7, train.anneal_steps, train.anneal_start, train.anneal_mid)
        return rays, batch.rgb

    rows["batch draw"] = timed(batch_draw, data, state, repeats=repeats)
    return rows


def run(args: argparse.Namespace) -> None:
    """Times the step and its parts and writes the result (see the module docstring)."""
    config = mx.load_config(args.config, args.overrides)
    dataset = load_dataset(config.data)
    rows = step_rows(config, dataset, args.repeats)
    rows.update(field_rows(config, mx.training.init_train_state(config, dataset).model, args.repeats))
    width = args.narrow_width
    widths = (
        [f"grid.decoder_width={width}", f"grid.view_width={width}"]
        if config.model.field == "grid"
        else [f"mlp.width={width}", f"mlp.view_width={width}"]
    )
    narrow = mx.load_config(args.config, [*args.overrides, *widths])
    rows[f"step, width-{width} field"] = step_rows(narrow, dataset, args.repeats, loss=False)["step"]
    narrow_model = mx.training.init_train_state(narrow, dataset).model
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
        lookup = mx.training.init_train_state(config, dataset).model.field.lookup
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
    harness.write_json(harness.default_out(args.out, "profile_step"), payload)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    harness.add_common(parser, None, "profile_step")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per row (default 5)")
    parser.add_argument("--narrow-width", type=int, default=8, help="MLP width of the 'width-N field' rows")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    run(parse_args(argv))


if __name__ == "__main__":
    main()
