"""Worst error against float64 numpy references over extreme inputs, as a markdown table.

    python benchmarks/stress_table.py > benchmarks/results/stress_table_cpu.md

Each case draws a fixed set of random extreme inputs (seeded), evaluates the package in the
stated dtype, and reports the largest error against the float64 reference of `tests/helpers.py`
(absolute for quantities in [0, 1], relative to `1 + |NLL| + largest component term` for NLLs),
and whether every value and every `jax.grad` gradient was finite. The tests in
`tests/test_stress.py` bound the same errors.
"""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from helpers import (  # noqa: E402
    quadrature_frustum_moments,
    ref_blend_weights,
    ref_blur_weights,
    ref_colour_nll,
    ref_colour_nll_logspace,
    ref_depth_nll,
    ref_positional_encoding,
)

from mixnerf_eqx import LaplaceMixture, blend_weights  # noqa: E402
from mixnerf_eqx._encoding import (  # noqa: E402
    conical_frustum_moments,
    integrated_positional_encoding,
    positional_encoding,
)
from mixnerf_eqx._render import expected_depth  # noqa: E402
from mixnerf_eqx._sampler.hierarchical import blur_weights, sample_piecewise_constant  # noqa: E402

NUM_DRAWS = 200
DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


def finite(tree):
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(tree))


def cast(dtype, *arrays):
    """The arrays in `dtype` for the package, and their rounded values in float64."""
    cast_ = tuple(jnp.asarray(np.asarray(a, np.float32)).astype(DTYPES[dtype]) for a in arrays)
    return cast_, tuple(np.asarray(c.astype(jnp.float32), np.float64) for c in cast_)


def extreme_ray(rng, num_samples):
    widths = rng.choice([0.0, 0.3, 1e10], num_samples, p=[0.2, 0.7, 0.1])
    t_edges = 2.0 + np.concatenate([[0.0], np.cumsum(widths)])
    density = rng.choice([0.0, 1e10, 1.0], num_samples) * rng.uniform(0.01, 3.0, num_samples)
    return t_edges, density


def extreme_mixture(rng, num_samples):
    weights = rng.uniform(0, 1, num_samples) * rng.choice([0.0, 1.0], num_samples)
    target = rng.uniform(0, 1, 3)
    location = target + rng.uniform(-1, 1, (num_samples, 3))
    beta = 10.0 ** rng.uniform(-12, 6, (num_samples, 3))
    return weights / max(weights.sum(), 1.0), location, beta, target


def nll_scale(location, beta, target):
    return float(np.max(np.sum(np.abs(target - location) / beta + np.abs(np.log(2 * beta)), axis=-1)))


def case_blend(dtype):
    rng = np.random.default_rng(0)
    worst, values_ok, grads_ok = 0.0, True, True
    fn = jax.jit(lambda d, t: blend_weights(d, t, jnp.ones((), d.dtype)))
    grad = jax.jit(jax.grad(lambda d, t: expected_depth(fn(d, t), t).astype(jnp.float32), argnums=(0, 1)))
    for _ in range(NUM_DRAWS):
        (t, d), (t_r, d_r) = cast(dtype, *extreme_ray(rng, 16))
        weights = fn(d, t)
        values_ok &= finite(weights) and finite(expected_depth(weights, t))
        grads_ok &= finite(grad(d, t))
        worst = max(
            worst, float(np.max(np.abs(np.asarray(weights, np.float64) - ref_blend_weights(d_r, t_r, 1.0))))
        )
    return worst, values_ok, grads_ok


def case_tiny_opacity():
    t = jnp.linspace(2.0, 6.0, 9)
    worst, values_ok, grads_ok = 0.0, True, True
    for density_value in (1e-30, 1e-20, 1e-12):
        d = jnp.full(8, density_value) * jnp.linspace(1.0, 2.0, 8)
        depth = expected_depth(blend_weights(d, t, jnp.asarray(1.0)), t)
        # At this opacity w_i = sigma_i delta_i: the reference depth is closed form.
        weights = np.asarray(d, np.float64) * np.diff(np.asarray(t, np.float64))
        mids = 0.5 * (np.asarray(t[1:], np.float64) + np.asarray(t[:-1], np.float64))
        worst = max(worst, abs(float(depth) - (weights * mids).sum() / weights.sum()))
        values_ok &= finite(depth)
        grads_ok &= finite(jax.grad(lambda x: expected_depth(blend_weights(x, t, jnp.asarray(1.0)), t))(d))
    return worst, values_ok, grads_ok


def case_nll(dtype, kind, mixture=None):
    rng = np.random.default_rng(1)
    mixture = mixture or LaplaceMixture()
    worst, values_ok, grads_ok = 0.0, True, True
    if kind == "colour":
        nll = mixture.colour_nll
    elif kind == "depth":
        nll = lambda w, depth, b, target: mixture.depth_nll(w, depth, b, target[0])
    else:
        nll = lambda depth, rgb, b, target, d, t: mixture.colour_nll(
            blend_weights(d, t, depth), rgb, b, target
        )
    value_fn = jax.jit(nll)
    grad_fn = jax.jit(jax.grad(lambda *a: nll(*a).astype(jnp.float32), argnums=(0, 1, 2)))
    for _ in range(NUM_DRAWS):
        weights, location, beta, target = extreme_mixture(rng, 8)
        if kind == "colour":
            args, (w_r, loc_r, beta_r, target_r) = cast(dtype, weights, location, beta, target)
            if mixture.likelihood_floor is None:
                if w_r.sum() == 0:
                    continue
                reference = ref_colour_nll_logspace(w_r, loc_r, beta_r, target_r, weight_eps=1e-10)
            else:
                reference = ref_colour_nll(w_r, loc_r, beta_r, target_r, weight_eps=1e-10, floor=1e-12)
            scale = nll_scale(loc_r, beta_r, target_r)
        elif kind == "depth":
            depths = np.clip(1.0 + location[:, 0] - target[0], 0.0, None) * rng.choice([0.0, 1.0], 8)
            args, (w_r, depth_r, beta_r, _) = cast(dtype, weights, depths, beta, np.ones(1))
            reference = ref_depth_nll(w_r, depth_r, beta_r, 1.0, weight_eps=1e-10, floor=1e-12)
            scale = nll_scale(depth_r[:, None], beta_r, 1.0)
        else:
            t_edges, density = extreme_ray(rng, 8)
            depths = rng.choice([0.0, 0.5, 1.0, 2.0], 8)
            args, (depth_r, loc_r, beta_r, target_r, d_r, t_r) = cast(
                dtype, depths, location, beta, target, density, t_edges
            )
            ref_weights = ref_blend_weights(d_r, t_r, depth_r)
            reference = ref_colour_nll(ref_weights, loc_r, beta_r, target_r, weight_eps=1e-10, floor=1e-12)
            scale = nll_scale(loc_r, beta_r, target_r)
        value = value_fn(*args)
        values_ok &= finite(value)
        grads_ok &= finite(grad_fn(*args))
        worst = max(worst, abs(float(value) - reference) / (1 + abs(reference) + scale))
    return worst, values_ok, grads_ok


def case_linear_overflow():
    args = (jnp.asarray([0.5, 0.5]), jnp.full((2, 3), 0.5), jnp.full((2, 3), 1e-14), jnp.full(3, 0.5))
    mixture = LaplaceMixture(evaluation="linear")
    value = mixture.colour_nll(*args)
    reference = -np.log(1 / (1 + 1e-10) * (1 / 2e-14) ** 3 + 1e-12)
    return (
        abs(float(value) - reference),
        finite(value),
        finite(jax.grad(mixture.colour_nll, argnums=2)(*args)),
    )


def case_linear_saturation(evaluation):
    weights, rgb, beta, target = (
        np.asarray([0.5, 0.5]),
        np.full((2, 3), 0.9),
        np.full((2, 3), 0.01),
        np.full(3, 0.1),
    )
    args = tuple(jnp.asarray(a, jnp.float32) for a in (weights, rgb, beta, target))
    mixture = LaplaceMixture(evaluation=evaluation, likelihood_floor=None)
    value = mixture.colour_nll(*args)
    reference = ref_colour_nll_logspace(weights, rgb, beta, target, weight_eps=1e-10)
    return (
        abs(float(value) - reference) / (1 + abs(reference)),
        finite(value),
        finite(jax.grad(mixture.colour_nll, argnums=2)(*args)),
    )


def case_resampling():
    rng = np.random.default_rng(2)
    worst, values_ok, grads_ok = 0.0, True, True
    draw = jax.jit(lambda b, w: sample_piecewise_constant(b, blur_weights(w, 0.01), 33, key=None))
    grad = jax.jit(jax.grad(lambda b, w: jnp.sum(draw(b, w)), argnums=(0, 1)))
    for _ in range(NUM_DRAWS):
        widths = rng.choice([0.0, 0.3, 10.0], 16)
        bins = jnp.asarray(2.0 + np.concatenate([[0.0], np.cumsum(widths)]), jnp.float32)
        weights = jnp.asarray(rng.uniform(0, 1, 16) * rng.choice([0.0, 1.0, 1e10]), jnp.float32)
        samples = draw(bins, weights)
        values_ok &= finite(samples)
        grads_ok &= finite(grad(bins, weights))
        # The float64 CDF at each draw against the stratum it was drawn for.
        ref_weights = ref_blur_weights(np.asarray(weights, np.float64), 0.01)
        bins_r = np.asarray(bins, np.float64)
        # Zero-length bins make the CDF jump: measure the distance of each stratum's u from
        # the CDF's left and right limits at the draw.
        masses = ref_weights / ref_weights.sum()
        widths_r = np.diff(bins_r)
        for sample, u in zip(np.asarray(samples, np.float64), np.linspace(0, 1 - 1e-5, 33), strict=True):
            partial = np.clip((sample - bins_r[:-1]) / np.where(widths_r > 0, widths_r, 1.0), 0.0, 1.0)
            left = (masses * np.where(widths_r > 0, partial, sample > bins_r[:-1])).sum()
            right = (masses * np.where(widths_r > 0, partial, sample >= bins_r[:-1])).sum()
            worst = max(worst, left - u, u - right, 0.0)
    return worst, values_ok, grads_ok


def case_encoding(dtype, integrated):
    rng = np.random.default_rng(3)
    worst, values_ok, grads_ok = 0.0, True, True
    max_deg = 16 if dtype == "float32" else 4
    for _ in range(NUM_DRAWS):
        (means, covs), (means_r, covs_r) = cast(dtype, rng.uniform(-1, 1, 3), 10.0 ** rng.uniform(-30, 30, 3))
        scales = 2.0 ** np.arange(max_deg)
        if integrated:
            value = integrated_positional_encoding(means, covs, 0, max_deg)
            variances = (scales[:, None] ** 2 * covs_r[None, :]).reshape(-1)
            damping = np.exp(-0.5 * np.concatenate([variances, variances]))
            reference = damping * ref_positional_encoding(means_r, 0, max_deg, append_identity=False)
            fn = lambda m, c: jnp.sum(integrated_positional_encoding(m, c, 0, max_deg)).astype(jnp.float32)
        else:
            value = positional_encoding(means, 0, max_deg)
            reference = ref_positional_encoding(means_r, 0, max_deg)
            fn = lambda m, c: jnp.sum(positional_encoding(m, 0, max_deg)).astype(jnp.float32)
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
        moments = conical_frustum_moments(t0_j, t1_j, radius)
        values_ok &= finite(moments)
        grads_ok &= finite(
            jax.grad(
                lambda a, b: sum(jnp.sum(m) for m in conical_frustum_moments(a, b, radius)), argnums=(0, 1)
            )(t0_j, t1_j)
        )
        if t1 > 0:
            reference = quadrature_frustum_moments(float(t0_j[0]), float(t1_j[0]), 0.01, "cone")
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
        lambda: case_nll("float32", "colour", LaplaceMixture(likelihood_floor=None)),
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


def main():
    print(f"Device: {jax.devices()[0].platform}; {NUM_DRAWS} random draws per randomised case.\n")
    print("| case | worst error vs float64 | values finite | grads finite |")
    print("|---|---|---|---|")
    for name, run in CASES:
        worst, values_ok, grads_ok = run()
        print(f"| {name} | {worst:.2e} | {'yes' if values_ok else 'NO'} | {'yes' if grads_ok else 'NO'} |")


if __name__ == "__main__":
    main()
