import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mixnerf_eqx.nn import depth_quantile


def _numpy_quantile(weights, edges, q):
    # Inverse of the piecewise-linear CDF by interpolation, in float64.
    cdf = np.concatenate([[0.0], np.cumsum(weights / weights.sum())])
    return float(np.interp(q, cdf, edges))


@pytest.mark.parametrize("q", [0.1, 0.5, 0.9])
def test_quantile_matches_interpolated_cdf(q):
    rng = np.random.default_rng(0)
    for _ in range(5):
        edges = np.sort(rng.uniform(2.0, 6.0, 17))
        weights = rng.uniform(0.0, 1.0, 16) ** 3
        value = depth_quantile(jnp.asarray(weights, jnp.float32), jnp.asarray(edges, jnp.float32), q)
        assert float(value) == pytest.approx(_numpy_quantile(weights, edges, q), abs=1e-4)


def test_median_of_one_hot_is_the_interval_midpoint():
    edges = jnp.linspace(2.0, 6.0, 9)
    weights = jnp.zeros(8).at[5].set(0.7)
    assert float(depth_quantile(weights, edges)) == pytest.approx(float(edges[5] + edges[6]) / 2, abs=1e-5)


def test_empty_ray_reports_far_and_batches_under_vmap():
    edges = jnp.tile(jnp.linspace(2.0, 6.0, 9), (3, 1))
    weights = jnp.stack([jnp.zeros(8), jnp.ones(8), jnp.zeros(8).at[0].set(1.0)])
    values = jax.jit(jax.vmap(depth_quantile))(weights, edges)
    np.testing.assert_allclose(np.asarray(values), [6.0, 4.0, 2.25], atol=1e-5)


def test_rejects_bad_quantile():
    with pytest.raises(ValueError, match="quantile"):
        depth_quantile(jnp.ones(4), jnp.linspace(0.0, 1.0, 5), 1.5)
