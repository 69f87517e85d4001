"""Stratified and hierarchical samplers, and inverse-transform sampling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    as_f32,
    key_fixture,  # noqa: F401 (the `key` fixture)
    make_ray,
    quadrature_frustum_moments,
    ref_blur_weights,
    ref_cdf,
)

from mixnerf_eqx.nn import HierarchicalSampler, RaySamples, StratifiedSampler
from mixnerf_eqx._nn.sampler import sample_piecewise_constant
from mixnerf_eqx._nn.sampler.hierarchical import blur_weights

NEAR, FAR = 2.0, 6.0

# --- stratified -----------------------------------------------------------------------------


def test_stratified_is_evenly_spaced_without_key():
    edges = np.asarray(StratifiedSampler(num_samples=8).sample_edges(make_ray(), None, None, key=None))
    assert edges.shape == (9,)
    assert edges[0] == NEAR and edges[-1] == FAR
    np.testing.assert_allclose(edges, np.linspace(NEAR, FAR, 9), rtol=1e-6, atol=0)


def test_stratified_lindisp_is_evenly_spaced_in_disparity():
    sampler = StratifiedSampler(num_samples=8, lindisp=True)
    edges = np.asarray(sampler.sample_edges(make_ray(), None, None, key=None), np.float64)
    np.testing.assert_allclose(edges[[0, -1]], [NEAR, FAR], rtol=1e-6)
    np.testing.assert_allclose(1 / edges, np.linspace(1 / NEAR, 1 / FAR, 9), rtol=1e-6)
    assert not np.allclose(edges, np.linspace(NEAR, FAR, 9), rtol=1e-2)


def test_stratified_with_key_jitters_within_strata(key):
    sampler = StratifiedSampler(num_samples=8)
    ray = make_ray()
    keys = jax.random.split(key, 500)
    sample = jax.jit(jax.vmap(lambda k: sampler.sample_edges(ray, None, None, key=k)))
    edges = np.asarray(sample(keys), np.float64)
    assert edges.shape == (500, 9)
    assert np.all(np.diff(edges, axis=-1) >= 0)
    assert np.all((edges >= NEAR) & (edges <= FAR))
    # Each edge stays in the half-intervals around its even position, and fills them.
    even = np.linspace(NEAR, FAR, 9)
    mids = 0.5 * (even[1:] + even[:-1])
    lower = np.concatenate([[NEAR], mids])
    upper = np.concatenate([mids, [FAR]])
    assert np.all((edges >= lower - 1e-6) & (edges <= upper + 1e-6))
    spread = edges.max(axis=0) - edges.min(axis=0)
    assert np.all(spread > 0.9 * (upper - lower))
    same = np.asarray(sampler.sample_edges(ray, None, None, key=keys[0]))
    np.testing.assert_array_equal(same, edges[0])


# --- inverse-transform sampling -------------------------------------------------------------


def _bins_and_weights(seed, num_bins=16):
    rng = np.random.default_rng(seed)
    bins = as_f32(np.sort(np.concatenate([[NEAR, FAR], rng.uniform(NEAR, FAR, num_bins - 1)])))
    weights = as_f32(rng.uniform(0.0, 1.0, num_bins) ** 3)
    return bins, weights


@jax.jit
def _jittered_draws(bins, weights, keys):
    """Eight stratified draws per key."""
    return jax.vmap(lambda k: sample_piecewise_constant(bins, weights, 8, key=k))(keys)


def test_deterministic_draws_are_evenly_spaced_quantiles():
    bins, weights = _bins_and_weights(0)
    draws = sample_piecewise_constant(jnp.asarray(bins), jnp.asarray(weights), 32, key=None)
    again = sample_piecewise_constant(jnp.asarray(bins), jnp.asarray(weights), 32, key=None)
    draws = np.asarray(draws, np.float64)
    np.testing.assert_array_equal(draws, np.asarray(again))
    assert np.all(np.diff(draws) >= 0)
    assert bins[0] <= draws[0] and draws[-1] <= bins[-1]
    # The deterministic draws sit at probabilities evenly spaced in [0, 1 - eps].
    np.testing.assert_allclose(ref_cdf(bins, weights, draws), np.linspace(0, 1, 32), atol=1e-4)


def test_jittered_draws_are_stratified():
    bins, weights = _bins_and_weights(1)
    keys = jax.random.split(jax.random.key(2), 64)
    draws = _jittered_draws(bins, weights, keys)
    draws = np.asarray(draws, np.float64)
    assert np.all(np.diff(draws, axis=-1) >= 0)
    assert np.all((draws >= bins[0]) & (draws <= bins[-1]))
    assert len(np.unique(draws[:, 0])) == 64
    # One draw per 1/8 of probability.
    probability = ref_cdf(bins, weights, draws)
    strata = np.arange(8)
    assert np.all(probability >= strata / 8 - 1e-4)
    assert np.all(probability <= (strata + 1) / 8 + 1e-4)


def test_jittered_draws_follow_the_piecewise_constant_pdf():
    bins, weights = _bins_and_weights(3, num_bins=12)
    keys = jax.random.split(jax.random.key(3), 4000)
    draws = _jittered_draws(bins, weights, keys)
    draws = np.asarray(draws, np.float64).ravel()
    # Split every bin in halves, so a wrong within-bin placement shows as well as wrong bin mass.
    cells = np.sort(np.concatenate([bins, 0.5 * (bins[1:] + bins[:-1])]))
    expected = np.repeat(weights / weights.sum(), 2) / 2
    keep = expected > 0
    counts, _ = np.histogram(draws, cells)
    n = draws.size
    chi_square = np.sum((counts[keep] - n * expected[keep]) ** 2 / (n * expected[keep]))
    dof = keep.sum() - 1
    # Mean dof, sd sqrt(2 dof) for iid draws; stratified draws only reduce the spread.
    assert chi_square < dof + 6 * np.sqrt(2 * dof)


def test_one_hot_weights_place_every_draw_in_their_bin():
    bins, _ = _bins_and_weights(4)
    weights = np.zeros(16, np.float32)
    weights[5] = 1.0
    draws = np.asarray(sample_piecewise_constant(jnp.asarray(bins), jnp.asarray(weights), 33, key=None))
    assert np.all((draws >= bins[5]) & (draws <= bins[6]))


def test_zero_weights_give_uniform_draws():
    bins = jnp.linspace(NEAR, FAR, 17)
    draws = np.asarray(sample_piecewise_constant(bins, jnp.zeros(16), 33, key=None), np.float64)
    assert np.all(np.isfinite(draws))
    assert draws[0] == NEAR
    np.testing.assert_allclose(np.diff(draws), (FAR - NEAR) * (1 - EPS32) / 32, rtol=1e-5)


EPS32 = float(np.finfo(np.float32).eps)


def test_deterministic_draws_span_zero_to_one_minus_float32_epsilon():
    """The released resampler draws at `linspace(0, 1 - eps)` with float32's machine epsilon
    (mip-NeRF's PyTorch ports use 1e-5, which ends the last draw 1e-5 short of the far edge)."""
    draws = np.asarray(sample_piecewise_constant(jnp.asarray([0.0, 1.0]), jnp.ones(1), 5, key=None))
    np.testing.assert_allclose(draws, np.linspace(0.0, 1.0 - EPS32, 5), rtol=0, atol=1e-7)
    assert draws[-1] > 1.0 - 1e-6


def test_padding_only_lifts_the_weight_sum_to_float32_epsilon():
    """Weights summing to 1e-6 (above float32's epsilon) are used as they are: every draw
    lands in the one bin that has weight. Below epsilon the padding spreads them out."""
    bins = jnp.linspace(0.0, 4.0, 5)
    weights = jnp.asarray([0.0, 0.0, 1e-6, 0.0])
    draws = np.asarray(sample_piecewise_constant(bins, weights, 9, key=None))
    assert np.all((draws >= 2.0) & (draws <= 3.0))
    tiny = np.asarray(sample_piecewise_constant(bins, weights * 1e-3, 9, key=None))
    assert tiny[0] < 2.0 and tiny[-1] > 3.0


# --- blur and the hierarchical sampler ------------------------------------------------------


@pytest.mark.parametrize("size", [1, 2, 9])
@pytest.mark.parametrize("padding", [0.0, 0.01])
def test_blur_weights_matches_reference(size, padding):
    weights = as_f32(np.random.default_rng(size).uniform(0, 1, size))
    got = np.asarray(blur_weights(jnp.asarray(weights), padding))
    np.testing.assert_allclose(got, ref_blur_weights(weights, padding), rtol=1e-6)


def _hierarchical_edges(num_samples, previous_weights, *, padding=0.01, key=None, stop_gradient=True):
    sampler = HierarchicalSampler(
        num_samples=num_samples, resample_padding=padding, stop_gradient=stop_gradient
    )
    previous_edges = jnp.linspace(NEAR, FAR, previous_weights.shape[0] + 1)
    return previous_edges, sampler.sample_edges(make_ray(), previous_edges, previous_weights, key=key)


@pytest.mark.parametrize("use_key", [False, True])
def test_hierarchical_edges_concentrate_on_the_weights(use_key):
    weights = jnp.zeros(16).at[7].set(1.0)
    key = jax.random.key(5) if use_key else None
    previous, edges = _hierarchical_edges(64, weights, key=key)
    previous, edges = np.asarray(previous), np.asarray(edges)
    assert edges.shape == (65,)
    assert np.all(np.diff(edges) >= 0)
    assert previous[0] <= edges[0] and edges[-1] <= previous[-1]
    # The blur spreads bin 7 over bins 6-8 (mass 2 of 2 + 16 * 0.01 with the padding).
    near_bin = (edges >= previous[6]) & (edges <= previous[9])
    assert near_bin.mean() > 0.9
    _, unpadded = _hierarchical_edges(64, weights, padding=0.0, key=key)
    unpadded = np.asarray(unpadded)
    assert np.all((unpadded >= previous[6]) & (unpadded <= previous[9]))


def test_hierarchical_sampler_is_deterministic_without_key():
    weights = jnp.asarray(_bins_and_weights(6)[1])
    _, first = _hierarchical_edges(32, weights)
    _, second = _hierarchical_edges(32, weights)
    np.testing.assert_array_equal(np.asarray(first), np.asarray(second))
    _, jittered = _hierarchical_edges(32, weights, key=jax.random.key(0))
    assert not np.allclose(np.asarray(first), np.asarray(jittered))


@pytest.mark.parametrize("stop_gradient", [True, False])
def test_gradients_stop_at_the_resampled_edges(stop_gradient):
    weights = jnp.asarray(_bins_and_weights(7)[1])

    def edge_sum(previous_weights):
        _, edges = _hierarchical_edges(32, previous_weights, stop_gradient=stop_gradient)
        return jnp.sum(edges**2)

    grad = np.asarray(jax.jit(jax.grad(edge_sum))(weights))
    if stop_gradient:
        np.testing.assert_array_equal(grad, 0.0)
    else:
        assert np.max(np.abs(grad)) > 0  # so the check above can tell the difference


# --- RaySamples from __call__ ---------------------------------------------------------------


@pytest.mark.parametrize("frustum", ["cone", "cylinder"])
@pytest.mark.parametrize("level", ["stratified", "hierarchical"])
def test_sampler_call_puts_means_on_the_ray_at_frustum_means(frustum, level):
    origin, direction, radius = (0.4, 0.1, 1.5), (0.3, -0.6, -1.2), 0.05
    ray = make_ray(origin, direction, radius=radius)
    if level == "stratified":
        samples = StratifiedSampler(num_samples=8, frustum=frustum)(ray, key=jax.random.key(0))
    else:
        previous = jnp.linspace(NEAR, FAR, 9)
        sampler = HierarchicalSampler(num_samples=8, frustum=frustum)
        samples = sampler(ray, previous, jnp.asarray(_bins_and_weights(8, 8)[1]), key=jax.random.key(0))
    assert isinstance(samples, RaySamples)
    assert samples.t_edges.shape == (9,) and samples.means.shape == samples.covs.shape == (8, 3)
    edges = np.asarray(samples.t_edges, np.float64)
    origin, direction = as_f32(origin).astype(np.float64), as_f32(direction).astype(np.float64)
    radius = float(as_f32(radius))
    t_mean = [
        quadrature_frustum_moments(t0, t1, radius, frustum)[0]
        for t0, t1 in zip(edges[:-1], edges[1:], strict=True)
    ]
    expected = origin + np.asarray(t_mean)[:, None] * direction
    np.testing.assert_allclose(np.asarray(samples.means), expected, rtol=1e-5, atol=1e-5)
    assert np.all(np.asarray(samples.covs) > 0)


@pytest.mark.parametrize("sampler", [StratifiedSampler, HierarchicalSampler])
def test_every_sampler_refuses_fewer_than_one_sample(sampler):
    with pytest.raises(ValueError, match="num_samples must be at least 1, got 0"):
        sampler(num_samples=0)
