"""Numerical stress tests: compositing, the mixture NLLs, resampling and the encodings.

Every test checks that values and `jax.grad` gradients are finite over extreme inputs
(scales 1e-12..1e6, densities 0 and 1e10, zero-length and 1e10-long intervals, empty rays,
zero predicted depth, one sample per ray, float32 and bfloat16), and, where the quantity is
defined, that it matches an independent float64 numpy reference from `helpers`.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    as_f64,
    central_difference,
    quadrature_frustum_moments,
    ref_blend_weights,
    ref_blur_weights,
    ref_colour_nll,
    ref_colour_nll_logspace,
    ref_composite_rgb,
    ref_depth_nll,
    ref_expected_depth,
    ref_positional_encoding,
)
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mixnerf_eqx.nn import LaplaceMixture, blend_weights
from mixnerf_eqx._nn.compositing import accumulation, composite_rgb, expected_depth
from mixnerf_eqx._nn.encoding import (
    conical_frustum_moments,
    integrated_positional_encoding,
    positional_encoding,
)
from mixnerf_eqx._nn.sampler.hierarchical import blur_weights, sample_piecewise_constant

SETTINGS = settings(max_examples=40, deadline=None)
DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}
EPS = {name: float(jnp.finfo(dtype).eps) for name, dtype in DTYPES.items()}

# Blending weights, colour and opacity lie in [0, 1]. In float32 each weight is a product of
# an expm1 and an exp of a cumulative sum over at most 16 samples: a few ulps of 1, so 1e-5
# leaves a factor ~80 of headroom. In bfloat16 (eps = 2^-7) every input, product and partial
# sum is rounded to 8 bits; measured worst 2.2e-3 over 3000 random extreme rays of 16 samples
# (benchmarks/stress_table.py shows the same figure), so 1e-2 is ~1 ulp at 1 of headroom.
WEIGHT_ATOL = {"float32": 1e-5, "bfloat16": 1e-2}
# The expected depth of rays no longer than 16: measured worst 4.9e-7 in float32 (a few ulps
# of the edges' magnitude, 1.9e-6 per ulp at 16), so 1e-5 is ~5 ulps.
DEPTH_ATOL_F32 = 1e-5
# NLLs: the residual term |r| / beta reaches 3e12 at beta = 1e-12, so errors are relative.
# `1 / beta` is `exp(-log beta)`, whose float32 rounding is ~|log beta| * eps ~ 3e-6
# relative; 2e-5 of (1 + |NLL| + largest component term) covers that with room. In
# bfloat16 the same rounding is ~|log beta| * 2^-8: measured worst 1.8e-2 relative to
# (1 + |NLL|) alone over 3000 draws; 5e-2 of the larger normaliser is a safe bound.
NLL_RTOL = {"float32": 2e-5, "bfloat16": 5e-2}
# Gradients against central differences of the float64 reference, in the moderate regime
# where both exist: float32 backward passes carry ~1e-6 relative error, the finite
# differences ~1e-8.
GRAD_RTOL, GRAD_ATOL = 1e-3, 1e-4
# Resampling: the CDF at a draw equals its stratum's u up to the float32 cumulative sum of
# at most 64 bins (~64 eps = 8e-6); the draw itself may be off by a few ulps of the largest
# edge, which `_edge_slack` absorbs.
CDF_ATOL = 5e-5
# Encodings: `2^k x` is exact (a power of two), but `phase + pi/2` and the sine's range
# reduction round at the phase's magnitude, so the error grows like eps * |phase|.
ENCODING_ULPS = 4.0
# Frustum moments against Gauss-Legendre quadrature: a few float32 ulps of each moment's size.
MOMENT_RTOL = 1e-4

positive_density = st.one_of(
    st.just(0.0), st.just(1e10), st.floats(1e-3, 1e3), st.floats(1e-30, 1e-3), st.floats(1e3, 1e10)
)
log_scale = st.floats(-12.0, 6.0)


def _finite(tree):
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(tree))


def _cast(dtype_name, *arrays):
    """The arrays in `dtype_name`, and the same (rounded) values in float64 for references."""
    dtype = DTYPES[dtype_name]
    cast = tuple(jnp.asarray(np.asarray(a, np.float32)).astype(dtype) for a in arrays)
    return cast, tuple(np.asarray(c.astype(jnp.float32), np.float64) for c in cast)


@st.composite
def ray_edges(draw, num_samples):
    """Sorted edges from 2, with zero-length, ordinary and (optionally) 1e10-long intervals."""
    widths = draw(
        st.lists(
            st.one_of(st.just(0.0), st.floats(1e-3, 1.0), st.just(1e10)),
            min_size=num_samples,
            max_size=num_samples,
        )
    )
    return 2.0 + np.concatenate([[0.0], np.cumsum(widths)])


# --- compositing ------------------------------------------------------------------------


@SETTINGS
@given(
    data=st.data(),
    num_samples=st.sampled_from([1, 16]),
    dtype=st.sampled_from(["float32", "bfloat16"]),
)
def test_compositing_stress(data, num_samples, dtype):
    t_edges = data.draw(ray_edges(num_samples))
    density = np.asarray(data.draw(st.lists(positive_density, min_size=num_samples, max_size=num_samples)))
    rgb = np.asarray(data.draw(st.lists(st.floats(0, 1), min_size=3 * num_samples, max_size=3 * num_samples)))
    step_scale = data.draw(st.floats(0.5, 2.0))
    (density_j, t_j, rgb_j, scale_j), (density_r, t_r, rgb_r, scale_r) = _cast(
        dtype, density, t_edges, rgb.reshape(num_samples, 3), step_scale
    )
    weights, colour, opacity, depth, grads = _composite_with_grads(density_j, t_j, scale_j, rgb_j)
    ref_weights = ref_blend_weights(density_r, t_r, scale_r)
    assert weights.dtype == DTYPES[dtype]
    assert _finite(weights) and _finite(grads)
    np.testing.assert_allclose(np.asarray(weights, np.float64), ref_weights, rtol=0, atol=WEIGHT_ATOL[dtype])
    ref_colour = ref_composite_rgb(ref_weights, rgb_r, np.ones(3))
    np.testing.assert_allclose(
        np.asarray(colour, np.float64), ref_colour, rtol=0, atol=2 * WEIGHT_ATOL[dtype]
    )
    np.testing.assert_allclose(
        float(opacity), ref_weights.sum(), rtol=0, atol=num_samples * WEIGHT_ATOL[dtype]
    )
    assert _finite(depth)
    assert float(t_j[0]) <= float(depth) <= float(t_j[-1])
    if dtype == "float32" and t_edges[-1] < 1e9:
        ref_depth = ref_expected_depth(np.asarray(weights, np.float64), t_r)
        np.testing.assert_allclose(float(depth), ref_depth, rtol=0, atol=DEPTH_ATOL_F32)


@jax.jit
def _composite_with_grads(density, t_edges, step_scale, rgb):
    """Weights, colour on white, opacity, depth, and the gradients of their sum (jitted: one
    compilation per shape and dtype keeps the property tests fast)."""
    background = jnp.ones(3, rgb.dtype)

    def outputs(density_, t_edges_, scale_):
        weights_ = blend_weights(density_, t_edges_, scale_)
        return (
            weights_,
            composite_rgb(weights_, rgb, background),
            accumulation(weights_),
            expected_depth(weights_, t_edges_),
        )

    def scalar(*args):
        _, colour_, opacity_, depth_ = outputs(*args)
        return (jnp.sum(colour_) + opacity_ + depth_).astype(jnp.float32)

    grads = jax.grad(scalar, argnums=(0, 1, 2))(density, t_edges, step_scale)
    return (*outputs(density, t_edges, step_scale), grads)


def test_all_weights_zero_is_an_empty_ray():
    t_edges = jnp.linspace(2.0, 6.0, 9)
    weights = blend_weights(jnp.zeros(8), t_edges, jnp.asarray(1.0))
    np.testing.assert_array_equal(np.asarray(weights), 0.0)
    assert float(expected_depth(weights, t_edges)) == 6.0
    np.testing.assert_array_equal(np.asarray(composite_rgb(weights, jnp.full((8, 3), 0.3), jnp.ones(3))), 1.0)
    grads = jax.grad(lambda d: expected_depth(blend_weights(d, t_edges, jnp.asarray(1.0)), t_edges))(
        jnp.zeros(8)
    )
    assert _finite(grads)


@pytest.mark.parametrize("density_value", [1e-30, 1e-20, 1e-12])
def test_expected_depth_gradient_at_tiny_opacity(density_value):
    """Before the fix, opacities below ~1e-19 gave NaN gradients (`x * total^-2 = x * inf`)."""
    t_edges = np.linspace(2.0, 6.0, 9)
    density = np.full(8, density_value) * np.linspace(1.0, 2.0, 8)
    weights_fn = lambda d: blend_weights(d, jnp.asarray(t_edges, jnp.float32), jnp.asarray(1.0))
    grads = jax.grad(lambda d: expected_depth(weights_fn(d), jnp.asarray(t_edges, jnp.float32)))(
        jnp.asarray(density, jnp.float32)
    )
    assert _finite(grads)
    # At this opacity the transmittance is 1 and `w_i = sigma_i delta_i` to within 1e-11
    # relative, and the depth is scale-free in the weights: its gradient is that of the
    # float64 depth of `sigma delta` at `sigma * s`, times `s` (s = 1 / density_value).
    scale = 1.0 / density_value
    reference = central_difference(
        lambda d: ref_expected_depth(d * np.diff(t_edges), t_edges), density * scale
    )
    np.testing.assert_allclose(np.asarray(grads) / scale, reference, rtol=GRAD_RTOL, atol=GRAD_ATOL)


def test_huge_density_and_long_last_interval():
    t_edges = jnp.asarray([2.0, 3.0, 4.0, 1e10])
    density = jnp.asarray([0.0, 1e10, 1e10])
    weights = blend_weights(density, t_edges, jnp.asarray(1.0))
    np.testing.assert_allclose(np.asarray(weights), [0.0, 1.0, 0.0], atol=0)
    assert float(expected_depth(weights, t_edges)) == 3.5
    grads = jax.grad(lambda d, t: expected_depth(blend_weights(d, t, jnp.asarray(1.0)), t), argnums=(0, 1))(
        density, t_edges
    )
    assert _finite(grads)


@pytest.mark.parametrize("floor", [1e-12, None])
def test_compositing_gradients_match_reference(floor):
    """Moderate rays: gradients of colour + depth + colour NLL match float64 central differences."""
    rng = np.random.default_rng(3)
    t_edges = np.sort(rng.uniform(2.0, 6.0, 9)).astype(np.float32).astype(np.float64)
    density = rng.uniform(0.1, 2.0, 8).astype(np.float32).astype(np.float64)
    rgb = rng.uniform(0, 1, (8, 3)).astype(np.float32).astype(np.float64)
    beta = rng.uniform(0.1, 0.5, (8, 3)).astype(np.float32).astype(np.float64)
    target = np.asarray([0.2, 0.5, 0.9])
    mixture = LaplaceMixture(likelihood_floor=floor)

    def package(d):
        weights = blend_weights(d, jnp.asarray(t_edges, jnp.float32), jnp.asarray(1.0))
        colour = composite_rgb(weights, jnp.asarray(rgb, jnp.float32))
        nll = mixture.colour_nll(
            weights,
            jnp.asarray(rgb, jnp.float32),
            jnp.asarray(beta, jnp.float32),
            jnp.asarray(target, jnp.float32),
        )
        return jnp.sum(colour) + expected_depth(weights, jnp.asarray(t_edges, jnp.float32)) + nll

    def reference(d):
        weights = ref_blend_weights(d, t_edges, 1.0)
        return (
            ref_composite_rgb(weights, rgb).sum()
            + ref_expected_depth(weights, t_edges)
            + ref_colour_nll(weights, rgb, beta, target, weight_eps=1e-10, floor=floor)
        )

    grads = jax.grad(package)(jnp.asarray(density, jnp.float32))
    np.testing.assert_allclose(
        np.asarray(grads), central_difference(reference, density), rtol=GRAD_RTOL, atol=GRAD_ATOL
    )


# --- the mixture ------------------------------------------------------------------------


@st.composite
def mixture_inputs(draw, num_samples):
    weight_kind = draw(st.sampled_from(["zero", "random", "sparse"]))
    if weight_kind == "zero":
        weights = np.zeros(num_samples)
    else:
        weights = np.asarray(draw(st.lists(st.floats(0, 1), min_size=num_samples, max_size=num_samples)))
        weights = weights / max(weights.sum(), 1.0)
        if weight_kind == "sparse":
            weights[: num_samples // 2] = 0.0
    target = np.asarray(draw(st.lists(st.floats(0, 1), min_size=3, max_size=3)))
    residual = np.asarray(
        draw(st.lists(st.floats(-1, 1), min_size=3 * num_samples, max_size=3 * num_samples))
    )
    location = np.reshape(target, (1, 3)) + residual.reshape(num_samples, 3)
    beta = 10.0 ** np.asarray(draw(st.lists(log_scale, min_size=3 * num_samples, max_size=3 * num_samples)))
    return weights, location, beta.reshape(num_samples, 3), target


def _component_scale(location, beta, target):
    """The largest |log-density| of any component: the size the NLL's rounding scales with."""
    return float(np.max(np.sum(np.abs(target - location) / beta + np.abs(np.log(2 * beta)), axis=-1)))


@SETTINGS
@given(
    data=st.data(),
    num_samples=st.sampled_from([1, 8]),
    dtype=st.sampled_from(["float32", "bfloat16"]),
    kind=st.sampled_from(["colour", "depth", "regenerated"]),
)
def test_mixture_nll_stress(data, num_samples, dtype, kind):
    weights, location, beta, target = data.draw(mixture_inputs(num_samples))
    if kind == "colour":
        (w_j, loc_j, beta_j, target_j), (w_r, loc_r, beta_r, target_r) = _cast(
            dtype, weights, location, beta, target
        )
        fn = _colour_nll_and_grads
        extra = (target_j,)
        reference = ref_colour_nll(w_r, loc_r, beta_r, target_r, weight_eps=1e-10, floor=1e-12)
        scale = _component_scale(loc_r, beta_r, target_r)
    elif kind == "depth":
        # Predicted depths from 0 (the head's norm at a zero vector) to target + 1.
        direction_norm = 1.0
        depths = np.clip(direction_norm + location[:, 0] - target[0], 0.0, None)
        depths[: data.draw(st.integers(0, num_samples))] = 0.0
        (w_j, loc_j, beta_j, target_j), (w_r, loc_r, beta_r, target_r) = _cast(
            dtype, weights, depths, beta, direction_norm
        )
        fn = _depth_nll_and_grads
        extra = (target_j,)
        reference = ref_depth_nll(w_r, loc_r, beta_r, target_r, weight_eps=1e-10, floor=1e-12)
        scale = _component_scale(loc_r[:, None], beta_r, target_r)
    else:
        # Eq. 8: weights recomposited with the predicted depth; zero depths give zero weights.
        t_edges = data.draw(ray_edges(num_samples))
        density = np.asarray(
            data.draw(st.lists(positive_density, min_size=num_samples, max_size=num_samples))
        )
        ray_depth = np.asarray(
            data.draw(
                st.lists(st.sampled_from([0.0, 0.5, 1.0, 2.0]), min_size=num_samples, max_size=num_samples)
            )
        )
        (d_j, t_j, depth_j, loc_j, beta_j, target_j), (d_r, t_r, depth_r, loc_r, beta_r, target_r) = _cast(
            dtype, density, t_edges, ray_depth, location, beta, target
        )
        fn = _regen_nll_and_grads
        extra = (target_j, d_j, t_j)
        w_j = depth_j
        ref_weights = ref_blend_weights(d_r, t_r, depth_r)
        reference = ref_colour_nll(ref_weights, loc_r, beta_r, target_r, weight_eps=1e-10, floor=1e-12)
        scale = _component_scale(loc_r, beta_r, target_r)
        if dtype == "bfloat16":
            # The bfloat16 weights themselves carry WEIGHT_ATOL of error, which the
            # log-coefficients amplify without bound as a weight nears 0: check finiteness only.
            reference = None
    value, grads = fn(w_j, loc_j, beta_j, *extra)
    assert value.dtype == DTYPES[dtype]
    assert _finite(value)
    if reference is not None:
        np.testing.assert_allclose(
            float(value), reference, rtol=0, atol=NLL_RTOL[dtype] * (1 + abs(reference) + scale)
        )
    assert _finite(grads)


def _value_and_grads(nll):
    """`nll(first, location, beta, *rest)` and its gradients in the first three, jitted once
    per shape and dtype (which keeps the property tests fast)."""

    def value_and_grads(first, location, beta, *rest):
        as_f32 = lambda *args: nll(*args, *rest).astype(jnp.float32)
        return nll(first, location, beta, *rest), jax.grad(as_f32, argnums=(0, 1, 2))(first, location, beta)

    return jax.jit(value_and_grads)


_colour_nll_and_grads = _value_and_grads(LaplaceMixture().colour_nll)
_depth_nll_and_grads = _value_and_grads(LaplaceMixture().depth_nll)
_regen_nll_and_grads = _value_and_grads(
    lambda ray_depth, rgb, beta, target, density, t_edges: LaplaceMixture().colour_nll(
        blend_weights(density, t_edges, ray_depth), rgb, beta, target
    )
)


@SETTINGS
@given(data=st.data(), num_samples=st.sampled_from([1, 8]))
def test_exact_nll_in_log_space_stress(data, num_samples):
    """Without the floor the NLL is exact, far below float32's (and float64's) linear range."""
    weights, location, beta, target = data.draw(mixture_inputs(num_samples))
    mixture = LaplaceMixture(likelihood_floor=None)
    (w_j, loc_j, beta_j, target_j), (w_r, loc_r, beta_r, target_r) = _cast(
        "float32", weights, location, beta, target
    )
    value = mixture.colour_nll(w_j, loc_j, beta_j, target_j)
    assert _finite(value)
    # XLA flushes float32 subnormals to zero (a weight of 1.6e-41 is an empty sample there),
    # so the reference sees the weights as the device does.
    w_r = np.where(np.abs(w_r) < np.finfo(np.float32).tiny, 0.0, w_r)
    if w_r.sum() > 0:
        reference = ref_colour_nll_logspace(w_r, loc_r, beta_r, target_r, weight_eps=1e-10)
        scale = _component_scale(loc_r, beta_r, target_r)
        np.testing.assert_allclose(
            float(value), reference, rtol=0, atol=NLL_RTOL["float32"] * (1 + abs(reference) + scale)
        )
    else:
        assert float(value) == 0.0
    assert _finite(jax.grad(mixture.colour_nll, argnums=(0, 1, 2))(w_j, loc_j, beta_j, target_j))


@pytest.mark.parametrize("beta_value", [1e-12, 1e-6, 1.0, 1e6])
@pytest.mark.parametrize("residual", [0.0, 1e-3, 1.0])
def test_mixture_gradients_extreme_scales(beta_value, residual):
    """Named corners of the scale range: gradients finite and equal to the float64 ones where
    the float64 reference is itself smooth (the floor does not swallow the likelihood)."""
    target = np.asarray([0.5, 0.5, 0.5])
    location = np.tile(target + residual, (4, 1))
    location[0] = target  # one well-fitted component, so the mixture has mass
    beta = np.full((4, 3), beta_value)
    weights = np.asarray([0.1, 0.2, 0.3, 0.4])
    mixture = LaplaceMixture()
    args = tuple(jnp.asarray(a, jnp.float32) for a in (weights, location, beta, target))
    value = mixture.colour_nll(*args)
    grads = jax.grad(mixture.colour_nll, argnums=(0, 1, 2))(*args)
    assert _finite(value) and _finite(grads)
    reference = ref_colour_nll(weights, location, beta, target, weight_eps=1e-10, floor=1e-12)
    np.testing.assert_allclose(float(value), reference, rtol=NLL_RTOL["float32"], atol=NLL_RTOL["float32"])
    if beta_value >= 1e-6:
        # d/d beta of the float64 reference (smooth here: no |x| kink at the perturbed beta).
        ref_grad = central_difference(
            lambda b: ref_colour_nll(weights, location, b, target, weight_eps=1e-10, floor=1e-12),
            beta,
            step=1e-6 * beta_value,
        )
        np.testing.assert_allclose(
            np.asarray(grads[2]), ref_grad, rtol=GRAD_RTOL, atol=GRAD_ATOL / beta_value
        )


def test_linear_evaluation_overflows_where_log_space_does_not():
    """The released arithmetic overflows for tiny scales at zero residual; log space does not."""
    weights = jnp.asarray([0.5, 0.5])
    rgb = jnp.full((2, 3), 0.5)
    beta = jnp.full((2, 3), 1e-14)
    target = jnp.full(3, 0.5)
    linear = LaplaceMixture(evaluation="linear").colour_nll(weights, rgb, beta, target)
    log_space = LaplaceMixture().colour_nll(weights, rgb, beta, target)
    assert not np.isfinite(float(linear))
    expected = -np.log(np.float64(1.0) / (1 + 1e-10) * (1 / 2e-14) ** 3)
    np.testing.assert_allclose(float(log_space), expected, rtol=NLL_RTOL["float32"])


def test_linear_evaluation_saturates_with_zero_gradient():
    """A poorly fitted ray: linear float32 caps at -log(1e-12) with zero gradient; the exact
    log-space NLL keeps both value and gradient (float64 reference in log space)."""
    weights, rgb, beta, target = (
        np.asarray([0.5, 0.5]),
        np.full((2, 3), 0.9),
        np.full((2, 3), 0.01),
        np.full(3, 0.1),
    )
    args = tuple(jnp.asarray(a, jnp.float32) for a in (weights, rgb, beta, target))
    linear = LaplaceMixture(evaluation="linear")
    np.testing.assert_allclose(float(linear.colour_nll(*args)), -np.log(1e-12), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(jax.grad(linear.colour_nll, argnums=2)(*args)), 0.0)
    exact = LaplaceMixture(likelihood_floor=None)
    reference = ref_colour_nll_logspace(weights, rgb, beta, target, weight_eps=1e-10)
    np.testing.assert_allclose(float(exact.colour_nll(*args)), reference, rtol=NLL_RTOL["float32"])
    # d NLL / d beta = (1 - |r| / beta) / beta per channel, shared by the two equal components.
    expected_grad = 0.5 * (1 - 0.8 / 0.01) / 0.01
    np.testing.assert_allclose(
        np.asarray(jax.grad(exact.colour_nll, argnums=2)(*args)), expected_grad, rtol=1e-4
    )


def test_regenerated_weights_with_zero_predicted_depth():
    """mu_d = 0 everywhere: zero regenerated weights, the floor's constant NLL, finite gradients."""
    t_edges = jnp.linspace(2.0, 6.0, 9)
    density = jnp.full(8, 5.0)
    mixture = LaplaceMixture()
    rgb, beta, target = jnp.full((8, 3), 0.4), jnp.full((8, 3), 0.1), jnp.full(3, 0.5)

    def regen_nll(ray_depth):
        return mixture.colour_nll(blend_weights(density, t_edges, ray_depth), rgb, beta, target)

    np.testing.assert_allclose(float(regen_nll(jnp.zeros(8))), -np.log(1e-12), rtol=1e-6)
    grads = jax.grad(regen_nll)(jnp.zeros(8))
    assert _finite(grads)


# --- resampling -------------------------------------------------------------------------


def _ref_cdf_bounds(bins, weights, t):
    """Left and right limits of the CDF at `t` of the piecewise-constant pdf (float64)."""
    masses = weights / weights.sum()
    widths = np.diff(bins)
    safe = np.where(widths > 0, widths, 1.0)
    partial = np.clip((t - bins[:-1]) / safe, 0.0, 1.0)
    left = np.where(widths > 0, partial, (t > bins[:-1]).astype(float))
    right = np.where(widths > 0, partial, (t >= bins[:-1]).astype(float))
    return float((masses * left).sum()), float((masses * right).sum())


@SETTINGS
@given(
    data=st.data(),
    num_bins=st.sampled_from([1, 16]),
    num_draws=st.sampled_from([1, 2, 17]),
    jitter=st.booleans(),
)
def test_resampling_stress(data, num_bins, num_draws, jitter):
    bins = data.draw(ray_edges(num_bins))
    weight_kind = data.draw(st.sampled_from(["zero", "random", "huge"]))
    weights = np.zeros(num_bins)
    if weight_kind != "zero":
        weights = np.asarray(data.draw(st.lists(st.floats(0, 1), min_size=num_bins, max_size=num_bins)))
        weights = weights * (1e10 if weight_kind == "huge" else 1.0)
    bins_j, weights_j = jnp.asarray(bins, jnp.float32), jnp.asarray(weights, jnp.float32)
    key = jax.random.key(data.draw(st.integers(0, 2**16))) if jitter else None
    draws, grads = _resample_with_grads(bins_j, weights_j, key, num_draws)
    assert _finite(draws) and _finite(grads)
    draws_r = np.asarray(draws, np.float64)
    assert np.all(np.diff(draws_r) >= 0)
    assert np.all((draws_r >= bins_j[0]) & (draws_r <= bins_j[-1]))
    # Each draw lies where the float64 CDF of the blurred, padded weights reaches its stratum.
    bins_r = np.asarray(bins_j, np.float64)
    ref_weights = ref_blur_weights(np.asarray(weights_j, np.float64), 0.01)
    if jitter:
        lower_u = np.arange(num_draws) / num_draws
        upper_u = lower_u + 1.0 / num_draws
    else:
        lower_u = upper_u = np.linspace(0.0, 1.0 - 1e-5, num_draws)
    slack = 4 * EPS["float32"] * np.abs(bins_r).max()
    for draw, lo_u, hi_u in zip(draws_r, lower_u, upper_u, strict=True):
        cdf_left, _ = _ref_cdf_bounds(bins_r, ref_weights, draw - slack)
        _, cdf_right = _ref_cdf_bounds(bins_r, ref_weights, draw + slack)
        assert cdf_left - CDF_ATOL <= hi_u and lo_u <= cdf_right + CDF_ATOL


@functools.partial(jax.jit, static_argnums=3)
def _resample_with_grads(bins, weights, key, num_draws):
    """Draws from the blurred weights (mip-NeRF's padding 0.01), and the gradients of their
    sum in the edges and weights (what `stop_gradient=False` would propagate)."""
    draw = lambda b, w: sample_piecewise_constant(b, blur_weights(w, 0.01), num_draws, key=key)
    grads = jax.grad(lambda b, w: jnp.sum(draw(b, w)), argnums=(0, 1))(bins, weights)
    return draw(bins, weights), grads


@pytest.mark.parametrize("tiny", [1e-30, 1e-20, 1e-12])
def test_resampling_gradients_with_a_nearly_empty_bin(tiny):
    # Unblurred weights (as a sampler without mip-NeRF's padding sees them): a bin holding a
    # tiny but non-zero share once gave `0 * span^-2 = NaN` in the weights' gradient.
    bins = jnp.linspace(0.0, 1.0, 5)

    def total(weights):
        return jnp.sum(sample_piecewise_constant(bins, weights, 6, key=None))

    grads = jax.grad(total)(jnp.array([tiny, 1.0, 1.0, 1.0]))
    reference = jax.grad(total)(jnp.array([0.0, 1.0, 1.0, 1.0]))
    assert _finite(grads)
    # A share of `tiny` moves the CDF by about `tiny`: the gradients of the other bins are
    # those of the exactly empty bin to float32 rounding.
    np.testing.assert_allclose(np.asarray(grads[1:]), np.asarray(reference[1:]), rtol=1e-5, atol=1e-6)


def test_resampling_bfloat16():
    bins = jnp.linspace(2.0, 6.0, 17, dtype=jnp.bfloat16)
    for weights in (jnp.zeros(16, jnp.bfloat16), jnp.full(16, 1e10, jnp.bfloat16)):
        draws = sample_piecewise_constant(bins, blur_weights(weights, 0.01), 9, key=None)
        assert draws.dtype == jnp.bfloat16 and _finite(draws)
        values = np.asarray(draws.astype(jnp.float32), np.float64)
        # Uniform in both cases (equal weights): the quantiles of U(2, 6) to bfloat16 precision.
        np.testing.assert_allclose(
            values, 2.0 + 4.0 * np.linspace(0, 1 - 1e-5, 9), atol=6.0 * EPS["bfloat16"]
        )


# --- encodings --------------------------------------------------------------------------


@SETTINGS
@given(
    data=st.data(),
    dtype=st.sampled_from(["float32", "bfloat16"]),
    max_deg=st.sampled_from([1, 4, 16]),
)
def test_encodings_stress(data, dtype, max_deg):
    means = np.asarray(data.draw(st.lists(st.floats(-10, 10), min_size=3, max_size=3)))
    log_var = np.asarray(data.draw(st.lists(st.floats(-30, 30), min_size=3, max_size=3)))
    covs = np.where(
        np.asarray(data.draw(st.lists(st.booleans(), min_size=3, max_size=3))), 0.0, 10.0**log_var
    )
    (means_j, covs_j), (means_r, covs_r) = _cast(dtype, means, covs)
    pe, ipe, grads = _encodings_with_grads(means_j, covs_j, max_deg)
    assert pe.dtype == ipe.dtype == DTYPES[dtype]
    assert _finite(pe) and _finite(ipe)
    scales = 2.0 ** np.arange(0, max_deg)
    phases = (scales[:, None] * means_r[None, :]).reshape(-1)
    # Rounding of `phase + pi/2` and of the sine's argument reduction, at each phase's size.
    tolerance = ENCODING_ULPS * EPS[dtype] * (2.0 + np.concatenate([phases, phases]))
    tolerance = np.abs(tolerance) + ENCODING_ULPS * EPS[dtype] * 2.0
    np.testing.assert_array_less(
        np.abs(
            np.asarray(pe.astype(jnp.float32), np.float64)[3:]
            - ref_positional_encoding(means_r, 0, max_deg)[3:]
        ),
        tolerance,
    )
    variances = (scales[:, None] ** 2 * covs_r[None, :]).reshape(-1)
    damping = np.exp(-0.5 * np.concatenate([variances, variances]))
    ref_ipe = damping * ref_positional_encoding(means_r, 0, max_deg, append_identity=False)
    np.testing.assert_array_less(
        np.abs(np.asarray(ipe.astype(jnp.float32), np.float64) - ref_ipe), tolerance + 4 * EPS[dtype]
    )
    assert _finite(grads)


@functools.partial(jax.jit, static_argnums=2)
def _encodings_with_grads(means, covs, max_deg):
    ipe_sum = lambda m, c: jnp.sum(integrated_positional_encoding(m, c, 0, max_deg)).astype(jnp.float32)
    grads = jax.grad(ipe_sum, argnums=(0, 1))(means, covs)
    pe = positional_encoding(means, 0, max_deg)
    return pe, integrated_positional_encoding(means, covs, 0, max_deg), grads


@SETTINGS
@example(t0=1.1754943508222875e-38, width=0.0)  # found by hypothesis: moments below float32's range
@given(
    t0=st.one_of(st.just(0.0), st.floats(0.0, 10.0)),
    width=st.one_of(st.just(0.0), st.floats(1e-3, 10.0), st.just(1e10)),
)
def test_frustum_moments_stress(t0, width):
    t0_j = jnp.asarray([t0], jnp.float32)
    t1_j = jnp.asarray([t0 + width], jnp.float32)
    radius = jnp.asarray([0.01], jnp.float32)
    moments = conical_frustum_moments(t0_j, t1_j, radius)
    assert _finite(moments)
    t0_r, t1_r = as_f64(t0_j[0], t1_j[0])
    if t1_r > 0:
        reference = quadrature_frustum_moments(t0_r, t1_r, 0.01, "cone")
        # Quadrature of `t^2`-weighted moments cancels catastrophically when the interval is
        # a tiny fraction of t; compare each moment relative to the size it is computed at.
        # Below float32's smallest normal number (t near 1e-38: t^2 underflows) only that
        # absolute resolution is left.
        sizes = (t1_r, t1_r**2, 0.01**2 * t1_r**2)
        floor = float(np.finfo(np.float32).tiny)
        for value, ref, size in zip(moments, reference, sizes, strict=True):
            np.testing.assert_allclose(float(value[0]), ref, rtol=0, atol=MOMENT_RTOL * size + floor)
    else:
        np.testing.assert_array_equal(np.asarray(moments), 0.0)
    grads = jax.grad(
        lambda a, b: sum(jnp.sum(m) for m in conical_frustum_moments(a, b, radius)), argnums=(0, 1)
    )(t0_j, t1_j)
    assert _finite(grads)
