"""Where a training step's time goes: the step against its parts, each compiled and timed alone.

    python benchmarks/profile_step.py                       # the paper's step (4096 rays, 128+128, 8x256)
    python benchmarks/profile_step.py train.batch_size=512  # a CPU-sized batch of the same model

Every row is one jitted function on the step's own shapes, compiled first and then timed
`--repeats` times to completion (`block_until_ready`); the median is reported with its share
of the full step. All rows run in one process, one after another, so their ratios are
comparable. The rows:

- `step`: the library's training step (`make_train_step`): batch draw, sample-space
  annealing, render, loss, gradient, optimiser, non-finite guard.
- `loss + gradient`: the same without the optimiser and the guard.
- `loss forward`: the render and the loss, no gradient.
- `field forward + backward`: the MLP (with its encodings) alone over the step's points, its
  outputs summed: the ceiling of `step_time.py`.
- `field forward`: the same without the gradient.
- `step, width-8 field`: the whole step with the MLP shrunk to width 8 (encodings, layer count
  and everything else unchanged): what the step costs besides the dense layers' products.
- the parts outside the field, on random inputs of the step's shapes: `random numbers`
  (per-ray and per-sample keys, jitter and density noise as the model draws them), `coarse
  samples` (stratified edges and frustum Gaussians), `fine samples` (resampling from the
  coarse weights), `compositing` (both levels' weights, colour, depth and opacity, forward +
  backward), `mixture NLLs` (the terms the config weights, forward + backward), `optimiser`
  (clipping and Adam over the model's parameters), `batch draw`.

Outputs: a printed markdown table and `benchmarks/results/profile_step_<tag>.json`.
"""

import argparse
import dataclasses
import json
import platform
import statistics
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

from mixnerf_eqx import build_model, load_config
from mixnerf_eqx._field import FieldOutputs
from mixnerf_eqx._loss import _level_nlls, loss_fn
from mixnerf_eqx._schedule import anneal_sample_space
from mixnerf_eqx._train import draw_batch, make_optimizer, make_train_step, training_rays
from mixnerf_eqx.data import load_dataset

RESULTS = Path(__file__).resolve().parent / "results"


def timed(fn, *args, repeats: int) -> dict:
    """Compile (first call) and the median of `repeats` further calls, each to completion."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return {"first_call_s": first, "median_s": statistics.median(times), "times_s": times}


def field_points(config, key) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Random Gaussians and view directions, as many as a training step evaluates."""
    count = config.train.batch_size * (config.model.num_coarse_samples + config.model.num_fine_samples)
    keys = jax.random.split(key, 3)
    means = jax.random.normal(keys[0], (count, 3))
    covs = 1e-4 * jnp.abs(jax.random.normal(keys[1], (count, 3)))
    viewdirs = jax.random.normal(keys[2], (count, 3))
    return means, covs, viewdirs / jnp.linalg.norm(viewdirs, axis=-1, keepdims=True)


def field_rows(config, model, repeats: int) -> dict[str, dict]:
    means, covs, viewdirs = field_points(config, jax.random.key(2))
    noise_keys = jax.random.split(jax.random.key(3), means.shape[0])

    def outputs_sum(field, means, covs, viewdirs, keys):
        out = jax.vmap(lambda m, c, v, k: field(m, c, v, key=k))(means, covs, viewdirs, keys)
        return sum(jnp.sum(x) for x in jax.tree_util.tree_leaves(out))

    forward = eqx.filter_jit(outputs_sum)
    forward_backward = eqx.filter_jit(eqx.filter_grad(outputs_sum))
    args = (model.field, means, covs, viewdirs, noise_keys)
    return {
        "field forward + backward": timed(forward_backward, *args, repeats=repeats),
        "field forward": timed(forward, *args, repeats=repeats),
    }


def part_rows(config, model, data, optimizer, repeats: int) -> dict[str, dict]:
    """The parts of a step outside the field, each on inputs of the step's shapes."""
    batch = config.train.batch_size
    n_coarse, n_fine = config.model.num_coarse_samples, config.model.num_fine_samples
    rays, target = draw_batch(data, batch, key=jax.random.key(4))
    keys = jax.random.split(jax.random.key(5), 8)
    rows = {}

    @eqx.filter_jit
    def random_numbers(key):
        # As `MixNeRF.__call__`/`render_ray`/`_render_level` and the samplers draw them.
        def per_ray(k):
            k = jax.random.split(k, 4)
            coarse_jitter = jax.random.uniform(k[0], (n_coarse + 1,))
            fine_jitter = jax.random.uniform(k[2], (n_fine + 1,))
            noise = [
                jax.vmap(lambda s: jax.random.normal(s, ()))(jax.random.split(k[i], n))
                for i, n in ((1, n_coarse), (3, n_fine))
            ]
            return coarse_jitter, fine_jitter, *noise

        return jax.vmap(per_ray)(jax.random.split(key, batch))

    rows["random numbers"] = timed(random_numbers, keys[0], repeats=repeats)

    sample_keys = jax.random.split(keys[1], batch)
    coarse = eqx.filter_jit(jax.vmap(lambda s, r, k: s(r, key=k), in_axes=(None, 0, 0)))
    rows["coarse samples"] = timed(coarse, model.coarse_sampler, rays, sample_keys, repeats=repeats)
    coarse_samples = coarse(model.coarse_sampler, rays, sample_keys)

    coarse_weights = jax.random.dirichlet(keys[2], jnp.ones(n_coarse), (batch,))
    fine = eqx.filter_jit(jax.vmap(lambda s, r, e, w, k: s(r, e, w, key=k), in_axes=(None, 0, 0, 0, 0)))
    rows["fine samples"] = timed(
        fine, model.fine_sampler, rays, coarse_samples.t_edges, coarse_weights, sample_keys, repeats=repeats
    )
    fine_samples = fine(model.fine_sampler, rays, coarse_samples.t_edges, coarse_weights, sample_keys)

    def random_outputs(key, n):
        k = jax.random.split(key, 4)
        mixture = model.mixture is not None
        return FieldOutputs(
            density=jax.random.exponential(k[0], (batch, n)),
            rgb=jax.random.uniform(k[1], (batch, n, 3)),
            beta=jax.random.uniform(k[2], (batch, n, 3), minval=0.01, maxval=1.0) if mixture else None,
            ray_depth=jax.random.uniform(k[3], (batch, n), minval=1.0, maxval=6.0) if mixture else None,
        )

    levels = (
        (random_outputs(keys[3], n_coarse), coarse_samples.t_edges),
        (random_outputs(keys[4], n_fine), fine_samples.t_edges),
    )

    def composite_loss(levels, renderer, rays, target):
        total = 0.0
        for outputs, edges in levels:
            level = jax.vmap(renderer)(outputs, edges, rays)
            total = total + jnp.mean((level.rgb - target) ** 2) + jnp.mean(level.depth) + jnp.mean(level.acc)
        return total

    rows["compositing (forward + backward)"] = timed(
        eqx.filter_jit(eqx.filter_grad(composite_loss)), levels, model.renderer, rays, target, repeats=repeats
    )

    weights = config.loss.weights()
    if model.mixture is not None and weights.uses_mixture:
        level = jax.vmap(model.renderer)(levels[0][0], levels[0][1], rays)
        direction_norm = jnp.linalg.norm(rays.directions, axis=-1)

        def nll_total(level, model):
            colour, depth, regen = _level_nlls(model, level, target, direction_norm, weights)
            return colour + weights.depth_nll * depth + weights.regen_nll * regen

        rows["mixture NLLs (forward + backward)"] = timed(
            eqx.filter_jit(eqx.filter_grad(nll_total)), level, model, repeats=repeats
        )

    params = eqx.filter(model, eqx.is_array)
    opt_state = optimizer.init(params)

    @eqx.filter_jit
    def optimiser_step(grads, opt_state, model):
        updates, opt_state = optimizer.update(grads, opt_state, eqx.filter(model, eqx.is_array))
        return eqx.apply_updates(model, updates), opt_state

    grads = jax.tree_util.tree_map(lambda x: 1e-3 * jnp.ones_like(x), params)
    rows["optimiser"] = timed(optimiser_step, grads, opt_state, model, repeats=repeats)

    @eqx.filter_jit
    def batch_draw(data, key, step):
        rays, target = draw_batch(data, batch, key=key)
        train = config.train
        return anneal_sample_space(
            rays, step, train.anneal_steps, train.anneal_start, train.anneal_mid
        ), target

    rows["batch draw"] = timed(batch_draw, data, keys[5], jnp.asarray(7, jnp.int32), repeats=repeats)
    return rows


def step_rows(config, model, data, optimizer, repeats: int) -> dict[str, dict]:
    rows = {}
    step_fn = make_train_step(config, optimizer)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_array))
    key, step = jax.random.key(1), jnp.asarray(100, jnp.int32)
    rows["step"] = timed(step_fn, model, opt_state, data, step, key, repeats=repeats)

    rays, target = draw_batch(data, config.train.batch_size, key=jax.random.key(6))
    lambda_colour, weights = jnp.asarray(0.5), config.loss.weights()

    def loss(model, rays, target, lambda_colour, key):
        return loss_fn(model, rays, target, lambda_colour, weights, key=key)[0]

    rows["loss + gradient"] = timed(
        eqx.filter_jit(eqx.filter_value_and_grad(loss)),
        model,
        rays,
        target,
        lambda_colour,
        key,
        repeats=repeats,
    )
    rows["loss forward"] = timed(
        eqx.filter_jit(loss), model, rays, target, lambda_colour, key, repeats=repeats
    )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=None, help="TOML config (default: the paper's settings)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--narrow-width", type=int, default=8, help="MLP width of the 'width-8 field' row")
    parser.add_argument(
        "--out", default=None, help="JSON path (default: results/profile_step_<backend>.json)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides, KEY=VALUE")
    args = parser.parse_args()

    config = load_config(args.config, args.overrides)
    data = training_rays(load_dataset(config.data))
    model = build_model(config, key=jax.random.key(0))
    optimizer = make_optimizer(config)

    rows = step_rows(config, model, data, optimizer, args.repeats)
    rows.update(field_rows(config, model, args.repeats))
    width = args.narrow_width
    narrow = load_config(args.config, [*args.overrides, f"model.width={width}", f"model.view_width={width}"])
    narrow_model = build_model(narrow, key=jax.random.key(0))
    narrow_rows = step_rows(narrow, narrow_model, data, make_optimizer(narrow), args.repeats)
    rows[f"step, width-{width} field"] = narrow_rows["step"]
    rows[f"field forward + backward, width {width}"] = field_rows(narrow, narrow_model, args.repeats)[
        "field forward + backward"
    ]
    rows.update(part_rows(config, model, data, optimizer, args.repeats))

    step_s = rows["step"]["median_s"]
    m = config.model
    print(
        f"\n{config.train.batch_size} rays, {m.num_coarse_samples}+{m.num_fine_samples} samples, "
        f"MLP {m.depth}x{m.width}, matmul {m.matmul_dtype}, remat {m.remat}; {jax.devices()}"
    )
    print("\n| part | ms (median) | share of the step | first call s |")
    print("|---|---|---|---|")
    for name, row in rows.items():
        row["share_of_step"] = row["median_s"] / step_s
        cells = (
            name,
            f"{1e3 * row['median_s']:.2f}",
            f"{row['share_of_step']:.3f}",
            f"{row['first_call_s']:.2f}",
        )
        print("| " + " | ".join(cells) + " |")
    ceiling = rows["field forward + backward"]["median_s"]
    print(f"\nstep throughput as a fraction of the field's forward + backward: {ceiling / step_s:.3f}")

    out = Path(args.out) if args.out else RESULTS / f"profile_step_{jax.default_backend()}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "config": args.config,
        "overrides": args.overrides,
        "model": dataclasses.asdict(config.model),
        "batch_size": config.train.batch_size,
        "machine": {
            "platform": platform.platform(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
        },
        "rows": rows,
        "fraction_of_field_forward_backward": ceiling / step_s,
    }
    out.write_text(json.dumps(record, indent=2))
    print(f"wrote {out.relative_to(Path.cwd()) if out.is_relative_to(Path.cwd()) else out.name}")


if __name__ == "__main__":
    main()
