"""Recalibrated intervals (isotonic and split conformal), FlipNeRF's calibration measures, and
what eval writes for a user to take away (depth arrays, point clouds).

References: predictive distributions whose truth is known (Laplace and Laplace-mixture draws
in numpy, float64), the closed-form coverage of a split-conformal interval (the new value's
rank among `n + 1` is uniform) and the closed-form quantiles of a Beta(2, 1) distribution,
a direct loop for the calibration error, and a plane whose world depth is known for the NDC
conversion.
"""

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._predictive.exports import world_points
from mixnerf_eqx._predictive.recalibration import (
    IsotonicMap,
    Recalibration,
    calibration_error,
    conformal_levels,
    minimum_calibration_pixels,
)
from mixnerf_eqx.data import Views

MASSES = (0.5, 0.8, 0.9, 0.95)


def laplace_cdf(x, location, scale):
    z = (x - location) / scale
    return np.where(z < 0, 0.5 * np.exp(np.minimum(z, 0)), 1 - 0.5 * np.exp(-np.maximum(z, 0)))


def too_narrow_pit(rng, count):
    """PIT values of Laplace(0, 1) truths under a model that predicts Laplace(0, 0.5) in each of
    three channels: intervals twice too narrow."""
    return laplace_cdf(rng.laplace(0.0, 1.0, (count, 3)), 0.0, 0.5)


def covered(pit, recalibration, index):
    return np.mean((pit >= recalibration.colour_lower[index]) & (pit <= recalibration.colour_upper[index]))


def test_recalibrated_intervals_hold_their_mass_where_the_raw_ones_do_not():
    rng = np.random.default_rng(0)
    calibration, test = too_narrow_pit(rng, 4000), too_narrow_pit(rng, 200_000)
    raw = Recalibration.fit("raw", calibration)
    for method in ("isotonic", "conformal"):
        fitted = Recalibration.fit(method, calibration, masses=MASSES)
        for index, mass in enumerate(MASSES):
            # The calibration set's own sampling error dominates: sd sqrt(m (1 - m) / 4000).
            tolerance = 4.0 * math.sqrt(mass * (1 - mass) / 4000)
            assert abs(covered(test, fitted, index) - mass) < tolerance, (method, mass)
    for index, mass in enumerate(MASSES):
        # Laplace(0, 1) inside the central interval of Laplace(0, 0.5): 1 - (1 - m)^(1/2).
        expected = 1.0 - math.sqrt(1.0 - mass)
        assert abs(covered(test, raw, index) - expected) < 0.01
        assert covered(test, raw, index) < mass - 0.1  # the check above can fail


def test_split_conformal_coverage_follows_the_ranks_of_its_ends():
    # With n = 10 calibration values and mass 0.5, the ends are the floor(11 / 4) = 2nd and
    # the ceil(33 / 4) = 9th smallest: a new exchangeable value lies between them when 2 to 8
    # of the others lie below it, probability exactly 7 / 11. With n = 19 and mass 0.9 the
    # ends are the 1st and the 19th: 18 / 20, the mass itself.
    rng = np.random.default_rng(1)
    trials = 40_000
    for count, mass, expected in ((10, 0.5, 7 / 11), (19, 0.9, 18 / 20)):
        calibration = rng.uniform(size=(trials, count))
        new = rng.uniform(size=trials)
        hits = np.empty(trials, bool)
        for trial in range(trials):
            lower, upper = conformal_levels(calibration[trial], (mass,))
            hits[trial] = lower[0, 0] <= new[trial] <= upper[0, 0]
        assert abs(hits.mean() - expected) < 4 * math.sqrt(expected * (1 - expected) / trials), count


def test_conformal_ends_follow_truths_that_lean_to_one_side():
    # PIT values from Beta(2, 1) (density 2u: truths lean above the model's median). The
    # equal-tailed ends converge to its quantiles sqrt((1 -+ m) / 2), and the interval holds
    # its mass on new values (narrower in PIT levels than a central interval of the same
    # mass, whose width there is m).
    rng = np.random.default_rng(7)
    calibration, new = rng.beta(2.0, 1.0, (20_000, 3)), rng.beta(2.0, 1.0, (200_000, 3))
    fitted = Recalibration.fit("conformal", calibration, masses=MASSES)
    for index, mass in enumerate(MASSES):
        lower, upper = fitted.colour_lower[index], fitted.colour_upper[index]
        assert np.allclose(lower, math.sqrt((1 - mass) / 2), atol=0.01), mass
        assert np.allclose(upper, math.sqrt((1 + mass) / 2), atol=0.01), mass
        assert abs(covered(new, fitted, index) - mass) < 0.01, mass


def test_too_few_calibration_pixels_and_bad_masses_are_clear_errors():
    assert minimum_calibration_pixels(0.95) == 39 and minimum_calibration_pixels(0.5) == 3
    assert minimum_calibration_pixels(0.9) == 19
    with pytest.raises(ValueError, match="38 calibration pixels are too few .* at least 39"):
        Recalibration.fit("conformal", np.full((38, 3), 0.5))
    # At the minimum the 95% interval's ends are the smallest and the largest value.
    values = np.random.default_rng(8).permutation(np.linspace(0.01, 0.99, 39))
    fitted = Recalibration.fit("conformal", np.stack([values] * 3, axis=1), masses=(0.5, 0.95))
    assert fitted.unbounded_masses() == {"colour": [], "depth": []}
    np.testing.assert_array_equal(fitted.colour_lower[1], 0.01)
    np.testing.assert_array_equal(fitted.colour_upper[1], 0.99)
    # The 50% interval's ends: the floor(40 / 4) = 10th and the ceil(120 / 4) = 30th smallest.
    np.testing.assert_allclose(fitted.colour_lower[0], np.sort(values)[9], rtol=0, atol=0)
    np.testing.assert_allclose(fitted.colour_upper[0], np.sort(values)[29], rtol=0, atol=0)
    for masses in ((0.5, 1.0), (0.0,), (), (-0.2,)):
        with pytest.raises(ValueError, match="interval mass"):
            Recalibration.fit("isotonic", np.full((50, 3), 0.5), masses=masses)
    with pytest.raises(ValueError, match="method must be one of"):
        Recalibration.fit("platt", np.full((50, 3), 0.5))
    with pytest.raises(ValueError, match=r"values in \[0, 1\]"):
        Recalibration.fit("conformal", np.array([[0.5, np.nan, 0.5]] * 30))
    with pytest.raises(ValueError, match="no calibration pixels"):
        Recalibration.fit("isotonic", np.zeros((0, 3)))


def test_calibration_error_follows_flipnerfs_definition():
    rng = np.random.default_rng(2)
    pit = np.round(rng.uniform(size=(300, 2)), 2)  # ties on purpose
    for column in range(2):
        values = np.sort(pit[:, column])
        # A direct loop: the fraction of values at or below each value.
        frequencies = np.array([np.sum(values <= value) / values.size for value in values])
        expected = np.mean((values - frequencies) ** 2)
        assert abs(calibration_error(pit)[column] - expected) < 1e-15
    # Uniform values are calibrated: the error is O(1 / n).
    assert calibration_error(np.arange(1, 1001) / 1001.0)[0] < 1e-6
    assert calibration_error(too_narrow_pit(rng, 5000))[0] > 5e-3


def test_isotonic_map_recovers_the_true_density():
    rng = np.random.default_rng(3)
    calibration, test_truth = rng.laplace(0.0, 1.0, (100_000, 1)), rng.laplace(0.0, 1.0, (100_000, 1))
    fitted = IsotonicMap.fit(laplace_cdf(calibration, 0.0, 0.5))
    pit = laplace_cdf(test_truth, 0.0, 0.5)
    raw_nll = -np.mean(np.log(np.exp(-np.abs(test_truth) / 0.5) / (2 * 0.5)))
    calibrated_nll = raw_nll - np.mean(fitted.log_slope(pit))
    true_nll = 1.0 + math.log(2.0)  # the entropy of Laplace(0, 1)
    assert abs(raw_nll - 2.0) < 0.02
    assert abs(calibrated_nll - true_nll) < 0.03
    # A and its inverse agree, and A maps the PIT values to nearly uniform ones.
    assert np.allclose(fitted(fitted.inverse(0.3)[None, :]), 0.3, atol=1e-9)
    assert calibration_error(fitted(pit))[0] < 1e-4


def test_isotonic_density_at_an_atom_is_the_neighbouring_segments():
    # PIT values piled on one value (float32 rounding to 1) make knots that several quantiles
    # share: the map jumps there, and the density of a truth on the atom is the continuous
    # part's next to it, not a slope of one shared knot to the next.
    rng = np.random.default_rng(6)
    pit = np.concatenate([rng.uniform(size=9000), np.full(500, 0.3), np.full(500, 1.0)])[:, None]
    fitted = IsotonicMap.fit(pit)

    def slope(u):
        return float(np.exp(fitted.log_slope(np.array([[u]])))[0, 0])

    # On an atom: the continuous part's slope beside it (after 0.3; before 1, the last knot),
    # not the jump over a zero-length run.
    assert slope(1.0) == slope(1.0 - 1e-12)
    assert slope(0.3) == slope(0.3 + 1e-12)
    # Closed form: A rises by 1 over [0, 1], 0.05 of it in each atom's jump, so its slope
    # integrates to 0.9 over the continuous part (a Monte-Carlo mean over uniform levels).
    levels = np.random.default_rng(7).uniform(size=(200_000, 1))
    assert abs(np.mean(np.exp(fitted.log_slope(levels))) - 0.9) < 0.01
    assert np.all(np.isfinite(fitted.log_slope(pit)))


def test_calibration_pixels_are_drawn_per_view_and_depths_kept_where_finite(short_run, tiny_scene):
    _, model = short_run
    val = tiny_scene.val
    pixels = val.num_views * val.height * val.width
    every = mx.uncertainty.calibration_pit(model, val, tiny_scene.near, tiny_scene.far, max_pixels=None)
    assert every["colour_cdf"].shape == (pixels, 3)
    assert every["depth_cdf"].shape == (int(np.isfinite(val.depths).sum()),)
    drawn = mx.uncertainty.calibration_pit(model, val, tiny_scene.near, tiny_scene.far, max_pixels=500, seed=3)
    chosen = np.sort(np.random.default_rng(3).choice(pixels, size=500, replace=False))
    np.testing.assert_allclose(drawn["colour_cdf"], every["colour_cdf"][chosen], atol=1e-6)
    assert drawn["depth_cdf"].size == int(np.isfinite(val.depths.reshape(-1)[chosen]).sum())
    # NDC rays are not measured in z-depth: no depth PIT values from them.
    ndc = dataclasses.replace(val, ndc=True)
    assert mx.uncertainty.calibration_pit(model, ndc, 0.0, 1.0, max_pixels=50)["depth_cdf"].size == 0


def test_levels_carry_their_masses_and_a_new_calibration_compiles_nothing(short_run, tiny_scene, monkeypatch):
    import equinox as eqx

    from mixnerf_eqx._predictive import uncertainty as _uncertainty
    from mixnerf_eqx.data import rays_for_views

    _, model = short_run
    once = eqx.filter_jit(eqx.debug.assert_max_traces(_uncertainty._summarise_rays, max_traces=1))
    monkeypatch.setattr(_uncertainty, "_summarise_chunk", once)
    view = tiny_scene.test.select([0])
    rays = rays_for_views(view, tiny_scene.near, tiny_scene.far)
    rng = np.random.default_rng(8)
    raw = mx.uncertainty.predict_rays(model, rays, masses=MASSES)
    fitted = Recalibration.fit("conformal", too_narrow_pit(rng, 400), masses=MASSES)
    moved = mx.uncertainty.predict_rays(model, rays, masses=MASSES, levels=fitted.interval_levels())
    assert not np.allclose(raw["colour_lower"], moved["colour_lower"])
    # Levels fitted for other masses of the same count are refused, not mislabelled.
    other = Recalibration.fit("conformal", too_narrow_pit(rng, 400), masses=(0.6, 0.7, 0.8, 0.9))
    with pytest.raises(ValueError, match="levels belong to the interval masses"):
        mx.uncertainty.predict_rays(model, rays, masses=MASSES, levels=other.interval_levels())
    with pytest.raises(ValueError, match="pass the recalibration the maps were made with"):
        mx.uncertainty.coverage_report({**raw, "masses": np.asarray(MASSES)}, view.images, None, other)


def test_the_mixtures_distribution_functions_match_float64(tmp_path):
    from test_predictive import as_mixture, draw, np_channel_cdf, np_log_density, random_mixtures

    rng = np.random.default_rng(4)
    coefficients, location, scale = random_mixtures(rng, 200, 5)
    truth = draw(rng, coefficients, location, scale, 1)[:, 0]
    mixture = as_mixture(coefficients, location, scale)
    cdf = np.asarray(mixture.cdf(jnp.asarray(truth, jnp.float32)))
    channel = np.asarray(mixture.channel_log_prob(jnp.asarray(truth, jnp.float32)))
    for c in range(3):
        reference = np.array([np_channel_cdf(truth[r, c], coefficients[r], location[r, :, c], scale[r, :, c]) for r in range(200)])
        np.testing.assert_allclose(cdf[:, c], reference, atol=2e-6)
        one_channel = np.stack([truth[:, c]] * 3, axis=-1)
        # The marginal density of channel c: the joint density of a 1-channel mixture.
        marginal = np_log_density(one_channel[:, None, :1], coefficients[:, None], location[:, None, :, c : c + 1], scale[:, None, :, c : c + 1])[:, 0]
        np.testing.assert_allclose(channel[:, c], marginal, rtol=2e-5, atol=2e-5)
    # Per-channel levels: each channel's quantile at its own level inverts its CDF.
    levels = jnp.asarray([[0.1, 0.5, 0.9], [0.3, 0.05, 0.7]], jnp.float32)
    quantiles = np.asarray(mixture.channel_quantiles(levels))
    for row in range(2):
        back = np.asarray(mixture.cdf(jnp.asarray(quantiles[row])))
        np.testing.assert_allclose(back, np.broadcast_to(levels[row], back.shape), atol=2e-5)


def test_the_termination_distance_cdf_is_piecewise_linear():
    weights = jnp.asarray([[0.0, 0.5, 0.25, 0.25]], jnp.float32)
    edges = jnp.asarray([[1.0, 2.0, 3.0, 4.0, 5.0]], jnp.float32)
    depth = mx.uncertainty.TerminationDistribution(weights, edges)
    at = jnp.asarray([[2.5]], jnp.float32)[:, 0]
    assert float(depth.cdf(at)[0]) == pytest.approx(0.25)
    assert float(depth.cdf(jnp.asarray([jnp.inf]))[0]) == 1.0
    assert float(depth.cdf(jnp.asarray([0.0]))[0]) == 0.0
    with pytest.raises(ValueError, match="one distance per ray"):
        depth.cdf(jnp.zeros((2,)))
    # A ray without weight terminates at its far bound, as its quantiles report.
    empty = mx.uncertainty.TerminationDistribution(jnp.zeros((1, 4), jnp.float32), edges)
    assert float(empty.cdf(jnp.asarray([4.9]))[0]) == 0.0 and float(empty.cdf(jnp.asarray([5.0]))[0]) == 1.0
    assert float(empty.quantile(0.5)[0]) == 5.0


def test_ndc_depth_maps_back_to_the_world_plane_it_came_from():
    # A camera at the origin looking down -z; an NDC depth t everywhere is the world plane
    # z = -1 / (1 - t) (near plane 1): t = 0.8 is the plane z = -5, a camera z-depth of 5.
    height, width, focal = 6, 8, 7.0
    pose = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)[None]
    views = Views(images=np.zeros((1, height, width, 3), np.float32), camtoworlds=pose, focal=focal, ndc=True)
    points, depth = world_points(views, 0, np.full((height, width), 0.8), 0.0, 1.0)
    np.testing.assert_allclose(points[..., 2], -5.0, rtol=1e-6)
    np.testing.assert_allclose(depth, 5.0, rtol=1e-6)
    # Each point lies on its pixel's ray from the camera: x / z = (u - W/2) / (-f), and
    # y / z = -(v - H/2) / (-f) (OpenGL: y up).
    u = np.arange(width) + 0.5 - width / 2
    v = np.arange(height) + 0.5 - height / 2
    np.testing.assert_allclose(points[0, :, 0] / points[0, :, 2], -u / focal, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(points[:, 0, 1] / points[:, 0, 2], v / focal, rtol=1e-5, atol=1e-7)
    # t = 1 is the point at infinity: no point, an infinite depth, no NaN depth.
    far_points, far_depth = world_points(views, 0, np.ones((height, width)), 0.0, 1.0)
    assert np.all(np.isnan(far_points)) and np.all(np.isinf(far_depth))
    # A bounded scene's depth is a distance along the unnormalised camera direction already.
    bounded = dataclasses.replace(views, ndc=False)
    _, plain = world_points(bounded, 0, np.full((height, width), 3.0), 2.0, 6.0)
    np.testing.assert_allclose(plain, 3.0, rtol=1e-6)


def test_ndc_round_trip_of_world_points_from_a_turned_and_moved_camera():
    from mixnerf_eqx.data import rays_for_views

    height, width, focal = 5, 9, 6.0
    angle = np.deg2rad(12.0)
    turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    tilt = np.array([[1, 0, 0], [0, np.cos(0.1), -np.sin(0.1)], [0, np.sin(0.1), np.cos(0.1)]])
    pose = np.concatenate([turn @ tilt, [[0.2], [-0.1], [0.3]]], axis=1)[None]
    views = Views(images=np.zeros((1, height, width, 3), np.float32), camtoworlds=pose.astype(np.float32), focal=focal, ndc=True)
    world = rays_for_views(dataclasses.replace(views, ndc=False), 0.0, 1.0)
    origins, directions = np.asarray(world.origins[0], np.float64), np.asarray(world.directions[0], np.float64)
    along = np.random.default_rng(1).uniform(3.0, 9.0, (height, width))  # camera z-depths
    truth = origins + along[..., None] * directions
    # The NDC ray parameter of each world point (NeRF's appendix C, near plane 1).
    z_ndc = 1.0 + 2.0 / truth[..., 2]
    t = (z_ndc + 1.0) / 2.0
    points, depth = world_points(views, 0, t, 0.0, 1.0)
    np.testing.assert_allclose(points, truth, rtol=2e-5, atol=2e-5)
    np.testing.assert_allclose(depth, along, rtol=2e-5)


def test_eval_recalibrates_on_validation_views_and_exports_depth_and_points(short_run, tiny_scene, tmp_path, capsys):
    trimesh = pytest.importorskip("trimesh")
    from mixnerf_eqx.cli.eval import main as eval_main

    out = tmp_path / "eval"
    common = [str(short_run[0]), "--max-views", "2", "--no-lpips", "--no-progress", "--no-renders"]
    assert eval_main([*common, "--out", str(out), "--uncertainty"]) == 0
    printed = capsys.readouterr().out
    assert "conformal intervals (fitted on the" in printed and "validation views" in printed
    report = json.loads((out / "metrics.json").read_text())["uncertainty"]
    calibration = report["calibration"]
    assert calibration["method"] == "conformal" and set(calibration["colour_coverage"]) == {"0.5", "0.8", "0.9", "0.95"}
    assert calibration["depth_coverage"] is not None  # the built-in scene knows its depth
    # "coverage" is the model's own intervals', beside the raw NLL.
    assert set(report["coverage"]) == set(calibration["colour_coverage"])
    restored = Recalibration.from_json(calibration["levels"])
    assert restored.method == "conformal" and restored.pixels > 0
    arrays = np.load(out / "uncertainty.npz")
    view = int(arrays["view_ids"][0])
    depth = np.load(out / f"test_{view:03d}_depth.npy")
    interval = np.load(out / f"test_{view:03d}_depth_interval.npy")
    assert depth.dtype == np.float32 and depth.shape == (tiny_scene.test.height, tiny_scene.test.width)
    assert interval.shape == (4, 2, *depth.shape)
    assert np.all(interval[:, 0] <= depth + 1e-4) and np.all(depth <= interval[:, 1] + 1e-4)
    # A standard reader sees the points, their colours and their uncertainty.
    cloud = trimesh.load(out / f"test_{view:03d}_points.ply")
    vertices = cloud.metadata["_ply_raw"]["vertex"]["data"]
    assert {"x", "y", "z", "red", "green", "blue", "depth_lower", "depth_upper", "colour_std"} <= set(vertices.dtype.names)
    assert len(cloud.vertices) == int(np.sum(arrays["acc"][0] >= 0.5))
    if len(vertices):
        assert np.all(vertices["depth_lower"] <= vertices["depth_upper"])

    isotonic = tmp_path / "isotonic"
    assert eval_main([*common, "--out", str(isotonic), "--uncertainty", "--calibration", "isotonic"]) == 0
    assert json.loads((isotonic / "metrics.json").read_text())["uncertainty"]["calibration"]["method"] == "isotonic"
    # Calibrating on the views being scored, or without the predictive pass: refused, before
    # anything is rendered; by default, the validation split gets the model's own intervals.
    import mixnerf_eqx.cli.eval as eval_module

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before refusing")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(eval_module, "evaluate", no_render)
        asked = ["--uncertainty", "--split", "val", "--calibration", "conformal"]
        assert eval_main([*common, "--out", str(tmp_path / "v"), *asked]) == 2
    assert "cannot score them" in capsys.readouterr().err
    assert eval_main([*common, "--out", str(tmp_path / "d"), "--uncertainty", "--split", "val"]) == 0
    assert "the model's own intervals (the views scored are the validation views" in capsys.readouterr().out
    assert eval_main([*common, "--out", str(tmp_path / "w"), "--calibration", "raw"]) == 2
    assert "needs --uncertainty" in capsys.readouterr().err
    assert eval_main([*common, "--out", str(tmp_path / "r"), "--uncertainty", "--split", "val", "--calibration", "raw"]) == 0


def test_recalibration_round_trips_through_json():
    rng = np.random.default_rng(5)
    fitted = Recalibration.fit("isotonic", too_narrow_pit(rng, 500), rng.uniform(size=200), masses=MASSES)
    again = Recalibration.from_json(json.dumps(fitted.to_json()))
    for name in ("colour_lower", "colour_upper", "depth_lower", "depth_upper"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fitted, name))
    np.testing.assert_array_equal(again.colour_map.knots, fitted.colour_map.knots)
    levels = fitted.interval_levels()
    assert levels.colour_lower.shape == (4, 3) and levels.depth_lower.shape == (4,)
    assert jax.tree_util.tree_structure(levels) == jax.tree_util.tree_structure(mx.uncertainty.IntervalLevels.raw(MASSES))


def test_conformal_ends_past_the_support_are_without_bound():
    from test_predictive import as_mixture, random_mixtures

    # 30% of the calibration truths lie above where the model puts mass (PIT values of
    # exactly 1): each interval's upper end must cover them too, so it is unbounded, while
    # the lower ends stay bounded (the 50% interval's at the 300th of 1,200 values, the
    # 90% one's at the 60th, both among the uniform ones).
    pit = np.concatenate([np.random.default_rng(9).uniform(size=(840, 3)), np.ones((360, 3))])
    fitted = Recalibration.fit("conformal", pit, pit[:, 0], masses=(0.5, 0.9))
    assert fitted.unbounded_masses() == {"colour": [0.5, 0.9], "depth": [0.5, 0.9]}
    assert np.all(fitted.colour_upper == 1.0) and np.all(fitted.depth_upper == 1.0)
    ordered = np.sort(pit, axis=0)
    np.testing.assert_array_equal(fitted.colour_lower, ordered[[299, 59]])
    np.testing.assert_array_equal(fitted.depth_lower, ordered[[299, 59], 0])
    coefficients, location, scale = random_mixtures(np.random.default_rng(10), 5, 4)
    weights = jnp.asarray(np.random.default_rng(11).uniform(0.1, 1.0, (5, 4)), jnp.float32)
    edges = jnp.broadcast_to(jnp.linspace(2.0, 6.0, 5, dtype=jnp.float32), (5, 5))
    prediction = mx.uncertainty.Predictive(
        colour=as_mixture(coefficients, location, scale),
        depth=mx.uncertainty.TerminationDistribution(weights, edges),
        rgb=jnp.zeros((5, 3)),
        render_depth=jnp.zeros((5,)),
        acc=jnp.ones((5,)),
    )
    summary = mx.uncertainty.summarise(prediction, (0.5, 0.9), levels=fitted.interval_levels())
    assert np.all(np.asarray(summary.colour_upper) >= 1.0)
    np.testing.assert_array_equal(np.asarray(summary.depth_upper), 6.0)
    # The bounded ends are solved as before: the raw quantiles at their levels.
    for index in range(2):
        np.testing.assert_allclose(
            np.asarray(summary.depth_lower[index]),
            np.asarray(prediction.depth.quantile(float(fitted.depth_lower[index]))),
            rtol=0,
            atol=1e-5,
        )
        assert np.all(np.asarray(summary.depth_lower[index]) > 2.0)


def test_eval_replaces_only_folders_it_wrote(short_run, tmp_path, capsys):
    from mixnerf_eqx.cli import eval as eval_module
    from mixnerf_eqx.cli.eval import main as eval_main

    common = [str(short_run[0]), "--max-views", "1", "--no-lpips", "--no-progress", "--no-renders"]
    # A folder of the user's that holds only the kinds of file eval writes.
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("holiday.png", "settings.json", "mesh.ply"):
        (photos / name).write_text("mine")
    assert eval_main([*common, "--out", str(photos)]) == 2
    assert "holds files eval did not write" in capsys.readouterr().err
    assert sorted(p.name for p in photos.iterdir()) == ["holiday.png", "mesh.ply", "settings.json"]
    # Folders beside --out that eval did not write are left alone, and in the way is an error.
    results = tmp_path / "results"
    for sibling in ("results.old", "results.partial"):
        (tmp_path / sibling).mkdir()
        (tmp_path / sibling / "thesis.tex").write_text("mine")
    assert eval_main([*common, "--out", str(results)]) == 2
    assert "eval did not write it" in capsys.readouterr().err
    assert (tmp_path / "results.old" / "thesis.tex").is_file() and (tmp_path / "results.partial" / "thesis.tex").is_file()
    assert not results.exists()
    # Its own output it replaces; a Ctrl-C after the results are in place says so.
    mine = tmp_path / "mine"
    assert eval_main([*common, "--out", str(mine)]) == 0
    assert eval_main([*common, "--out", str(mine)]) == 0

    def interrupted(run_dir):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(eval_module, "plot_curves", interrupted)
        assert eval_main([*common, "--out", str(mine)]) == 130
    err = capsys.readouterr().err
    assert "the evaluation's results are in place" in err and "nothing was changed" not in err
    assert (mine / "metrics.json").is_file()
