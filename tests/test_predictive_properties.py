"""Properties of the predictive API over arbitrary inputs (hypothesis).

Every public entry point of the predictive path (`ColourMixture`, `TerminationDistribution`,
`mx.predictive`, `mx.uncertainty.summarise`) is called with scalars of every accepted type, finite or not,
and ray batches of zero, one or a few rays. Each call either raises a `ValueError` exactly
when an input is out of its domain, or returns finite numbers that satisfy the distribution's
invariants: quantiles non-decreasing in the level, lower <= upper, the distribution function
at a quantile equal to its level (so an interval holds its mass), depths within the rays'
bounds. The distributions' own arithmetic is compared with float64 references elsewhere
(`test_predictive.py`); this file checks the boundary and the invariants.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import mixnerf_eqx as mx
from mixnerf_eqx._nn.compositing import termination_cdf
from mixnerf_eqx._predictive.distribution import ColourMixture, TerminationDistribution

SETTINGS = settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

_ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)
# One real number in every type the API accepts: Python int and float, numpy scalars and
# 0-d arrays, JAX arrays. Around the domain's edges more often than a uniform draw would be.
_EDGES = st.sampled_from([0.0, 1.0, -0.0, 1e-12, 1 - 1e-7, 0.5, 2.0, -1.0, math.nan, math.inf, -math.inf])
_REALS = st.one_of(_ANY_FLOAT, _EDGES, st.floats(0.0, 1.0, exclude_min=True, exclude_max=True))
# The same for the float32 types (a float64 beyond float32's range would overflow in the cast).
_REALS32 = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    _EDGES,
    st.floats(0.0, 1.0, exclude_min=True, exclude_max=True, width=32),
)
SCALARS = st.one_of(
    _REALS,
    st.integers(-2, 3),
    _REALS32.map(np.float32),
    _REALS.map(np.float64),
    _REALS.map(np.asarray),
    _REALS32.map(jnp.asarray),
)
RAY_COUNTS = st.sampled_from([0, 1, 3])


def _value(x) -> float:
    """What a scalar means, in float64 (a JAX array of a float64 that overflows float32 is inf)."""
    return float(np.asarray(x))


def _level_ok(x) -> bool:
    """In (0, 1), in float64 and in the float32 the distributions compute in (1e-50 is 0 there),
    and not below float32's smallest normal number (XLA on the CPU flushes subnormals to 0)."""
    value = _value(x)
    return math.isfinite(value) and 0.0 < value < 1.0 and np.finfo(np.float32).tiny <= np.float32(value) < 1.0


def _mass_ok(mass) -> bool:
    """A central interval's mass and the two levels it is read at, formed as the API forms them
    (in the mass's own arithmetic: float32 for float32 scalars)."""
    return _level_ok(mass) and _level_ok(0.5 * (1.0 - mass)) and _level_ok(0.5 * (1.0 + mass))


def _temperature_ok(x, scales) -> bool:
    """Finite and positive, in float64 and in float32 (at least float32's smallest normal
    number: XLA flushes subnormal ones to zero), and its product with every scale of the
    mixture (`scales`) finite and positive in float32 too."""
    value = _value(x)
    tiny = np.finfo(np.float32).tiny
    if not (math.isfinite(value) and 0.0 < value < float(np.finfo(np.float32).max) and np.float32(value) >= tiny):
        return False
    with np.errstate(over="ignore", under="ignore"):
        product = np.asarray(scales, np.float32) * np.float32(value)
    return bool(np.all(np.isfinite(product) & (product > 0)))


def _mixture(count: int, seed: int) -> ColourMixture:
    rng = np.random.default_rng(seed)
    components = 4
    coefficients = rng.dirichlet(np.full(components, 0.5), size=count)
    coefficients[rng.random((count, components)) < 0.2] = 0.0  # some components carry nothing
    total = coefficients.sum(axis=-1, keepdims=True)
    coefficients = np.where(total > 0, coefficients / np.where(total > 0, total, 1.0), 1.0 / components)
    location = rng.uniform(-0.2, 1.2, (count, components, 3))
    scale = 10.0 ** rng.uniform(-4, 0, (count, components, 3))
    return ColourMixture(*(jnp.asarray(a, jnp.float32) for a in (coefficients, location, scale)))


def _termination(count: int, seed: int) -> TerminationDistribution:
    rng = np.random.default_rng(seed)
    samples = 6
    weights = rng.uniform(0, 1, (count, samples)) * (rng.random((count, samples)) < 0.7)
    if count:
        weights[0] = 0.0 if rng.random() < 0.3 else weights[0]  # a ray that nothing stops
    widths = rng.uniform(0, 1, (count, samples)) * (rng.random((count, samples)) < 0.8)  # zero widths too
    edges = 2.0 + np.concatenate([np.zeros((count, 1)), np.cumsum(widths, axis=-1)], axis=-1)
    return TerminationDistribution(jnp.asarray(weights, jnp.float32), jnp.asarray(edges, jnp.float32))


def _outcome(call):
    """`("error", message)` for a ValueError, else `("value", result)`; anything else fails."""
    try:
        return "value", call()
    except ValueError as error:
        message = str(error)
        assert message and "\n" not in message.strip(), f"an unclear error: {message!r}"
        return "error", message


# How far from a quantile the distribution function is read on either side: the solvers stop
# within 1e-6 of the root, and a component may be far sharper than that (a scale of 1e-7).
_STEP = 1e-5


def _assert_quantiles(quantiles, levels, cdf):
    """Finite, non-decreasing in the level, and each a quantile: the distribution function
    (where `cdf` is given) at most the level just below it and at least the level just above."""
    quantiles = np.asarray(quantiles, np.float64)
    assert np.all(np.isfinite(quantiles))
    order = np.argsort(np.asarray([_value(x) for x in levels]), kind="stable")
    assert np.all(np.diff(quantiles[order], axis=0) >= -1e-6)
    if cdf is not None:
        for quantile, level in zip(quantiles, levels, strict=True):
            step = _STEP * np.maximum(1.0, np.abs(quantile))
            assert np.all(cdf(quantile - step) <= _value(level) + 1e-4)
            assert np.all(cdf(quantile + step) >= _value(level) - 1e-4)


@SETTINGS
@given(
    count=RAY_COUNTS,
    seed=st.integers(0, 2**16),
    levels=st.lists(SCALARS, min_size=1, max_size=3),
    temperature=SCALARS,
)
@example(count=1, seed=0, levels=[4.511335799909543e-44], temperature=1.0)  # a float32 subnormal
def test_colour_mixture_refuses_exactly_the_bad_inputs_and_keeps_its_invariants(
    count, seed, levels, temperature
):
    mixture = _mixture(count, seed)
    kind, result = _outcome(lambda: mixture.with_temperature(temperature).quantiles(levels))
    valid = _temperature_ok(temperature, mixture.scale) and all(_level_ok(x) for x in levels)
    assert (kind == "value") == valid, (kind, result)
    if kind == "error":
        return
    scaled = mixture.with_temperature(temperature)
    assert result.shape == (len(levels), count, 3)

    def cdf(quantile):
        return np.asarray(scaled.cdf(jnp.asarray(quantile, jnp.float32)), np.float64)

    _assert_quantiles(result, levels, cdf)


@SETTINGS
@given(count=RAY_COUNTS, seed=st.integers(0, 2**16), mass=SCALARS)
def test_colour_intervals_hold_their_mass(count, seed, mass):
    mixture = _mixture(count, seed)
    kind, result = _outcome(lambda: mixture.interval(mass))
    assert (kind == "value") == _mass_ok(mass), (kind, result)
    if kind == "error":
        return
    lower, upper = (np.asarray(x, np.float64) for x in result)
    assert np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower <= upper + 1e-6)

    def cdf(x):
        return np.asarray(mixture.cdf(jnp.asarray(x, jnp.float32)), np.float64)

    # The interval holds its mass: at least with its ends moved out a little, at most with
    # them moved in.
    step = _STEP * np.maximum(1.0, np.maximum(np.abs(lower), np.abs(upper)))
    assert np.all(cdf(upper + step) - cdf(lower - step) >= _value(mass) - 2e-4)
    assert np.all(cdf(upper - step) - cdf(lower + step) <= _value(mass) + 2e-4)


@SETTINGS
@given(
    count=RAY_COUNTS,
    seed=st.integers(0, 2**16),
    levels=st.lists(SCALARS, min_size=1, max_size=3),
    mass=SCALARS,
)
def test_termination_refuses_exactly_the_bad_inputs_and_keeps_its_invariants(count, seed, levels, mass):
    termination = _termination(count, seed)
    kind, result = _outcome(lambda: termination.quantiles(levels))
    assert (kind == "value") == all(_level_ok(x) for x in levels), (kind, result)
    if kind == "value":
        weights = np.asarray(termination.weights, np.float64)
        edges = np.asarray(termination.t_edges, np.float64)
        quantiles = np.asarray(result, np.float64)
        assert quantiles.shape == (len(levels), count)
        _assert_quantiles(quantiles, levels, None)
        assert np.all(quantiles >= edges[:, :1].T - 1e-5) and np.all(quantiles <= edges[:, -1:].T + 1e-5)
        stopped = weights.sum(axis=-1) > 0
        # A ray that nothing stops terminates at its far bound; the others where their
        # distribution function reaches the level: just below the quantile it is at most the
        # level, at it at least (a zero-width interval is a point mass, a jump of the function).
        np.testing.assert_allclose(
            quantiles[:, ~stopped], np.broadcast_to(edges[~stopped, -1], quantiles[:, ~stopped].shape)
        )

        def cdf(t, w, e):
            return float(
                termination_cdf(jnp.float32(t), jnp.asarray(w, jnp.float32), jnp.asarray(e, jnp.float32))
            )

        step = _STEP * np.maximum(1.0, np.abs(edges[:, -1]))
        for quantile, level in zip(quantiles, levels, strict=True):
            for ray in np.flatnonzero(stopped):
                q, w, e = quantile[ray], weights[ray], edges[ray]
                assert cdf(q - step[ray], w, e) <= _value(level) + 1e-4
                assert cdf(q + step[ray], w, e) >= _value(level) - 1e-4
    kind, result = _outcome(lambda: termination.interval(mass))
    assert (kind == "value") == _mass_ok(mass), (kind, result)
    if kind == "value":
        lower, upper = (np.asarray(x) for x in result)
        assert np.all(np.isfinite(lower)) and np.all(lower <= upper)


@pytest.fixture(scope="module")
def tiny_model(tiny_scene):
    from helpers import TINY_OVERRIDES

    config = mx.load_config("builtin", TINY_OVERRIDES)
    return mx.training.init_train_state(config, tiny_scene).model


_BOUNDS = st.one_of(st.floats(0.0, 8.0), st.sampled_from([math.nan, math.inf, -math.inf]))


def _rays(count, near, far):
    directions = jnp.zeros((count, 3)).at[:, 2].set(-1.0).at[:, 0].set(jnp.linspace(-0.2, 0.2, count))
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    return mx.nn.RayBundle(
        origins=jnp.zeros((count, 3)).at[:, 2].set(4.0),
        directions=directions,
        viewdirs=directions,
        radii=jnp.full((count, 1), 0.002),
        near=jnp.full((count, 1), near),
        far=jnp.full((count, 1), far),
    )


@SETTINGS
@given(
    count=RAY_COUNTS,
    near=_BOUNDS,
    far=_BOUNDS,
    temperature=SCALARS,
    masses=st.lists(SCALARS, min_size=1, max_size=2),
)
def test_predictive_summaries_are_refused_or_ordered(tiny_model, count, near, far, temperature, masses):
    rays = _rays(count, near, far)

    def summary():
        return mx.uncertainty.summarise(mx.predictive(tiny_model, rays, temperature=temperature), masses=tuple(masses))

    kind, result = _outcome(summary)
    bounds_ok = count == 0 or (math.isfinite(near) and math.isfinite(far) and near <= far)
    scales = mx.predictive(tiny_model, rays).colour.scale if bounds_ok else np.ones(1)
    # summarise reads the masses as Python floats.
    masses_ok = all(_level_ok(m) and _mass_ok(_value(m)) for m in masses)
    valid = bounds_ok and _temperature_ok(temperature, scales) and masses_ok
    assert (kind == "value") == valid, (kind, result)
    if kind == "error":
        return
    order = np.argsort([_value(m) for m in masses], kind="stable")
    for prefix in ("colour", "depth"):
        median = np.asarray(getattr(result, f"{prefix}_median"), np.float64)
        lower = np.asarray(getattr(result, f"{prefix}_lower"), np.float64)[order]
        upper = np.asarray(getattr(result, f"{prefix}_upper"), np.float64)[order]
        for values in (median, lower, upper, np.asarray(getattr(result, f"{prefix}_mean"))):
            assert np.all(np.isfinite(values)), prefix
        assert np.all(lower <= median + 1e-5) and np.all(median <= upper + 1e-5), prefix
        # Wider masses give nested intervals.
        assert np.all(np.diff(lower, axis=0) <= 1e-5) and np.all(np.diff(upper, axis=0) >= -1e-5), prefix
    depths = np.asarray(result.depth_lower), np.asarray(result.depth_upper), np.asarray(result.depth_median)
    for depth in depths:
        assert np.all(depth >= near - 1e-4) and np.all(depth <= far + 1e-4)
