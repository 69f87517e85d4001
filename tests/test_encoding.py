"""Positional encoding, integrated positional encoding and frustum Gaussians.

References: a direct numpy positional encoding, Monte-Carlo expectations of it under a
Gaussian, Gauss-Legendre quadrature of a frustum's moments along the ray, and Monte-Carlo
points drawn uniformly inside the 3D frustum.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    as_f32,
    monte_carlo_frustum_points,
    monte_carlo_ipe,
    quadrature_frustum_moments,
    ref_positional_encoding,
)

from mixnerf_eqx.nn import frustum_gaussians, integrated_positional_encoding, positional_encoding
from mixnerf_eqx._nn.encoding import conical_frustum_moments, cylinder_moments

# --- positional encoding ----------------------------------------------------------------


@pytest.mark.parametrize("min_deg, max_deg", [(0, 4), (2, 5), (0, 1)])
def test_positional_encoding_matches_numpy(min_deg, max_deg):
    rng = np.random.default_rng(0)
    x = as_f32(rng.uniform(-2, 2, (7, 3)))
    got = np.asarray(positional_encoding(jnp.asarray(x), min_deg, max_deg))
    assert got.shape == (7, 3 + 2 * 3 * (max_deg - min_deg))
    # Phases reach 2^(max_deg-1) * 2, so float32 sin is good to a few ulp of that.
    np.testing.assert_allclose(got, ref_positional_encoding(x, min_deg, max_deg), atol=2e-6, rtol=0)


def test_positional_encoding_without_identity():
    x = as_f32(np.random.default_rng(1).uniform(-1, 1, 3))
    got = np.asarray(positional_encoding(jnp.asarray(x), 0, 3, append_identity=False))
    assert got.shape == (2 * 3 * 3,)
    np.testing.assert_allclose(got, ref_positional_encoding(x, 0, 3, append_identity=False), atol=2e-6)


# --- integrated positional encoding -----------------------------------------------------

IPE_CASES = [
    # (mean, variance per axis): tiny variances (IPE ~ PE), frequencies straddling
    # exp(-a^2 var / 2) ~ 1/e, and a large variance that wipes out every frequency.
    ([0.3, -1.2, 0.7], [1e-8, 1e-6, 1e-7]),
    ([0.5, 0.1, -0.4], [1e-3, 1e-2, 3e-2]),
    ([-1.5, 2.0, 0.05], [1.0, 4e-3, 2e-4]),
]


@pytest.mark.parametrize("mean, var", IPE_CASES)
def test_ipe_matches_monte_carlo(mean, var):
    rng = np.random.default_rng(2)
    min_deg, max_deg = 0, 6
    expected, standard_error = monte_carlo_ipe(rng, mean, var, min_deg, max_deg, num_draws=200_000)
    got = np.asarray(
        integrated_positional_encoding(jnp.asarray(as_f32(mean)), jnp.asarray(as_f32(var)), min_deg, max_deg)
    )
    assert got.shape == (2 * 3 * (max_deg - min_deg),)
    # 5 standard errors of the Monte-Carlo mean, plus float32 rounding of phases up to ~70.
    np.testing.assert_array_less(np.abs(got - expected), 5 * standard_error + 1e-4)


def test_ipe_of_a_point_is_the_positional_encoding():
    x = as_f32(np.random.default_rng(3).uniform(-2, 2, (4, 3)))
    got = np.asarray(integrated_positional_encoding(jnp.asarray(x), jnp.zeros((4, 3)), 1, 5))
    np.testing.assert_allclose(got, ref_positional_encoding(x, 1, 5, append_identity=False), atol=2e-6)


# --- frustum moments along the ray ------------------------------------------------------

INTERVALS = [(0.0, 1.0), (2.0, 6.0), (1.0, 1.001), (3.0, 3.0001), (0.2, 10.0)]


@pytest.mark.parametrize("t0, t1", INTERVALS)
def test_conical_frustum_moments_match_quadrature(t0, t1):
    radius = 0.7
    t_mean, t_var, r_var = (
        float(v) for v in conical_frustum_moments(jnp.float32(t0), jnp.float32(t1), jnp.float32(radius))
    )
    ref_mean, ref_var, ref_r_var = quadrature_frustum_moments(
        *(float(v) for v in as_f32(t0, t1, radius)), "cone"
    )
    # The mip-NeRF r_var formula, radius^2 (mu^2/4 + 5/12 hw^2 - 4/15 hw^4 / (3 mu^2 + hw^2)),
    # is radius^2 E[t^2] / 4 under the cone's t^2 density: each axis across the ray of a disc
    # of radius radius * t has variance (radius t)^2 / 4. Thin intervals would lose every digit
    # of t_var to cancellation in the naive form; the stable form keeps float32 precision.
    np.testing.assert_allclose(t_mean, ref_mean, rtol=1e-6)
    np.testing.assert_allclose(t_var, ref_var, rtol=1e-4)
    np.testing.assert_allclose(r_var, ref_r_var, rtol=1e-5)


@pytest.mark.parametrize("t0, t1", INTERVALS)
def test_cylinder_moments_match_quadrature(t0, t1):
    radius = 0.7
    t_mean, t_var, r_var = (
        float(v) for v in cylinder_moments(jnp.float32(t0), jnp.float32(t1), jnp.float32(radius))
    )
    ref_mean, ref_var, ref_r_var = quadrature_frustum_moments(
        *(float(v) for v in as_f32(t0, t1, radius)), "cylinder"
    )
    np.testing.assert_allclose(t_mean, ref_mean, rtol=1e-6)
    np.testing.assert_allclose(t_var, ref_var, rtol=1e-4)
    np.testing.assert_allclose(r_var, ref_r_var, rtol=1e-6)


# --- frustum Gaussians in world space ---------------------------------------------------


@pytest.mark.parametrize("shape", ["cone", "cylinder"])
@pytest.mark.parametrize(
    "direction",
    # Unnormalised, off-axis directions: ||d|| != 1 separates "radius per unit t" from
    # "radius per unit length", and no axis-aligned shortcut holds.
    [[0.3, -0.4, -1.0], [1.5, 0.2, 0.9]],
)
def test_frustum_gaussians_match_monte_carlo(shape, direction):
    rng = np.random.default_rng(4)
    origin = as_f32([0.5, -0.2, 1.0])
    direction = as_f32(direction)
    radius = 0.15
    t_edges = as_f32([0.5, 1.0, 1.6, 3.0])
    means, covs = frustum_gaussians(
        jnp.asarray(t_edges), jnp.asarray(origin), jnp.asarray(direction), jnp.full((1,), radius), shape
    )
    means, covs = np.asarray(means), np.asarray(covs)
    assert means.shape == covs.shape == (3, 3)
    num_points = 200_000
    for i in range(3):
        points = monte_carlo_frustum_points(
            rng, origin, direction, float(t_edges[i]), float(t_edges[i + 1]), radius, shape, num_points
        )
        centred = points - points.mean(axis=0)
        mc_var = (centred**2).mean(axis=0)
        mean_error = np.sqrt(mc_var / num_points)
        var_error = np.sqrt(((centred**4).mean(axis=0) - mc_var**2) / num_points)
        np.testing.assert_array_less(np.abs(means[i] - points.mean(axis=0)), 5 * mean_error + 1e-6)
        np.testing.assert_array_less(np.abs(covs[i] - mc_var), 5 * var_error + 1e-7)


@pytest.mark.parametrize("shape", ["cone", "cylinder"])
def test_frustum_means_lie_on_the_ray(shape):
    origin = as_f32([1.0, 2.0, -0.5])
    direction = as_f32([0.2, -0.7, -1.1])
    t_edges = as_f32([2.0, 2.5, 4.0, 6.0])
    means, _ = frustum_gaussians(
        jnp.asarray(t_edges), jnp.asarray(origin), jnp.asarray(direction), jnp.full((1,), 0.01), shape
    )
    offsets = np.asarray(means, np.float64) - origin
    t = offsets @ direction / (direction @ direction)
    np.testing.assert_allclose(offsets, t[:, None] * direction[None, :], atol=1e-5)
    expected_t = [
        quadrature_frustum_moments(t0, t1, 0.01, shape)[0]
        for t0, t1 in zip(t_edges[:-1], t_edges[1:], strict=True)
    ]
    np.testing.assert_allclose(t, expected_t, rtol=1e-5)
