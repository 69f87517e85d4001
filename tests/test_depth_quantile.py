import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._nn.compositing import termination_quantile
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


def _first_reaching(weights, edges, q):
    # inf {t : F(t) >= q} by brute force in float64: F on a fine grid inside each interval.
    masses = weights / weights.sum()
    before = 0.0
    for i, mass in enumerate(masses):
        if before + mass >= q and mass > 0:
            return edges[i] + (q - before) / mass * (edges[i + 1] - edges[i])
        before += mass
    return edges[-1]


def test_the_quantile_is_exact_with_empty_and_zero_width_intervals():
    """The exact inverse of the piecewise-linear distribution function, to float32's resolution:
    intervals without mass are never answered (the first interval that reaches the level is),
    a zero-width interval answers its edge, and many levels share one ray under vmap."""
    rng = np.random.default_rng(3)
    levels = np.array([1e-6, 0.025, 0.1, 0.25, 0.5, 0.75, 0.9, 0.975, 0.999, 1 - 1e-6])
    rays_edges, rays_weights = [], []
    while len(rays_edges) < 200:
        edges = np.sort(rng.uniform(2.0, 6.0, 33))
        edges[rng.integers(0, 33, 3)] = edges[rng.integers(0, 33)]  # some zero-width intervals
        weights = rng.uniform(0.0, 1.0, 32) ** 4 * (rng.uniform(size=32) < 0.6)  # some without mass
        if weights.sum() > 0:
            rays_edges.append(np.sort(edges))
            rays_weights.append(weights)
    termination = mx.uncertainty.TerminationDistribution(
        jnp.asarray(np.stack(rays_weights), jnp.float32), jnp.asarray(np.stack(rays_edges), jnp.float32)
    )
    got = np.asarray(termination.quantiles(levels), np.float64)  # (levels, rays)
    want = np.array(
        [[_first_reaching(w, e, q) for w, e in zip(rays_weights, rays_edges, strict=True)] for q in levels]
    )
    # Where the distribution function is steep the answer is float32-exact: edges near 6 are
    # 4.8e-7 apart and the cumulative sum's rounding moves the answer by a few of those.
    interior = levels <= 0.975
    assert float(np.max(np.abs(got - want)[interior])) < 1e-5
    # Everywhere, near the ends too (a level within 1e-6 of 1 can fall in the last interval
    # with mass, a tiny one, where a rounding of 1e-7 moves the answer far): the answer is the
    # quantile of a level within 1e-6 of the one asked, F(t - d) <= q + 1e-6 <= F(t + d) + 2e-6.
    for i, q in enumerate(levels):
        for w, e, t in zip(rays_weights, rays_edges, got[i], strict=True):
            assert _cdf(w, e, t - 1e-6) <= q + 1e-6 and _cdf(w, e, t + 1e-6) >= q - 1e-6


def _cdf(weights, edges, t):
    # The float64 distribution function (a zero-width interval's mass counts from its edge on).
    masses = weights / weights.sum()
    widths = np.diff(edges)
    inside = np.clip((t - edges[:-1]) / np.where(widths > 0, widths, 1.0), 0, 1)
    covered = np.where(widths > 0, inside, t >= edges[:-1])
    return float(np.sum(masses * covered))


def test_the_quantiles_gradient_is_the_implicit_one():
    """d quantile / d parameters = -(dF/d parameters) / f at the quantile (the implicit function
    theorem, which the former bisection differentiated), checked against float64 differences."""
    rng = np.random.default_rng(4)
    edges = np.sort(rng.uniform(2.0, 6.0, 17))
    weights = rng.uniform(0.2, 1.0, 16)

    def quantile64(w, e, q=0.3):
        return _first_reaching(w, e, q)

    grad_w, grad_e = jax.grad(lambda w, e: depth_quantile(w, e, 0.3), argnums=(0, 1))(
        jnp.asarray(weights, jnp.float32), jnp.asarray(edges, jnp.float32)
    )
    step = 1e-6
    for i in range(16):
        bump = np.zeros(16)
        bump[i] = step
        numeric = (quantile64(weights + bump, edges) - quantile64(weights - bump, edges)) / (2 * step)
        assert float(grad_w[i]) == pytest.approx(numeric, rel=1e-3, abs=1e-4)
    for i in range(17):
        bump = np.zeros(17)
        bump[i] = step
        numeric = (quantile64(weights, edges + bump) - quantile64(weights, edges - bump)) / (2 * step)
        assert float(grad_e[i]) == pytest.approx(numeric, rel=1e-3, abs=1e-4)


def test_the_former_tolerance_warns():
    # A FutureWarning: shown by default wherever it is raised from (the shape-check wrapper
    # stands between the caller and the function).
    with pytest.warns(FutureWarning, match="tolerance is no longer used"):
        depth_quantile(jnp.ones(4), jnp.linspace(0.0, 1.0, 5), 0.5, tolerance=1e-6)


def test_a_level_near_one_stays_within_the_mass():
    """Trailing intervals without mass are never answered, however near 1 the level: the
    cumulative sum is normalised by its own end, so it reaches exactly 1 at the last mass."""
    rng = np.random.default_rng(5)
    worst = 0.0
    for _ in range(300):
        weights = np.concatenate([rng.uniform(0.0, 1.0, 40), np.zeros(88)])
        edges = np.linspace(2.0, 6.0, 129)
        value = depth_quantile(jnp.asarray(weights, jnp.float32), jnp.asarray(edges, jnp.float32), 1 - 1e-7)
        worst = max(worst, float(value))
    assert worst <= edges[40] + 1e-5  # the last interval with mass ends at 3.25


def test_a_level_of_zero_is_the_first_edge():
    """F is 0 up to the first mass, so inf {t : F(t) >= 0} is the first edge; a tiny level
    lands just inside the first interval with mass."""
    weights, edges = jnp.asarray([0.0, 0.0, 1.0, 1.0]), jnp.linspace(0.0, 4.0, 5)
    assert float(termination_quantile(0.0, weights, edges)) == 0.0
    assert float(depth_quantile(weights, edges, 1e-6)) == pytest.approx(2.0, abs=1e-5)


@pytest.mark.parametrize(
    ("weights", "edges", "level", "answer"),
    [
        # A gap without mass: the level the first interval ends at is answered at its end,
        # not past the gap (inf {t : F(t) >= q}).
        ([1.0, 0.0, 1.0], [0.0, 1.0, 2.0, 3.0], 0.5, 1.0),
        ([1.0, 0.0, 1.0], [0.0, 1.0, 2.0, 3.0], 0.25, 0.5),
        ([1.0, 0.0, 1.0], [0.0, 1.0, 2.0, 3.0], 0.75, 2.5),
        # A zero-width interval holding a third of the mass: F jumps there, so every level it
        # spans is answered at its edge.
        ([1.0, 1.0, 1.0], [0.0, 1.0, 1.0, 2.0], 0.5, 1.0),
        ([1.0, 1.0, 1.0], [0.0, 1.0, 1.0, 2.0], 0.625, 1.0),
        ([1.0, 1.0, 1.0], [0.0, 1.0, 1.0, 2.0], 0.8125, 1.4375),
    ],
)
def test_hand_worked_quantiles_at_gaps_and_jumps(weights, edges, level, answer):
    value = depth_quantile(jnp.asarray(weights), jnp.asarray(edges), level)
    assert float(value) == pytest.approx(answer, abs=1e-6)
