"""Worst error against float64 numpy references over extreme inputs, as a markdown table.

    python benchmarks/stress_table.py [--out PATH]

Each case draws a fixed set of random extreme inputs (seeded), evaluates the package's public
functions in the stated dtype, and reports the largest error against a float64 reference
written below from the equations (absolute for quantities in [0, 1], relative to
`1 + |NLL| + largest component term` for NLLs), and whether every value and every `jax.grad`
gradient was finite. `tests/test_stress.py` bounds the same errors. Prints the table and
writes it to `benchmarks/results/stress_table_<backend>.md` unless `--out` says otherwise.
"""

import argparse
from pathlib import Path

import harness
import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx

NUM_DRAWS = 200
DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}
WEIGHT_EPS, FLOOR = 1e-10, 1e-12  # the mixture's defaults
EPS_F32 = float(np.finfo(np.float32).eps)  # the resampler's draws span [0, 1 - EPS_F32]


# ----------------------------------------------------------------------------- float64 references


def reference_blend_weights(density, t_edges, step_scale) -> np.ndarray:
    """Paper eq. 2: `w_i = (1 - exp(-tau_i)) prod_{j<i} exp(-tau_j)`, `tau_i = sigma_i (t_{i+1} - t_i) s`."""
    tau = np.asarray(density, np.float64) * np.diff(t_edges) * np.asarray(step_scale, np.float64)
    survive = np.exp(-tau)
    before = np.concatenate([[1.0], np.cumprod(survive)[:-1]])
    return before * -np.expm1(-tau)


def reference_mixture_nll(weights, log_components, floor: float | None) -> float:
    """`-log(sum_j pi_j exp(log_components_j) [+ floor])`, `pi_j = w_j / (sum w + eps)`,
    with the sum taken as a log-sum-exp so that nothing underflows."""
    pi = weights / (weights.sum() + WEIGHT_EPS)
    with np.errstate(divide="ignore"):
        terms = np.log(pi) + log_components
    peak = terms.max()
    log_likelihood = -np.inf if peak == -np.inf else peak + np.log(np.exp(terms - peak).sum())
    return float(-log_likelihood if floor is None else -np.logaddexp(log_likelihood, np.log(floor)))


def laplace_log_density(x, location, scale) -> np.ndarray:
    return -np.log(2.0 * scale) - np.abs(x - location) / scale


def reference_colour_nll(weights, rgb, beta, target, floor: float | None = FLOOR) -> float:
    """Paper eq. 5: each component is the product of three per-channel Laplace densities."""
    return reference_mixture_nll(weights, laplace_log_density(target, rgb, beta).sum(axis=-1), floor)


def reference_depth_nll(weights, ray_depth, beta, target) -> float:
    """Paper eq. 7 as released: the depth residual under each of the three colour scales."""
    return reference_mixture_nll(
        weights, laplace_log_density(target, ray_depth[:, None], beta).sum(axis=-1), FLOOR
    )


def reference_blur(weights, padding: float) -> np.ndarray:
    """mip-NeRF's blur: the mean of each weight's max with its left and its right neighbour."""
    left = np.maximum(weights, np.concatenate([weights[:1], weights[:-1]]))
    right = np.maximum(weights, np.concatenate([weights[1:], weights[-1:]]))
    return 0.5 * (left + right) + padding


def reference_encoding(x, max_deg: int, variances=None, identity: bool = True) -> np.ndarray:
    """`[x, sin(2^k x), cos(2^k x)]` (frequency-major), each damped by `exp(-4^k var / 2)`
    when `variances` are given (the expected encoding of a Gaussian)."""
    scales = 2.0 ** np.arange(max_deg)
    phases = (scales[:, None] * x[None, :]).reshape(-1)
    damping = (
        1.0 if variances is None else np.exp(-0.5 * (scales[:, None] ** 2 * variances[None, :]).reshape(-1))
    )
    features = [damping * np.sin(phases), damping * np.cos(phases)]
    return np.concatenate([x, *features] if identity else features)


def reference_cone_moments(t0: float, t1: float, radius: float) -> tuple[float, float, float]:
    """Mean and variance of `t` and the variance across the ray of a cone between `t0` and
    `t1`: `t` has density proportional to `t^2`, and a disc of radius `r t` has variance
    `(r t)^2 / 4` along each axis. Integrated exactly around the midpoint `c` (half-width `h`)."""
    c, h = 0.5 * (t0 + t1), 0.5 * (t1 - t0)
    if c == 0:
        return 0.0, 0.0, 0.0
    # With s = t - c: the integrals of (c + s)^2 s^k over [-h, h], k = 0, 1, 2, over 2h.
    m0 = c**2 + h**2 / 3
    m1 = 2 * c * h**2 / 3
    m2 = c**2 * h**2 / 3 + h**4 / 5
    mean_s, second_s = m1 / m0, m2 / m0
    second_t = c**2 + 2 * c * mean_s + second_s
    return c + mean_s, second_s - mean_s**2, radius**2 * second_t / 4


# ----------------------------------------------------------------------------- cases


def finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(tree))


def cast(dtype: str, *arrays):
    """The arrays in `dtype` for the package, and their rounded values in float64."""
    cast_ = tuple(jnp.asarray(np.asarray(a, np.float32)).astype(DTYPES[dtype]) for a in arrays)
    return cast_, tuple(np.asarray(c.astype(jnp.float32), np.float64) for c in cast_)


def extreme_ray(rng, num_samples: int):
    widths = rng.choice([0.0, 0.3, 1e10], num_samples, p=[0.2, 0.7, 0.1])
    t_edges = 2.0 + np.concatenate([[0.0], np.cumsum(widths)])
    density = rng.choice([0.0, 1e10, 1.0], num_samples) * rng.uniform(0.01, 3.0, num_samples)
    return t_edges, density


def extreme_mixture(rng, num_samples: int):
    weights = rng.uniform(0, 1, num_samples) * rng.choice([0.0, 1.0], num_samples)
    target = rng.uniform(0, 1, 3)
    location = target + rng.uniform(-1, 1, (num_samples, 3))
    beta = 10.0 ** rng.uniform(-12, 6, (num_samples, 3))
    return weights / max(weights.sum(), 1.0), location, beta, target


def nll_scale(location, beta, target) -> float:
    return float(np.max(np.sum(np.abs(target - location) / beta + np.abs(np.log(2 * beta)), axis=-1)))


def case_blend(dtype: str):
    rng = np.random.default_rng(0)
    worst, values_ok, grads_ok = 0.0, True, True
    fn = jax.jit(lambda d, t: mx.nn.blend_weights(d, t, jnp.ones((), d.dtype)))
    grad = jax.jit(jax.grad(lambda d, t: mx.nn.expected_depth(fn(d, t), t).astype(jnp.float32), argnums=(0, 1)))
    for _ in range(NUM_DRAWS):
        (t, d), (t_r, d_r) = cast(dtype, *extreme_ray(rng, 16))
        weights = fn(d, t)
        values_ok &= finite(weights) and finite(mx.nn.expected_depth(weights, t))
        grads_ok &= finite(grad(d, t))
        error = np.abs(np.asarray(weights, np.float64) - reference_blend_weights(d_r, t_r, 1.0))
        worst = max(worst, float(np.max(error)))
    return worst, values_ok, grads_ok


def case_tiny_opacity():
    t = jnp.linspace(2.0, 6.0, 9)
    worst, values_ok, grads_ok = 0.0, True, True
    for density_value in (1e-30, 1e-20, 1e-12):
        d = jnp.full(8, density_value) * jnp.linspace(1.0, 2.0, 8)
        depth = mx.nn.expected_depth(mx.nn.blend_weights(d, t, jnp.asarray(1.0)), t)
        # At this opacity w_i = sigma_i delta_i: the reference depth is closed form.
        weights = np.asarray(d, np.float64) * np.diff(np.asarray(t, np.float64))
        mids = 0.5 * (np.asarray(t[1:], np.float64) + np.asarray(t[:-1], np.float64))
        worst = max(worst, abs(float(depth) - (weights * mids).sum() / weights.sum()))
        values_ok &= finite(depth)
        grads_ok &= finite(
            jax.grad(lambda x: mx.nn.expected_depth(mx.nn.blend_weights(x, t, jnp.asarray(1.0)), t))(d)
        )
    return worst, values_ok, grads_ok


def case_nll(dtype: str, kind: str, mixture: mx.nn.LaplaceMixture | None = None):
    rng = np.random.default_rng(1)
    mixture = mixture or mx.nn.LaplaceMixture()
    worst, values_ok, grads_ok = 0.0, True, True
    if kind == "colour":
        nll = mixture.colour_nll
    elif kind == "depth":
        nll = lambda w, depth, b, target: mixture.depth_nll(w, depth, b, target[0])
    else:
        nll = lambda depth, rgb, b, target, d, t: mixture.colour_nll(
            mx.nn.blend_weights(d, t, depth), rgb, b, target
        )
    value_fn = jax.jit(nll)
    grad_fn = jax.jit(jax.grad(lambda *a: nll(*a).astype(jnp.float32), argnums=(0, 1, 2)))
    for _ in range(NUM_DRAWS):
        weights, location, beta, target = extreme_mixture(rng, 8)
        if kind == "colour":
            args, (w_r, loc_r, beta_r, target_r) = cast(dtype, weights, location, beta, target)
            if mixture.likelihood_floor is None and w_r.sum() == 0:
                continue  # the exact NLL of an empty ray is infinite (the package counts it as 0)
            reference = reference_colour_nll(w_r, loc_r, beta_r, target_r, mixture.likelihood_floor)
            scale = nll_scale(loc_r, beta_r, target_r)
        elif kind == "depth":
            depths = np.clip(1.0 + location[:, 0] - target[0], 0.0, None) * rng.choice([0.0, 1.0], 8)
            args, (w_r, depth_r, beta_r, _) = cast(dtype, weights, depths, beta, np.ones(1))
            reference = reference_depth_nll(w_r, depth_r, beta_r, 1.0)
            scale = nll_scale(depth_r[:, None], beta_r, 1.0)
        else:
            t_edges, density = extreme_ray(rng, 8)
            depths = rng.choice([0.0, 0.5, 1.0, 2.0], 8)
            args, (depth_r, loc_r, beta_r, target_r, d_r, t_r) = cast(
                dtype, depths, location, beta, target, density, t_edges
            )
            weights_r = reference_blend_weights(d_r, t_r, depth_r)
            reference = reference_colour_nll(weights_r, loc_r, beta_r, target_r)
            scale = nll_scale(loc_r, beta_r, target_r)
        value = value_fn(*args)
        values_ok &= finite(value)
        grads_ok &= finite(grad_fn(*args))
        worst = max(worst, abs(float(value) - reference) / (1 + abs(reference) + scale))
    return worst, values_ok, grads_ok


def case_linear_overflow():
    args = (jnp.asarray([0.5, 0.5]), jnp.full((2, 3), 0.5), jnp.full((2, 3), 1e-14), jnp.full(3, 0.5))
    mixture = mx.nn.LaplaceMixture(evaluation="linear")
    value = mixture.colour_nll(*args)
    reference = -np.log(1 / (1 + 1e-10) * (1 / 2e-14) ** 3 + 1e-12)
    return (
        abs(float(value) - reference),
        finite(value),
        finite(jax.grad(mixture.colour_nll, argnums=2)(*args)),
    )


def case_linear_saturation(evaluation: str):
    weights, rgb, beta, target = (
        np.asarray([0.5, 0.5]),
        np.full((2, 3), 0.9),
        np.full((2, 3), 0.01),
        np.full(3, 0.1),
    )
    args = tuple(jnp.asarray(a, jnp.float32) for a in (weights, rgb, beta, target))
    mixture = mx.nn.LaplaceMixture(evaluation=evaluation, likelihood_floor=None)
    value = mixture.colour_nll(*args)
    reference = reference_colour_nll(weights, rgb, beta, target, floor=None)
    return (
        abs(float(value) - reference) / (1 + abs(reference)),
        finite(value),
        finite(jax.grad(mixture.colour_nll, argnums=2)(*args)),
    )


def case_resampling():
    rng = np.random.default_rng(2)
    worst, values_ok, grads_ok = 0.0, True, True
    draw = jax.jit(lambda b, w: mx.nn.sample_piecewise_constant(b, mx.nn.blur_weights(w, 0.01), 33, key=None))
    grad = jax.jit(jax.grad(lambda b, w: jnp.sum(draw(b, w)), argnums=(0, 1)))
    for _ in range(NUM_DRAWS):
        widths = rng.choice([0.0, 0.3, 10.0], 16)
        bins = jnp.asarray(2.0 + np.concatenate([[0.0], np.cumsum(widths)]), jnp.float32)
        weights = jnp.asarray(rng.uniform(0, 1, 16) * rng.choice([0.0, 1.0, 1e10]), jnp.float32)
        samples = draw(bins, weights)
        values_ok &= finite(samples)
        grads_ok &= finite(grad(bins, weights))
        # The float64 CDF at each draw against the stratum it was drawn for. Zero-length bins
        # make the CDF jump: measure the distance of each stratum's u from the CDF's left and
        # right limits at the draw.
        blurred = reference_blur(np.asarray(weights, np.float64), 0.01)
        masses = blurred / blurred.sum()
        bins_r = np.asarray(bins, np.float64)
        widths_r = np.diff(bins_r)
        for sample, u in zip(np.asarray(samples, np.float64), np.linspace(0, 1 - EPS_F32, 33), strict=True):
            partial = np.clip((sample - bins_r[:-1]) / np.where(widths_r > 0, widths_r, 1.0), 0.0, 1.0)
            left = (masses * np.where(widths_r > 0, partial, sample > bins_r[:-1])).sum()
            right = (masses * np.where(widths_r > 0, partial, sample >= bins_r[:-1])).sum()
            worst = max(worst, left - u, u - right, 0.0)
    return worst, values_ok, grads_ok


def case_encoding(dtype: str, integrated: bool):
    rng = np.random.default_rng(3)
    worst, values_ok, grads_ok = 0.0, True, True
    max_deg = 16 if dtype == "float32" else 4
    for _ in range(NUM_DRAWS):
        (means, covs), (means_r, covs_r) = cast(dtype, rng.uniform(-1, 1, 3), 10.0 ** rng.uniform(-30, 30, 3))
        if integrated:
            value = mx.nn.integrated_positional_encoding(means, covs, 0, max_deg)
            reference = reference_encoding(means_r, max_deg, covs_r, identity=False)
            fn = lambda m, c: jnp.sum(mx.nn.integrated_positional_encoding(m, c, 0, max_deg)).astype(jnp.float32)
        else:
            value = mx.nn.positional_encoding(means, 0, max_deg)
            reference = reference_encoding(means_r, max_deg)
            fn = lambda m, c: jnp.sum(mx.nn.positional_encoding(m, 0, max_deg)).astype(jnp.float32)
        values_ok &= finite(value)
        grads_ok &= finite(jax.grad(fn, argnums=(0, 1))(means, covs))
        worst = max(
            worst, float(np.max(np.abs(np.asarray(value.astype(jnp.float32), np.float64) - reference)))
        )
    return worst, values_ok, grads_ok


def case_frustum():
    worst, values_ok, grads_ok = 0.0, True, True
    radius = jnp.asarray([0.01])
    for t0, t1 in [(0.0, 0.0), (2.0, 2.0), (2.0, 2.5), (0.0, 1e10), (2.0, 1e10), (1e3, 1e3 + 1e-2)]:
        t0_j, t1_j = jnp.asarray([t0], jnp.float32), jnp.asarray([t1], jnp.float32)
        moments = mx.nn.conical_frustum_moments(t0_j, t1_j, radius)
        values_ok &= finite(moments)
        grads_ok &= finite(
            jax.grad(
                lambda a, b: sum(jnp.sum(m) for m in mx.nn.conical_frustum_moments(a, b, radius)), argnums=(0, 1)
            )(t0_j, t1_j)
        )
        if t1 > 0:
            reference = reference_cone_moments(float(t0_j[0]), float(t1_j[0]), 0.01)
            sizes = (t1, t1**2, 0.01**2 * t1**2)
            for value, ref, size in zip(moments, reference, sizes, strict=True):
                worst = max(worst, abs(float(value[0]) - ref) / size)
    return worst, values_ok, grads_ok


CASES = [
    ("blend weights, f32 (densities 0..1e10, zero and 1e10-long intervals)", lambda: case_blend("float32")),
    ("blend weights, bf16", lambda: case_blend("bfloat16")),
    ("expected depth at opacity 1e-30..1e-12, f32", case_tiny_opacity),
    ("colour NLL, f32 (beta 1e-12..1e6, |r| <= 1, empty rays)", lambda: case_nll("float32", "colour")),
    ("colour NLL, bf16", lambda: case_nll("bfloat16", "colour")),
    ("depth NLL, f32 (zero predicted depths)", lambda: case_nll("float32", "depth")),
    ("regenerated colour NLL, f32 (zero predicted depths)", lambda: case_nll("float32", "regenerated")),
    (
        "exact colour NLL (no floor), log space, f32",
        lambda: case_nll("float32", "colour", mx.nn.LaplaceMixture(likelihood_floor=None)),
    ),
    ("released linear arithmetic (comparison only), beta 1e-14, r = 0: overflow", case_linear_overflow),
    (
        "linear arithmetic (comparison only), no floor, poorly fitted ray: underflow",
        lambda: case_linear_saturation("linear"),
    ),
    ("exact NLL, log space f32, poorly fitted ray", lambda: case_linear_saturation("log")),
    ("resampling CDF, f32 (zero, 1e10 weights)", case_resampling),
    ("PE, f32, max_deg 16", lambda: case_encoding("float32", False)),
    ("IPE, f32, max_deg 16, variances 1e-30..1e30", lambda: case_encoding("float32", True)),
    ("PE, bf16, max_deg 4", lambda: case_encoding("bfloat16", False)),
    ("IPE, bf16, max_deg 4", lambda: case_encoding("bfloat16", True)),
    ("frustum moments, f32 (zero-length, 1e10-long)", case_frustum),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--out", default=None, help="markdown path (default: results/stress_table_<backend>.md)"
    )
    parser.add_argument("--cases", type=int, nargs="+", default=None, help="run only these cases (1-based)")
    args = parser.parse_args()
    selected = [case for index, case in enumerate(CASES, 1) if args.cases is None or index in args.cases]
    lines = [
        f"Device: {jax.devices()[0].platform}; {NUM_DRAWS} random draws per randomised case.",
        "",
        "| case | worst error vs float64 | values finite | grads finite |",
        "|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for name, run in selected:
        worst, values_ok, grads_ok = run()
        lines.append(
            f"| {name} | {worst:.2e} | {'yes' if values_ok else 'NO'} | {'yes' if grads_ok else 'NO'} |"
        )
        print(lines[-1], flush=True)
    out = Path(args.out) if args.out else harness.RESULTS / f"stress_table_{harness.platform_tag()}.md"
    harness.write_markdown(out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
