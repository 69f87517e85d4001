"""The predictive distribution: quantiles, intervals, modes, moments, depth, calibration measures.

References: a float64 numpy bisection of the mixture's distribution function, Monte-Carlo
samples drawn from the mixture in numpy, a dense grid search (and the exhaustive search over
the grid of component coordinates) for the mode, and the piecewise-linear inverse of the
termination distance's distribution function.
"""

import dataclasses
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._predictive.distribution import mixing_coefficients
from mixnerf_eqx.data import rays_for_views

MASSES = (0.5, 0.8, 0.9, 0.95)


# ----------------------------------------------------------------------------- references


def random_mixtures(rng, num_rays, num_components, *, low=0.01, high=0.5, concentration=1.0):
    coefficients = rng.dirichlet(np.full(num_components, concentration), size=num_rays)
    location = rng.uniform(0.0, 1.0, (num_rays, num_components, 3))
    scale = np.exp(rng.uniform(np.log(low), np.log(high), (num_rays, num_components, 3)))
    return coefficients, location, scale


def as_mixture(coefficients, location, scale):
    return mx.uncertainty.ColourMixture(
        jnp.asarray(coefficients, jnp.float32),
        jnp.asarray(location, jnp.float32),
        jnp.asarray(scale, jnp.float32),
    )


def np_channel_cdf(x, coefficients, location, scale):
    """Float64 mixture CDF of one channel at the points `x` (any shape)."""
    z = (np.asarray(x, np.float64)[..., None] - location) / scale
    component = np.where(z < 0, 0.5 * np.exp(np.minimum(z, 0)), 1 - 0.5 * np.exp(-np.maximum(z, 0)))
    return np.sum(coefficients * component, axis=-1)


def np_quantile(level, coefficients, location, scale):
    """Float64 bisection on [-1e3, 1e3], 200 halvings."""
    lower, upper = -1e3, 1e3
    for _ in range(200):
        middle = 0.5 * (lower + upper)
        if np_channel_cdf(middle, coefficients, location, scale) < level:
            lower = middle
        else:
            upper = middle
    return 0.5 * (lower + upper)


def np_log_density(points, coefficients, location, scale):
    """Float64 joint log density at `points` (..., 3)."""
    points = np.asarray(points, np.float64)[..., None, :]
    component = np.sum(-np.abs(points - location) / scale - np.log(2 * scale), axis=-1)
    with np.errstate(divide="ignore"):
        return np.logaddexp.reduce(np.log(coefficients) + component, axis=-1)


def draw(rng, coefficients, location, scale, count):
    """`count` draws from each ray's mixture: (num_rays, count, 3)."""
    num_rays, num_components = coefficients.shape
    picks = np.stack([rng.choice(num_components, size=count, p=p) for p in coefficients])
    rows = np.arange(num_rays)[:, None]
    return rng.laplace(location[rows, picks], scale[rows, picks])


# ----------------------------------------------------------------------------- colour


def test_quantiles_match_a_float64_bisection_and_monte_carlo():
    rng = np.random.default_rng(0)
    coefficients, location, scale = random_mixtures(rng, 6, 8)
    # The references see the float32 values the package sees.
    coefficients, location, scale = (np.float64(np.float32(x)) for x in (coefficients, location, scale))
    mixture = as_mixture(coefficients, location, scale)
    samples = draw(rng, coefficients, location, scale, 40_000)
    levels = (0.025, 0.1, 0.5, 0.9, 0.975)
    single = np.asarray(jax.jit(lambda m: m.quantile(0.1))(mixture))
    batched = np.asarray(jax.jit(lambda m: m.quantiles(levels))(mixture))
    assert single.shape == (6, 3) and batched.shape == (len(levels), 6, 3)
    np.testing.assert_array_equal(batched[1], single)
    for level, got in zip(levels, batched, strict=True):
        for ray, channel in itertools.product(range(6), range(3)):
            args = coefficients[ray], location[ray, :, channel], scale[ray, :, channel]
            reference = np_quantile(level, *args)
            assert abs(got[ray, channel] - reference) < 1e-4
            # The mass below the answer, in float64, is the level to float32 rounding: of the
            # distribution function's sum, and of the answer (a few spacings times the density).
            density = np.sum(args[0] * np.exp(-np.abs(got[ray, channel] - args[1]) / args[2]) / (2 * args[2]))
            rounding = 1e-6 + 4 * density * np.spacing(got[ray, channel])
            assert abs(np_channel_cdf(got[ray, channel], *args) - level) < rounding
            # Monte Carlo: the fraction of draws below the answer, within 5 binomial sigmas.
            below = np.mean(samples[ray, :, channel] <= got[ray, channel])
            assert abs(below - level) < 5 * np.sqrt(level * (1 - level) / samples.shape[1])


def test_central_intervals_hold_their_mass_and_nest():
    rng = np.random.default_rng(1)
    coefficients, location, scale = random_mixtures(rng, 5, 6)
    mixture = as_mixture(coefficients, location, scale)
    intervals = jax.jit(lambda m: [m.interval(mass) for mass in MASSES])(mixture)
    previous = None
    for mass, (lower, upper) in zip(MASSES, intervals, strict=True):
        lower, upper = np.asarray(lower), np.asarray(upper)
        for ray, channel in itertools.product(range(5), range(3)):
            args = coefficients[ray], location[ray, :, channel], scale[ray, :, channel]
            held = np_channel_cdf(upper[ray, channel], *args) - np_channel_cdf(lower[ray, channel], *args)
            assert abs(held - mass) < 4e-6
        if previous is not None:
            assert np.all(lower <= previous[0]) and np.all(upper >= previous[1])
        previous = (lower, upper)
    with pytest.raises(ValueError, match="in \\(0, 1\\)"):
        mixture.interval(1.0)


def test_mean_and_standard_deviation_match_closed_forms_and_samples():
    rng = np.random.default_rng(2)
    coefficients, location, scale = random_mixtures(rng, 4, 5)
    mixture = as_mixture(coefficients, location, scale)
    mean = np.sum(coefficients[..., None] * location, axis=1)
    variance = np.sum(coefficients[..., None] * (2 * scale**2 + location**2), axis=1) - mean**2
    np.testing.assert_allclose(np.asarray(mixture.mean()), mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(mixture.std()), np.sqrt(variance), rtol=1e-5)
    samples = draw(rng, coefficients, location, scale, 200_000)
    np.testing.assert_allclose(np.asarray(mixture.std()), samples.std(axis=1), rtol=0.02)


def test_modes_match_a_dense_grid_search_and_the_exhaustive_vertex_search():
    rng = np.random.default_rng(3)
    # Scales from sharp to broad, per channel: modes off every component's location occur.
    coefficients, location, scale = random_mixtures(rng, 40, 4, low=0.005, high=2.0, concentration=2.0)
    # And one made so: two components, each sharp in the channel where the other is broad,
    # whose densities add up most at (0.2, 0.2, 0.5), where neither sits.
    coefficients[0] = [0.4995, 0.4995, 0.0005, 0.0005]
    location[0] = [[0.2, 0.5, 0.5], [0.5, 0.2, 0.5], [0.9, 0.9, 0.9], [0.1, 0.9, 0.1]]
    scale[0] = [[0.01, 1.0, 0.05], [1.0, 0.01, 0.05], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]]
    modes = np.asarray(jax.jit(lambda m: m.mode())(as_mixture(coefficients, location, scale)))
    axis = np.linspace(-0.2, 1.2, 43)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    off_component = 0
    for ray in range(40):
        args = coefficients[ray], location[ray], scale[ray]
        found = np_log_density(modes[ray], *args)
        dense = np_log_density(grid, *args).max()
        vertices = np.array(list(itertools.product(*location[ray].T)))
        exhaustive = np_log_density(vertices, *args).max()
        assert found >= dense - 1e-4
        assert found >= exhaustive - 1e-4
        off_component += np_log_density(location[ray], *args).max() < exhaustive - 1e-3
    np.testing.assert_allclose(modes[0], [0.2, 0.2, 0.5], atol=1e-6)
    # The search is tested where starting at the best component is not enough.
    assert off_component >= 1


def test_log_prob_and_entropy():
    rng = np.random.default_rng(4)
    coefficients, location, scale = random_mixtures(rng, 4, 5)
    mixture = as_mixture(coefficients, location, scale)
    points = rng.uniform(0, 1, (4, 3))
    expected = [np_log_density(points[i], coefficients[i], location[i], scale[i]) for i in range(4)]
    np.testing.assert_allclose(
        np.asarray(mixture.log_prob(jnp.asarray(points, jnp.float32))), expected, rtol=1e-5
    )
    entropy = -np.sum(coefficients * np.log(coefficients), axis=-1)
    np.testing.assert_allclose(np.asarray(mixture.coefficient_entropy()), entropy, rtol=1e-5)


def test_quantile_gradient_is_the_implicit_function_derivative():
    rng = np.random.default_rng(5)
    coefficients, location, scale = random_mixtures(rng, 1, 4)
    coefficients, location, scale = coefficients[0], location[0, :, 0], scale[0, :, 0]
    level = 0.3
    gradient = jax.jit(
        jax.grad(
            lambda loc: mx.uncertainty.ColourMixture(
                jnp.asarray(coefficients, jnp.float32)[None],
                jnp.broadcast_to(loc[None, :, None], (1, 4, 3)),
                jnp.broadcast_to(jnp.asarray(scale, jnp.float32)[None, :, None], (1, 4, 3)),
            ).quantile(level)[0, 0]
        )
    )(jnp.asarray(location, jnp.float32))
    # F(q(mu), mu) = level: dq/dmu_j = pi_j f_j(q) / p(q), with f_j the component density.
    q = np_quantile(level, coefficients, location, scale)
    density = coefficients * np.exp(-np.abs(q - location) / scale) / (2 * scale)
    np.testing.assert_allclose(np.asarray(gradient), density / density.sum(), rtol=1e-3, atol=1e-6)


@jax.jit
def summaries(mixture):
    lower, upper = mixture.interval(0.9)
    return {
        "mean": mixture.mean(),
        "std": mixture.std(),
        "median": mixture.median(),
        "q95": mixture.quantile(0.95),
        "lower": lower,
        "upper": upper,
        "mode": mixture.mode(),
        "entropy": mixture.coefficient_entropy(),
        "log_prob": mixture.log_prob(jnp.full((1, 3), 0.5)),
    }


def test_degenerate_rays_give_finite_documented_answers():
    location = np.tile(np.linspace(0.1, 0.9, 4)[:, None], (1, 3))
    one_hot = np.array([0.0, 1.0, 0.0, 0.0])
    cases = {
        "one component": (one_hot, np.full((4, 3), 0.1)),
        "no weight": (np.zeros(4), np.full((4, 3), 0.1)),
        "tiny beta": (np.full(4, 0.25), np.full((4, 3), 1e-30)),
        "huge beta": (np.full(4, 0.25), np.full((4, 3), 1e30)),
    }
    for name, (weights, scale) in cases.items():
        coefficients = np.asarray(mixing_coefficients(jnp.asarray(weights, jnp.float32)))
        mixture = as_mixture(coefficients[None], location[None], scale[None])
        values = summaries(mixture)
        assert all(np.all(np.isfinite(np.asarray(v))) for v in values.values()), name
        median = values["median"][0]
        if name == "one component":
            # A single Laplace density: its own median and quantiles.
            np.testing.assert_allclose(median, 0.3666667, rtol=1e-5)
            upper = values["q95"][0]
            np.testing.assert_allclose(upper, 0.3666667 - 0.1 * np.log(0.1), rtol=1e-5)
        if name == "no weight":
            # Uniform coefficients: the components' average.
            np.testing.assert_allclose(values["mean"][0], 0.5, rtol=1e-6)
        if name == "tiny beta":
            # Point masses: quantiles fall on component locations.
            assert np.min(np.abs(median[0] - location[:, 0])) < 1e-6
        if name == "huge beta":
            np.testing.assert_allclose(values["std"][0], np.sqrt(2) * 1e30, rtol=1e-4)
            np.testing.assert_allclose(values["q95"][0], -1e30 * np.log(0.1), rtol=1e-4)


# ----------------------------------------------------------------------------- depth


def test_termination_distance_matches_the_piecewise_linear_inverse():
    rng = np.random.default_rng(6)
    edges = np.sort(rng.uniform(2.0, 6.0, (5, 17)), axis=-1)
    weights = rng.uniform(0, 1, (5, 16)) * (rng.uniform(0, 1, (5, 16)) < 0.6)
    depth = mx.uncertainty.TerminationDistribution(jnp.asarray(weights, jnp.float32), jnp.asarray(edges, jnp.float32))
    levels = (0.05, 0.1, 0.5, 0.9, 0.95)
    batched, single = jax.jit(lambda d: (d.quantiles(levels), [d.quantile(level) for level in (0.1, 0.95)]))(
        depth
    )
    # The batched solve (all levels at once) agrees with `depth_quantile`.
    np.testing.assert_allclose(np.asarray(batched)[[1, 4]], np.asarray(single), atol=2e-6)
    quantiles = dict(zip(levels, np.asarray(batched), strict=True))
    masses = weights / weights.sum(-1, keepdims=True)
    cumulative = np.concatenate([np.zeros((5, 1)), np.cumsum(masses, -1)], -1)
    for level in (0.05, 0.5, 0.95):
        got = np.asarray(quantiles[level])
        for ray in range(5):
            # The exact inverse, to float32's rounding of the cumulative sum (a steep interval
            # makes a mass check in float32 meaningless, so the check is on the depth).
            assert abs(got[ray] - np.interp(level, cumulative[ray], edges[ray])) < 1e-5
    centres = 0.5 * (edges[:, 1:] + edges[:, :-1])
    widths = edges[:, 1:] - edges[:, :-1]
    mean = np.sum(masses * centres, -1)
    variance = np.sum(masses * (centres**2 + widths**2 / 12), -1) - mean**2
    np.testing.assert_allclose(np.asarray(depth.mean()), mean, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(depth.std()), np.sqrt(variance), rtol=1e-4)
    lower, upper = np.asarray(quantiles[0.1]), np.asarray(quantiles[0.9])
    for ray in range(5):
        assert abs(lower[ray] - np.interp(0.1, cumulative[ray], edges[ray])) < 1e-5
        assert abs(upper[ray] - np.interp(0.9, cumulative[ray], edges[ray])) < 1e-5
    # A ray with no weight puts everything at its far bound.
    empty = mx.uncertainty.TerminationDistribution(jnp.zeros((1, 16)), jnp.asarray(edges[:1], jnp.float32))
    for value in (empty.mean(), empty.median(), *empty.interval(0.9)):
        np.testing.assert_allclose(np.asarray(value), edges[0, -1], rtol=1e-6)
    assert float(empty.std()[0]) == 0.0


# ----------------------------------------------------------------------------- calibration


def test_coverage_is_nominal_when_the_truth_is_drawn_from_the_mixture():
    rng = np.random.default_rng(7)
    num_rays = 4000
    coefficients, location, scale = random_mixtures(rng, num_rays, 6)
    truth = draw(rng, coefficients, location, scale, 1)[:, 0]
    mixture = as_mixture(coefficients, location, scale)
    levels = [0.5 * (1 - mass) for mass in MASSES] + [0.5 * (1 + mass) for mass in MASSES]
    bounds, narrow_bounds = (
        np.asarray(x)
        for x in jax.jit(lambda m: (m.quantiles(levels), m.with_temperature(0.5).quantiles(levels)))(mixture)
    )
    for index, mass in enumerate(MASSES):
        nominal = bounds[index], bounds[index + len(MASSES)]
        narrow = narrow_bounds[index], narrow_bounds[index + len(MASSES)]
        coverage = mx.uncertainty.interval_coverage(*nominal, truth)
        assert coverage.shape == (3,)
        tolerance = 4.5 * np.sqrt(mass * (1 - mass) / num_rays)
        assert np.all(np.abs(coverage - mass) < tolerance)
        # Scales halved are caught by the same tolerance: the coverage check can fail.
        assert np.all(mx.uncertainty.interval_coverage(*narrow, truth) < mass - tolerance)


def test_fit_temperature_recovers_a_known_scale_factor():
    rng = np.random.default_rng(8)
    coefficients, location, scale = random_mixtures(rng, 3000, 4)
    truth = draw(rng, coefficients, location, 2.0 * scale, 1)[:, 0]
    fitted = mx.uncertainty.fit_temperature(as_mixture(coefficients, location, scale), jnp.asarray(truth, jnp.float32))
    assert abs(fitted - 2.0) < 0.1


def test_sparsification_against_a_direct_loop():
    rng = np.random.default_rng(9)
    error = rng.exponential(1.0, 500)
    spread = error + rng.normal(0, 0.5, 500)
    result = mx.uncertainty.sparsification(spread, error, num_fractions=10)
    for index, fraction in enumerate(result.fractions):
        kept = int(round(500 * (1 - fraction)))
        by_spread = error[np.argsort(-spread, kind="stable")][500 - kept :].mean() / error.mean()
        oracle = np.sort(error)[:kept].mean() / error.mean()
        assert abs(result.by_spread[index] - by_spread) < 1e-12
        assert abs(result.oracle[index] - oracle) < 1e-12
    assert 0 < result.ause < result.random_area
    assert mx.uncertainty.sparsification(error, error).ause == 0.0


# ----------------------------------------------------------------------------- on a model


def test_predictive_pass_of_a_model_compiles_once(tiny_config, tiny_scene, monkeypatch):
    from mixnerf_eqx._nn.model import build_model
    from mixnerf_eqx._predictive import uncertainty as _uncertainty

    model = build_model(tiny_config, key=jax.random.key(0))
    view = tiny_scene.test.select([0])
    rays = rays_for_views(view, tiny_scene.near, tiny_scene.far)
    # The pass must not retrace per call, per temperature or per view.
    once = eqx.filter_jit(eqx.debug.assert_max_traces(_uncertainty._summarise_rays, max_traces=1))
    monkeypatch.setattr(_uncertainty, "_summarise_chunk", once)
    chunk = rays.batch_shape[0] * rays.batch_shape[1] * rays.batch_shape[2]
    maps = mx.uncertainty.predict_rays(model, rays, chunk, targets=view.images)
    wider = mx.uncertainty.predict_rays(model, rays, chunk, temperature=2.0, targets=view.images)
    other = tiny_scene.test.select([1])
    mx.uncertainty.predict_rays(
        model, rays_for_views(other, tiny_scene.near, tiny_scene.far), chunk, targets=other.images
    )
    assert maps["colour_lower"].shape == (len(MASSES), *rays.batch_shape, 3)
    assert np.all(wider["colour_std"] > maps["colour_std"])

    # The colour mixture is the coarse level's components with normalised weights; the
    # termination distance's mean is the rendered depth.
    render = eqx.filter_jit(lambda m, r: m(r))(model, rays)
    weights = np.asarray(render.coarse.weights, np.float64)
    expected = np.sum(
        (weights / weights.sum(-1, keepdims=True))[..., None] * np.asarray(render.coarse.field.rgb), axis=-2
    )
    np.testing.assert_allclose(maps["colour_mean"], expected, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(maps["depth_mean"], np.asarray(render.fine.depth), rtol=1e-5)
    np.testing.assert_allclose(maps["rgb"], np.asarray(render.fine.rgb), rtol=1e-5, atol=1e-6)
    assert np.all(maps["colour_lower"][-1] <= maps["colour_median"])
    assert np.all(maps["colour_median"] <= maps["colour_upper"][-1])
    report = mx.uncertainty.calibration_report(maps, view.images, view.depths)
    assert set(report["coverage"]) == {"0.5", "0.8", "0.9", "0.95"}
    assert np.isfinite(report["nll"]) and np.isfinite(report["depth_ause"])

    baseline = build_model(dataclasses.replace(tiny_config, method="mipnerf"), key=jax.random.key(0))
    with pytest.raises(ValueError, match="no mixture heads"):
        mx.predictive(baseline, rays)


def test_background_component_joins_the_predictive_mixture(tiny_config, tiny_scene):
    """A model trained with a background component (`loss.background_component`) predicts the
    mixture its colour NLL scored: the samples' unnormalised weights and the transmittance on
    the background's Laplace density. Reference: float64 numpy from the render's own weights,
    densities and edges; and the loss's own NLL of the same pixels."""
    from mixnerf_eqx._nn.model import build_model

    loss = dataclasses.replace(tiny_config.loss, background_component=True, background_scale=0.02)
    config = dataclasses.replace(tiny_config, loss=loss)
    model = build_model(config, key=jax.random.key(3), white_background=True)
    assert model.mixture.background == (1.0, 1.0, 1.0)
    view = tiny_scene.test.select([0])
    rays = rays_for_views(view, tiny_scene.near, tiny_scene.far).reshape(-1)
    targets = np.asarray(view.images, np.float32).reshape(-1, 3)
    prediction = eqx.filter_jit(lambda m, r: mx.predictive(m, r))(model, rays)
    coarse = eqx.filter_jit(lambda m, r: m(r))(model, rays).coarse

    weights = np.asarray(coarse.weights, np.float64)
    density = np.asarray(coarse.field.density, np.float64)
    edges = np.asarray(coarse.t_edges, np.float64)
    norm = np.linalg.norm(np.asarray(rays.directions, np.float64), axis=-1)
    light = np.exp(-np.sum(density * np.maximum(np.diff(edges, axis=-1), 0.0) * norm[:, None], axis=-1))
    # An untrained model leaves much of the light to the background: the component matters here.
    assert np.median(light) > 0.05 and np.min(light) < 0.95
    masses = np.concatenate([weights, light[:, None]], axis=-1)
    coefficients = masses / masses.sum(-1, keepdims=True)
    extra = np.ones((len(light), 1, 3))
    location = np.concatenate([np.asarray(coarse.field.rgb, np.float64), extra], axis=1)
    scale = np.concatenate([np.asarray(coarse.field.beta, np.float64), 0.02 * extra], axis=1)

    colour = prediction.colour
    assert colour.coefficients.shape == (len(light), weights.shape[-1] + 1)
    np.testing.assert_allclose(colour.coefficients, coefficients, rtol=2e-4, atol=1e-6)
    reference = np_log_density(targets, coefficients, location, scale)
    np.testing.assert_allclose(colour.log_prob(jnp.asarray(targets)), reference, rtol=1e-4, atol=1e-3)
    reference_cdf = np.stack([np_channel_cdf(targets[:, c], coefficients, location[..., c], scale[..., c])
                              for c in range(3)], axis=-1)
    np.testing.assert_allclose(colour.cdf(jnp.asarray(targets)), reference_cdf, atol=2e-5)
    # The mixture's mean is the coarse render over the white background, in the chunked pass too.
    np.testing.assert_allclose(colour.mean(), np.asarray(coarse.rgb), atol=2e-5)
    maps = mx.uncertainty.predict_rays(model, rays, 300, targets=targets)  # the last chunk padded
    np.testing.assert_allclose(maps["colour_mean"], np.asarray(coarse.rgb), atol=2e-5)
    np.testing.assert_allclose(maps["colour_cdf"], reference_cdf, atol=2e-5)
    # A temperature multiplies the background's scale as it does every other.
    np.testing.assert_allclose(mx.predictive(model, rays, temperature=2.0).colour.scale[:, -1], 0.04, rtol=1e-6)
    # The training objective scores the same pixels with the same density.
    from mixnerf_eqx._nn.compositing import log_transmittance

    log_t = jax.vmap(log_transmittance)(coarse.field.density, coarse.t_edges, jnp.asarray(norm, jnp.float32))
    nll = jax.vmap(model.mixture.colour_nll)(coarse.weights, coarse.field.rgb, coarse.field.beta,
                                             jnp.asarray(targets), log_t)
    np.testing.assert_allclose(-np.asarray(colour.log_prob(jnp.asarray(targets))), nll, rtol=1e-4, atol=1e-3)

    # Without the option, the coefficients stay the weights normalised over the samples.
    plain = build_model(tiny_config, key=jax.random.key(3), white_background=True)
    assert plain.mixture.background is None
    assert mx.predictive(plain, rays).colour.coefficients.shape == weights.shape


def test_eval_writes_uncertainty_maps_and_calibration(tiny_config, tiny_scene, tmp_path):
    import json

    from mixnerf_eqx.cli.eval import main as eval_main

    # A run folder holding an untrained state: the command's plumbing, not the model, is tested.
    run_dir = tmp_path / "run"
    config = dataclasses.replace(
        tiny_config, train=dataclasses.replace(tiny_config.train, run_dir=str(run_dir))
    )
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps(mx.config.config_to_dict(config)))
    mx.runs.save_checkpoint(
        run_dir, mx.training.init_train_state(config, tiny_scene), config=mx.config.config_to_dict(config)
    )
    out = tmp_path / "eval"
    arguments = [str(run_dir), "--max-views", "1", "--no-lpips", "--no-progress", "--out", str(out)]
    assert eval_main([*arguments, "--uncertainty", "--temperature", "1.5"]) == 0
    report = json.loads((out / "metrics.json").read_text())["uncertainty"]
    assert report["temperature"] == 1.5 and len(report["coverage"]) == 4
    arrays = np.load(out / "uncertainty.npz")
    height, width = tiny_scene.test.height, tiny_scene.test.width
    assert arrays["colour_std"].shape == (1, height, width, 3)
    assert arrays["depth_lower"].shape == (4, 1, height, width)
    view = int(arrays["view_ids"][0])
    for name in ("colour_spread", "colour_error", "depth_spread", "depth_error"):
        assert (out / f"test_{view:03d}_{name}.png").is_file()
    assert eval_main([*arguments, "--uncertainty", "--temperature", "0"]) == 2
