"""The Laplace mixture NLLs (paper eqs. 4-7, 9) against float64 numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    as_f32,
    as_f64,
    central_difference,
    random_ray,
    ref_blend_weights,
    ref_colour_nll,
    ref_colour_nll_logspace,
    ref_depth_nll,
)

from mixnerf_eqx.nn import LaplaceMixture, blend_weights, log_transmittance

NUM_SAMPLES = 12
FLOOR_NLL = -np.log(1e-12)  # ~= 27.631, where the released loss saturates


def _moderate_ray(seed):
    """A ray whose mixture likelihood is of order one: residuals ~0.1, scales ~0.1-0.5.

    Every array is float32-representable, so the package and the references see the same
    numbers. Residuals keep away from zero so finite differences do not straddle the kink
    of |x|.
    """
    rng = np.random.default_rng(seed)
    t_edges, density, rgb = random_ray(rng, NUM_SAMPLES, max_density=1.0)
    target = rng.uniform(0.2, 0.8, 3)
    residual = rng.uniform(0.02, 0.25, (NUM_SAMPLES, 3)) * rng.choice([-1.0, 1.0], (NUM_SAMPLES, 3))
    rgb = target + residual
    beta = rng.uniform(0.1, 0.5, (NUM_SAMPLES, 3))
    direction_norm = rng.uniform(1.0, 1.4)
    ray_depth = direction_norm + rng.uniform(0.02, 0.3, NUM_SAMPLES) * rng.choice([-1.0, 1.0], NUM_SAMPLES)
    weights = ref_blend_weights(density, t_edges, direction_norm)
    arrays = as_f64(*as_f32(t_edges, density, rgb, beta, target, ray_depth, weights, direction_norm))
    names = ("t_edges", "density", "rgb", "beta", "target", "ray_depth", "weights", "direction_norm")
    return dict(zip(names, arrays, strict=True))


def _j(x):
    return jnp.asarray(as_f32(x))


# --- values -------------------------------------------------------------------------------

MIXTURES_AND_REFERENCES = [
    # (mixture, weight_eps, floor of the reference)
    (LaplaceMixture(), 1e-10, 1e-12),
    (LaplaceMixture(likelihood_floor=None), 1e-10, None),
    (LaplaceMixture(weight_eps=0.0, likelihood_floor=None), 0.0, None),
    (LaplaceMixture(evaluation="linear"), 1e-10, 1e-12),
    (LaplaceMixture(evaluation="linear", weight_eps=0.0, likelihood_floor=None), 0.0, None),
]


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("mixture, weight_eps, floor", MIXTURES_AND_REFERENCES)
def test_colour_nll_matches_reference(seed, mixture, weight_eps, floor):
    ray = _moderate_ray(seed)
    got = float(mixture.colour_nll(_j(ray["weights"]), _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])))
    expected = ref_colour_nll(
        ray["weights"], ray["rgb"], ray["beta"], ray["target"], weight_eps=weight_eps, floor=floor
    )
    # float32 log-sum-exp of ~12 terms of order one: a few ulp of values of order one.
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("depth_scale", ["colour", "single"])
@pytest.mark.parametrize("mixture, weight_eps, floor", MIXTURES_AND_REFERENCES)
def test_depth_nll_matches_reference(seed, depth_scale, mixture, weight_eps, floor):
    ray = _moderate_ray(100 + seed)
    mixture = LaplaceMixture(
        weight_eps=mixture.weight_eps,
        likelihood_floor=mixture.likelihood_floor,
        evaluation=mixture.evaluation,
        depth_scale=depth_scale,
    )
    got = float(
        mixture.depth_nll(
            _j(ray["weights"]), _j(ray["ray_depth"]), _j(ray["beta"]), jnp.float32(ray["direction_norm"])
        )
    )
    expected = ref_depth_nll(
        ray["weights"],
        ray["ray_depth"],
        ray["beta"],
        ray["direction_norm"],
        scale=depth_scale,
        weight_eps=weight_eps,
        floor=floor,
    )
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


def test_depth_scale_options_differ():
    ray = _moderate_ray(7)
    args = (_j(ray["weights"]), _j(ray["ray_depth"]), _j(ray["beta"]), jnp.float32(ray["direction_norm"]))
    colour = float(LaplaceMixture(depth_scale="colour").depth_nll(*args))
    single = float(LaplaceMixture(depth_scale="single").depth_nll(*args))
    assert abs(colour - single) > 0.1


@pytest.mark.parametrize("seed", range(3))
def test_regenerated_colour_nll_matches_reference(seed):
    ray = _moderate_ray(200 + seed)
    regen_weights = blend_weights(_j(ray["density"]), _j(ray["t_edges"]), _j(ray["ray_depth"]))
    got = float(
        LaplaceMixture().colour_nll(regen_weights, _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"]))
    )
    ref_regen = ref_blend_weights(ray["density"], ray["t_edges"], ray["ray_depth"])
    expected = ref_colour_nll(
        ref_regen, ray["rgb"], ray["beta"], ray["target"], weight_eps=1e-10, floor=1e-12
    )
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


# --- log against linear evaluation --------------------------------------------------------


def _badly_fitted_ray():
    """Every component sits one unit from the target with scale 1e-3: a likelihood of
    about exp(-2981), below even float64's range."""
    ray = _moderate_ray(300)
    rgb = as_f64(as_f32(ray["target"] - 1.0)) * np.ones((NUM_SAMPLES, 1))
    beta = np.full((NUM_SAMPLES, 3), as_f64(as_f32(1e-3)))
    return ray["weights"], rgb, beta, ray["target"]


def test_linear_evaluation_saturates_at_the_floor():
    weights, rgb, beta, target = _badly_fitted_ray()
    got = float(LaplaceMixture(evaluation="linear").colour_nll(_j(weights), _j(rgb), _j(beta), _j(target)))
    np.testing.assert_allclose(got, FLOOR_NLL, rtol=1e-6)


def test_log_evaluation_without_floor_is_exact_for_a_badly_fitted_ray():
    weights, rgb, beta, target = _badly_fitted_ray()
    got = float(LaplaceMixture(likelihood_floor=None).colour_nll(_j(weights), _j(rgb), _j(beta), _j(target)))
    expected = ref_colour_nll_logspace(weights, rgb, beta, target, weight_eps=1e-10)
    assert expected > 2900
    np.testing.assert_allclose(got, expected, rtol=1e-4)


def test_log_evaluation_with_floor_saturates_with_finite_gradients():
    weights, rgb, beta, target = _badly_fitted_ray()
    mixture = LaplaceMixture()
    value, grads = jax.value_and_grad(mixture.colour_nll, argnums=(0, 1, 2))(
        _j(weights), _j(rgb), _j(beta), _j(target)
    )
    np.testing.assert_allclose(float(value), FLOOR_NLL, rtol=1e-6)
    for grad in grads:
        assert np.all(np.isfinite(np.asarray(grad)))


# --- mixing coefficients and empty rays ---------------------------------------------------


@pytest.mark.parametrize("weight_eps", [1e-10, 0.0])
def test_mixing_coefficients_are_normalised_weights(weight_eps):
    ray = _moderate_ray(400)
    log_pi = LaplaceMixture(weight_eps=weight_eps).log_mixing_coefficients(_j(ray["weights"]))
    pi = np.exp(np.asarray(log_pi, np.float64))
    np.testing.assert_allclose(pi.sum(), 1.0, rtol=1e-5)
    np.testing.assert_allclose(pi, ray["weights"] / ray["weights"].sum(), rtol=1e-5)


EMPTY_RAY_MIXTURES = [
    LaplaceMixture(),
    LaplaceMixture(likelihood_floor=None),
    LaplaceMixture(weight_eps=0.0),
    LaplaceMixture(weight_eps=0.0, likelihood_floor=None),
    LaplaceMixture(evaluation="linear"),
]


@pytest.mark.parametrize("mixture", EMPTY_RAY_MIXTURES)
def test_empty_ray_gives_finite_nll_and_gradients(mixture):
    ray = _moderate_ray(500)
    weights = jnp.zeros(NUM_SAMPLES, jnp.float32)
    value, grads = jax.value_and_grad(mixture.colour_nll, argnums=(0, 1, 2))(
        weights, _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])
    )
    assert np.isfinite(float(value))
    for grad in grads:
        assert np.all(np.isfinite(np.asarray(grad)))
    depth_value, depth_grads = jax.value_and_grad(mixture.depth_nll, argnums=(0, 1, 2))(
        weights, _j(ray["ray_depth"]), _j(ray["beta"]), jnp.float32(ray["direction_norm"])
    )
    assert np.isfinite(float(depth_value))
    for grad in depth_grads:
        assert np.all(np.isfinite(np.asarray(grad)))


def test_empty_ray_contributes_only_the_floor_by_default():
    ray = _moderate_ray(501)
    weights = jnp.zeros(NUM_SAMPLES, jnp.float32)
    got = float(LaplaceMixture().colour_nll(weights, _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])))
    np.testing.assert_allclose(got, FLOOR_NLL, rtol=1e-6)


# --- gradients ----------------------------------------------------------------------------


def _assert_grad_close(got, expected):
    # float32 reverse mode against float64 central differences (truncation ~1e-12 here).
    got, expected = np.asarray(got, np.float64), as_f64(expected)
    scale = np.max(np.abs(expected))
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("mixture, weight_eps, floor", MIXTURES_AND_REFERENCES[:3])
def test_colour_nll_gradients_match_finite_differences(seed, mixture, weight_eps, floor):
    ray = _moderate_ray(600 + seed)
    weights, rgb, beta, target = ray["weights"], ray["rgb"], ray["beta"], ray["target"]
    grads = jax.grad(mixture.colour_nll, argnums=(0, 1, 2))(_j(weights), _j(rgb), _j(beta), _j(target))
    options = dict(weight_eps=weight_eps, floor=floor)
    expected = (
        central_difference(lambda w: ref_colour_nll(w, rgb, beta, target, **options), weights),
        central_difference(lambda c: ref_colour_nll(weights, c, beta, target, **options), rgb),
        central_difference(lambda b: ref_colour_nll(weights, rgb, b, target, **options), beta),
    )
    for got, reference in zip(grads, expected, strict=True):
        _assert_grad_close(got, reference)


@pytest.mark.parametrize("depth_scale", ["colour", "single"])
def test_depth_nll_gradients_match_finite_differences(depth_scale):
    ray = _moderate_ray(700)
    weights, ray_depth, beta, target = ray["weights"], ray["ray_depth"], ray["beta"], ray["direction_norm"]
    mixture = LaplaceMixture(depth_scale=depth_scale)
    grads = jax.grad(mixture.depth_nll, argnums=(0, 1, 2))(
        _j(weights), _j(ray_depth), _j(beta), jnp.float32(target)
    )
    options = dict(scale=depth_scale, weight_eps=1e-10, floor=1e-12)
    expected = (
        central_difference(lambda w: ref_depth_nll(w, ray_depth, beta, target, **options), weights),
        central_difference(lambda d: ref_depth_nll(weights, d, beta, target, **options), ray_depth),
        central_difference(lambda b: ref_depth_nll(weights, ray_depth, b, target, **options), beta),
    )
    for got, reference in zip(grads, expected, strict=True):
        _assert_grad_close(got, reference)


def test_regenerated_nll_gradients_reach_density_and_ray_depth():
    ray = _moderate_ray(800)
    density, t_edges, ray_depth = ray["density"], ray["t_edges"], ray["ray_depth"]
    rgb, beta, target = ray["rgb"], ray["beta"], ray["target"]
    mixture = LaplaceMixture()

    def regen_nll(density, ray_depth):
        weights = blend_weights(density, _j(t_edges), ray_depth)
        return mixture.colour_nll(weights, _j(rgb), _j(beta), _j(target))

    def ref_regen_nll(density, ray_depth):
        weights = ref_blend_weights(density, t_edges, ray_depth)
        return ref_colour_nll(weights, rgb, beta, target, weight_eps=1e-10, floor=1e-12)

    grads = jax.grad(regen_nll, argnums=(0, 1))(_j(density), _j(ray_depth))
    expected = (
        central_difference(lambda s: ref_regen_nll(s, ray_depth), density),
        central_difference(lambda d: ref_regen_nll(density, d), ray_depth),
    )
    for got, reference in zip(grads, expected, strict=True):
        assert np.max(np.abs(reference)) > 1e-3  # the regenerated loss does train both
        _assert_grad_close(got, reference)


@pytest.mark.parametrize("mixture", [LaplaceMixture(), LaplaceMixture(likelihood_floor=None)])
def test_zero_weight_components_do_not_contribute(mixture):
    weights = as_f64(as_f32([0.5, 0.0, 0.3]))
    target = as_f64(as_f32([0.5, 0.5, 0.5]))
    rgb = as_f64(as_f32([[0.6, 0.4, 0.55], [0.5, 0.5, 0.5], [0.3, 0.6, 0.5]]))
    # pi_1 = 0, so component 1 must not matter however sharp it is; in float32 the linear
    # evaluation still represents this likelihood exactly (exp(3 * 28.9) < float32 max).
    beta = as_f64(as_f32([[0.2] * 3, [1e-13] * 3, [0.3] * 3]))
    got = float(mixture.colour_nll(_j(weights), _j(rgb), _j(beta), _j(target)))
    linear = float(LaplaceMixture(evaluation="linear").colour_nll(_j(weights), _j(rgb), _j(beta), _j(target)))
    expected = ref_colour_nll(weights, rgb, beta, target, weight_eps=1e-10, floor=mixture.likelihood_floor)
    np.testing.assert_allclose(linear, expected, rtol=1e-5)
    np.testing.assert_allclose(got, expected, rtol=1e-5)


# --- the background component (`background`, an option; off in the paper's configs) -------


def _ref_background_nll(weights, rgb, beta, target, background, scale, floor, transmittance=None):
    """`-log(sum_j w_j prod_c Laplace(c; rgb_jc, beta_jc) + T prod_c Laplace(c; background_c,
    scale) [+ floor])`, linear float64: unnormalised weights; `T = 1 - sum_j w_j` unless given."""
    weights, rgb, beta, target = as_f64(weights, rgb, beta, target)
    samples = np.prod(np.exp(-np.abs(target - rgb) / beta) / (2 * beta), axis=-1)
    background = np.prod(np.exp(-np.abs(target - np.asarray(background)) / scale) / (2 * scale))
    transmittance = 1.0 - weights.sum() if transmittance is None else transmittance
    return -np.log(np.sum(weights * samples) + transmittance * background + (floor or 0.0))


BACKGROUND_MIXTURES = [
    # (mixture, floor of the reference)
    (LaplaceMixture(background=(1.0, 1.0, 1.0), background_scale=0.2), 1e-12),
    (LaplaceMixture(background=(1.0, 1.0, 1.0), background_scale=0.2, likelihood_floor=None), None),
    (LaplaceMixture(background=(0.9, 0.5, 1.0), background_scale=0.5, evaluation="linear"), 1e-12),
]


def _partly_transparent_ray(seed):
    """A moderate ray whose weights sum to about one half, with a target near the background
    colour, so that both the samples and the background carry the likelihood."""
    ray = _moderate_ray(seed)
    ray["weights"] = as_f64(as_f32(ray["weights"] * 0.5 / ray["weights"].sum()))
    ray["target"] = as_f64(as_f32(np.clip(ray["target"] + 0.3, 0.0, 1.0)))
    return ray


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("mixture, floor", BACKGROUND_MIXTURES)
def test_background_component_matches_reference(seed, mixture, floor):
    ray = _partly_transparent_ray(700 + seed)
    got = float(mixture.colour_nll(_j(ray["weights"]), _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])))
    expected = _ref_background_nll(
        ray["weights"],
        ray["rgb"],
        ray["beta"],
        ray["target"],
        mixture.background,
        mixture.background_scale,
        floor,
    )
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    # Not the normalised mixture: the transmittance carries half the mass here.
    normalised = ref_colour_nll(ray["weights"], ray["rgb"], ray["beta"], ray["target"], floor=floor)
    assert abs(got - normalised) > 1e-2


@pytest.mark.parametrize("seed", range(2))
def test_background_component_gradients_match_finite_differences(seed):
    mixture, floor = BACKGROUND_MIXTURES[0]
    ray = _partly_transparent_ray(720 + seed)
    weights, rgb, beta, target = ray["weights"], ray["rgb"], ray["beta"], ray["target"]
    grads = jax.grad(mixture.colour_nll, argnums=(0, 1, 2))(_j(weights), _j(rgb), _j(beta), _j(target))
    options = dict(background=mixture.background, scale=mixture.background_scale, floor=floor)
    expected = (
        central_difference(lambda w: _ref_background_nll(w, rgb, beta, target, **options), weights),
        central_difference(lambda c: _ref_background_nll(weights, c, beta, target, **options), rgb),
        central_difference(lambda b: _ref_background_nll(weights, rgb, b, target, **options), beta),
    )
    for got, reference in zip(grads, expected, strict=True):
        _assert_grad_close(got, reference)


def test_transparent_ray_is_the_background_density_exactly():
    """All weights zero: the NLL is the background component's alone, in closed form."""
    ray = _moderate_ray(740)
    mixture = LaplaceMixture(background=(1.0, 1.0, 1.0), background_scale=0.05, likelihood_floor=None)
    weights = jnp.zeros(NUM_SAMPLES, jnp.float32)
    value, grads = jax.value_and_grad(mixture.colour_nll, argnums=(0, 1, 2))(
        weights, _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])
    )
    target = as_f64(as_f32(ray["target"]))
    expected = np.sum(np.log(2 * 0.05) + (1.0 - target) / 0.05)
    np.testing.assert_allclose(float(value), expected, rtol=1e-6)
    for grad in grads:
        assert np.all(np.isfinite(np.asarray(grad)))


def test_opaque_ray_has_no_background_mass_and_finite_gradients():
    """Weights that sum to one (or just above, by rounding) leave nothing to the background:
    the NLL is the normalised mixture's, and no gradient is NaN."""
    ray = _moderate_ray(741)
    weights = as_f64(as_f32(ray["weights"] / ray["weights"].sum() * (1 + 2e-7)))
    mixture = LaplaceMixture(background=(1.0, 1.0, 1.0), weight_eps=0.0)
    value, grads = jax.value_and_grad(mixture.colour_nll, argnums=(0, 1, 2))(
        _j(weights), _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])
    )
    plain = LaplaceMixture(weight_eps=0.0).colour_nll(
        _j(weights), _j(ray["rgb"]), _j(ray["beta"]), _j(ray["target"])
    )
    np.testing.assert_allclose(float(value), float(plain), rtol=1e-5, atol=1e-5)
    for grad in grads:
        assert np.all(np.isfinite(np.asarray(grad)))


def test_background_leaves_the_depth_mixture_normalised():
    ray = _partly_transparent_ray(742)
    args = (_j(ray["weights"]), _j(ray["ray_depth"]), _j(ray["beta"]), jnp.float32(ray["direction_norm"]))
    with_background = LaplaceMixture(background=(1.0, 1.0, 1.0)).depth_nll(*args)
    np.testing.assert_array_equal(np.asarray(with_background), np.asarray(LaplaceMixture().depth_nll(*args)))


@pytest.mark.parametrize("bad", [dict(background=(1.0, 1.0)), dict(background_scale=0.0)])
def test_background_options_are_checked(bad):
    # The runtime type check (in tests) or the module's own check, whichever sees it first.
    with pytest.raises((ValueError, TypeError)):
        LaplaceMixture(**bad)


@pytest.mark.parametrize("evaluation", ["log", "linear"])
@pytest.mark.parametrize("optical_depth", [5.0, 20.0, 30.0])
def test_an_opaque_floater_keeps_its_push_toward_transparency(evaluation, optical_depth):
    """A red floater of optical depth 5 to 30 in front of a white target, from its densities
    through `blend_weights` and `log_transmittance` (as the losses call them): the NLL and its
    gradient in the densities against float64 with `T = exp(-sum sigma delta)`. Formed as
    `1 - sum w`, `T` is rounding noise in float32 beyond an optical depth of about 16, the
    NLL sits at the floor and the density gets no gradient at all."""
    num = NUM_SAMPLES
    t_edges = as_f64(as_f32(np.linspace(2.0, 6.0, num + 1)))
    density = as_f64(as_f32(np.full(num, optical_depth / 4.0)))
    rgb = np.tile([0.9, 0.1, 0.1], (num, 1))
    beta = np.full((num, 3), 0.05)
    target = np.ones(3)
    mixture = LaplaceMixture(background=(1.0, 1.0, 1.0), background_scale=0.05, evaluation=evaluation)

    def ours(density):
        weights = blend_weights(density, _j(t_edges), jnp.float32(1.0))
        log_t = log_transmittance(density, _j(t_edges), jnp.float32(1.0))
        return mixture.colour_nll(weights, _j(rgb), _j(beta), _j(target), log_t)

    def reference(density):
        weights = ref_blend_weights(density, t_edges, 1.0)
        transmittance = np.exp(-np.sum(density * np.diff(t_edges)))
        return _ref_background_nll(weights, rgb, beta, target, (1.0, 1.0, 1.0), 0.05, 1e-12, transmittance)

    value, grad = jax.value_and_grad(ours)(_j(density))
    np.testing.assert_allclose(float(value), reference(density), rtol=1e-5)
    expected = central_difference(reference, density, step=1e-5)
    np.testing.assert_allclose(np.asarray(grad), expected, rtol=1e-3, atol=1e-4 * np.abs(expected).max())
    assert np.asarray(grad).sum() > 0  # more density, more NLL: the floater is pushed away
