"""Could the predictive pass's colour quantiles be solved more cheaply than by bisection?

Two ways, each measured against what it would replace (`../uncertainty.md`, "Where the
predictive pass's time goes"):

- fewer steps: Newton's method started from the mixture's distribution function tabulated at
  the components' sorted locations (which brackets every level between two adjacent
  locations), safeguarded by that bracket, on the function itself or on its log (below the
  median; its complement's log above), then one plain Newton step kept in the bracket (7
  sums over the components per level, against the bisection's 24). Printed: the largest
  distance, over 2,000 random mixtures of 32 components and 9 levels, to a float64 bisection,
  against the shipped solver's.
- fewer components (`--run RUN`): how many of a trained model's coarse components a ray needs
  for the mass it drops to stay under a bound, on the run's first test view.
- less bookkeeping (`--loop`): the shipped solve (optimistix's bisection, vmapped over levels,
  channels and rays) against the same 24 halvings of the same bracket in one fixed-count loop
  over whole arrays, on one chunk of 4096 random rays of 32 components, 9 levels and 3
  channels: their largest difference and the median of 5 timings each, in one process.

    python benchmarks/experiments/quantile_newton.py
    python benchmarks/experiments/quantile_newton.py --run runs/SWEEP/fern/seed_2 --data-dir ../shared/data
    python benchmarks/experiments/quantile_newton.py --loop
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import rays_for_views

LEVELS = np.array([0.5, 0.25, 0.1, 0.05, 0.025, 0.75, 0.9, 0.95, 0.975], np.float32)
# name: (the coefficients' Dirichlet concentration, the scales' range (log-uniform), clustered)
CASES = {
    "Dirichlet 1, scales 0.01 to 0.5 (like the test suite's)": (1.0, (0.01, 0.5), False),
    "Dirichlet 0.05, scales 0.001 to 0.5": (0.05, (0.001, 0.5), False),
    "Dirichlet 0.05, scales 1e-4 to 0.01": (0.05, (1e-4, 1e-2), False),
    "Dirichlet 1, scales 0.2 to 3": (1.0, (0.2, 3.0), False),
    "Dirichlet 0.01, scales 1e-5 to 1": (0.01, (1e-5, 1.0), False),
    "Dirichlet 0.3, scales 0.001 to 0.05, locations in 5 clusters": (0.3, (1e-3, 0.05), True),
}


def _inverse_scale(scale):
    return jnp.exp(-jnp.log(jnp.maximum(scale, jnp.finfo(scale.dtype).tiny)))


def _laplace_quantile(level, location, scale):
    return location + scale * jnp.where(level < 0.5, jnp.log(2.0 * level), -jnp.log(2.0 - 2.0 * level))


def _terms(x, coefficients, location, inverse_scale):
    tail = 0.5 * jnp.exp(-jnp.abs(x - location) * inverse_scale)
    below = x < location
    cdf = jnp.sum(coefficients * jnp.where(below, tail, 1.0 - tail))
    survival = jnp.sum(coefficients * jnp.where(below, 1.0 - tail, tail))
    return cdf, survival, jnp.sum(coefficients * tail * inverse_scale)


def newton_quantiles(levels, coefficients, location, scale, steps: int, in_logs: bool):
    inverse = _inverse_scale(scale)
    present = coefficients > 0
    component = _laplace_quantile(levels[:, None], location, scale)
    outer_low = jnp.min(jnp.where(present, component, jnp.inf), axis=-1)
    outer_high = jnp.max(jnp.where(present, component, -jnp.inf), axis=-1)
    nodes = jnp.sort(location)
    table = jax.vmap(lambda x: _terms(x, coefficients, location, inverse)[0])(nodes)
    count = nodes.shape[0]
    index = jnp.searchsorted(table, levels)
    left, right = jnp.maximum(index - 1, 0), jnp.minimum(index, count - 1)
    inside = (index > 0) & (index < count)
    low = jnp.where(index > 0, jnp.maximum(nodes[left], outer_low), outer_low)
    high = jnp.where(index < count, jnp.minimum(nodes[right], outer_high), outer_high)
    fraction = jnp.clip((levels - table[left]) / jnp.maximum(table[right] - table[left], 1e-30), 0.0, 1.0)
    start = jnp.where(
        inside, nodes[left] + fraction * (nodes[right] - nodes[left]), jnp.where(index == 0, high, low)
    )
    evaluate = jax.vmap(_terms, in_axes=(0, None, None, None))

    def step(_, state):
        x, low, high = state
        cdf, survival, density = evaluate(x, coefficients, location, inverse)
        residual = cdf - levels
        low, high = jnp.where(residual < 0, x, low), jnp.where(residual >= 0, x, high)
        if in_logs:
            proposal = jnp.where(
                levels < 0.5,
                x - (jnp.log(cdf) - jnp.log(levels)) * cdf / density,
                x + (jnp.log(survival) - jnp.log1p(-levels)) * survival / density,
            )
        else:
            proposal = x - residual / density
        accepted = (proposal > low) & (proposal < high)
        return jnp.where(accepted, proposal, 0.5 * (low + high)), low, high

    x, low, high = jax.lax.fori_loop(0, steps, step, (jnp.clip(start, low, high), low, high))
    # A last plain Newton step, kept inside the bracket the steps have narrowed.
    cdf, _, density = evaluate(x, coefficients, location, inverse)
    return jnp.clip(x - (cdf - levels) / density, low, high)


def float64_quantiles(levels, coefficients, location, scale):
    """Bisection on [-1e3, 1e3] in float64, 200 halvings, every ray at once."""
    coefficients, location, scale = (
        np.asarray(a, np.float64)[:, None, :] for a in (coefficients, location, scale)
    )
    low = np.full((coefficients.shape[0], levels.size), -1e3)
    high = np.full_like(low, 1e3)
    for _ in range(200):
        middle = 0.5 * (low + high)
        z = (middle[..., None] - location) / scale
        cdf = np.sum(
            coefficients
            * np.where(z < 0, 0.5 * np.exp(np.minimum(z, 0)), 1 - 0.5 * np.exp(-np.maximum(z, 0))),
            -1,
        )
        below = cdf < levels
        low, high = np.where(below, middle, low), np.where(below, high, middle)
    return 0.5 * (low + high)


def accuracy(rays: int = 2000, components: int = 32) -> None:
    rng = np.random.default_rng(0)
    levels = jnp.asarray(LEVELS)
    # The shipped solver, through the public mixture: one channel per mixture, every level.
    shipped = jax.jit(
        lambda c, m, b: (
            mx.uncertainty.ColourMixture(c, m[..., None], b[..., None])
            .channel_quantiles(levels[:, None])[..., 0]
            .T
        )
    )
    print(
        "| mixtures (coefficients' Dirichlet concentration, scales) | shipped bisection "
        "| Newton, 6 steps | Newton on the logs, 6 steps |"
    )
    print("|---|---|---|---|")
    for name, (concentration, (smallest, largest), clustered) in CASES.items():
        coefficients = rng.dirichlet(np.full(components, concentration), size=rays).astype(np.float32)
        coefficients /= coefficients.sum(-1, keepdims=True)
        location = rng.uniform(0, 1, (rays, components))
        if clustered:
            location = np.round(location * 4) / 4 + rng.normal(0, 1e-4, location.shape)
        scale = np.exp(rng.uniform(np.log(smallest), np.log(largest), (rays, components)))
        arrays = [jnp.asarray(a, jnp.float32) for a in (coefficients, location, scale)]
        reference = float64_quantiles(LEVELS.astype(np.float64), *(np.asarray(a) for a in arrays))
        errors = [np.abs(np.asarray(shipped(*arrays)) - reference).max()]
        for in_logs in (False, True):
            solve = jax.jit(
                jax.vmap(lambda c, m, b, in_logs=in_logs: newton_quantiles(levels, c, m, b, 6, in_logs))
            )
            errors.append(np.abs(np.asarray(solve(*arrays)) - reference).max())
        print(f"| {name} | " + " | ".join(f"{error:.1e}" for error in errors) + " |")


def components_needed(run_dir: str, data_dir: str | None) -> None:
    run = mx.runs.restore_run(run_dir, data_dir=data_dir)
    dataset = run.dataset
    rays = rays_for_views(dataset.test.select([0]), dataset.near, dataset.far).reshape(-1)
    coefficients = np.sort(
        np.asarray(mx.uncertainty.collect_mixtures(run.model, rays, 4096).coefficients), -1
    )
    count = coefficients.shape[-1]
    dropped_mass = np.cumsum(coefficients, -1)  # the smallest j + 1 components' mass
    for bound in (1e-7, 1e-6, 1e-5, 1e-4):
        needed = count - (dropped_mass <= bound).sum(-1)
        per_chunk = needed[: needed.size // 4096 * 4096].reshape(-1, 4096).max(-1)
        print(
            f"dropped mass <= {bound:g}: a ray needs {np.median(needed):.0f} of {count} components (median), "
            f"{np.quantile(needed, 0.99):.0f} (99th percentile); "
            f"a 4096-ray chunk {per_chunk.min()} to {per_chunk.max()}"
        )


def loop_quantiles(levels, coefficients, location, scale, steps: int = 24):
    """The shipped bisection's bracket and halvings, for every level, ray and channel at once:
    `(levels,)`, `(rays, S)`, `(rays, S, C)` -> `(levels, rays, C)`."""
    inverse = _inverse_scale(scale)[None]
    component = _laplace_quantile(levels[:, None, None, None], location[None], scale[None])
    present = (coefficients > 0)[None, :, :, None]
    low = jnp.min(jnp.where(present, component, jnp.inf), axis=2)
    high = jnp.max(jnp.where(present, component, -jnp.inf), axis=2)
    weights = coefficients[None, :, :, None]

    def halve(_, bracket):
        low, high = bracket
        middle = 0.5 * (low + high)
        tail = 0.5 * jnp.exp(-jnp.abs(middle[:, :, None] - location[None]) * inverse)
        cdf = jnp.sum(weights * jnp.where(middle[:, :, None] < location[None], tail, 1.0 - tail), axis=2)
        below = cdf < levels[:, None, None]
        return jnp.where(below, middle, low), jnp.where(below, high, middle)

    low, high = jax.lax.fori_loop(0, steps, halve, (low, high))
    return 0.5 * (low + high)


def loop_timing(rays: int = 4096, components: int = 32) -> None:
    rng = np.random.default_rng(0)
    coefficients = jnp.asarray(rng.dirichlet(np.ones(components), rays), jnp.float32)
    location = jnp.asarray(rng.uniform(0, 1, (rays, components, 3)), jnp.float32)
    scale = jnp.asarray(np.exp(rng.uniform(np.log(0.01), np.log(0.5), (rays, components, 3))), jnp.float32)
    levels = jnp.asarray(LEVELS)
    mixture = mx.uncertainty.ColourMixture(coefficients, location, scale)
    shipped = jax.jit(lambda m: m.quantiles(levels))
    loop = jax.jit(loop_quantiles)
    solves = {
        "shipped": lambda: shipped(mixture),
        "fixed-count loop": lambda: loop(levels, coefficients, location, scale),
    }
    answers = {name: np.asarray(solve().block_until_ready()) for name, solve in solves.items()}
    print(f"largest difference: {np.abs(answers['shipped'] - answers['fixed-count loop']).max():.1e}")
    for name, solve in solves.items():
        seconds = []
        for _ in range(5):
            started = time.perf_counter()
            solve().block_until_ready()
            seconds.append(time.perf_counter() - started)
        print(f"{name}: {np.median(seconds):.3f} s per chunk of {rays} rays (median of 5)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", default=None, help="a trained run: count the components its rays need")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument(
        "--loop", action="store_true", help="time the shipped solve against a fixed-count loop"
    )
    args = parser.parse_args()
    if args.loop:
        loop_timing()
    elif args.run:
        components_needed(args.run, args.data_dir)
    else:
        accuracy()


if __name__ == "__main__":
    main()
