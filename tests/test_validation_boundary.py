"""Inputs of the predictive API and metrics files, checked at the boundary for every accepted
type (`docs/reliability.md`, "On bad input")."""

import json
import dataclasses
import math
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._predictive.distribution import ColourMixture, TerminationDistribution
from mixnerf_eqx._util import json_io as strict_json


def _mixture():
    rng = np.random.default_rng(0)
    coefficients = rng.dirichlet(np.ones(4), size=5).astype(np.float32)
    location = rng.uniform(0, 1, (5, 4, 3)).astype(np.float32)
    scale = rng.uniform(0.05, 0.3, (5, 4, 3)).astype(np.float32)
    return ColourMixture(jnp.asarray(coefficients), jnp.asarray(location), jnp.asarray(scale))


def _termination():
    weights = jnp.full((5, 8), 1.0 / 8)
    edges = jnp.broadcast_to(jnp.linspace(2.0, 6.0, 9), (5, 9))
    return TerminationDistribution(weights, edges)


BAD_LEVELS = [
    0,
    1,
    0.0,
    1.0,
    -0.5,
    1.5,
    math.nan,
    math.inf,
    np.float32(1.5),
    np.float64(0.0),
    jnp.asarray(1.5),
]
GOOD_LEVELS = [0.5, np.float32(0.25), np.float64(0.75), jnp.asarray(0.5), np.asarray(0.5)]


@pytest.mark.parametrize("distribution", [_mixture, _termination])
@pytest.mark.parametrize("level", BAD_LEVELS, ids=repr)
def test_every_bad_level_is_the_range_message_whatever_its_type(distribution, level):
    dist = distribution()
    for call in (
        dist.quantile,
        dist.interval,
        lambda x: dist.quantiles([0.5, x]),
        lambda x: dist.quantiles(jnp.asarray([0.5, x])),
    ):
        with pytest.raises(ValueError, match=r"must lie in \(0, 1\)"):
            call(level)


@pytest.mark.parametrize("distribution", [_mixture, _termination])
@pytest.mark.parametrize("level", GOOD_LEVELS, ids=repr)
def test_every_accepted_type_gives_the_same_quantile(distribution, level):
    dist = distribution()
    reference = np.asarray(dist.quantile(float(level)))
    np.testing.assert_array_equal(np.asarray(dist.quantile(level)), reference)
    stacked = np.asarray(dist.quantiles(jnp.asarray([float(level), 0.9])))
    np.testing.assert_array_equal(stacked[0], reference)


def test_a_traced_bad_level_fails_when_computed():
    dist = _mixture()
    quantile = jax.jit(lambda level: dist.quantile(level))
    assert np.all(np.isfinite(np.asarray(quantile(0.5))))
    with pytest.raises(Exception, match=r"must lie in \(0, 1\)"):
        jax.block_until_ready(quantile(1.5))


@pytest.mark.parametrize(
    "temperature",
    # 1e-39 and 1e-45 are positive, but subnormal in float32: XLA flushes them to zero on the CPU.
    [-1, 0, -1.0, 0.0, math.nan, math.inf, -math.inf, np.float32(-2.0), jnp.asarray(math.inf), 1e-39, 1e-45],
    ids=repr,
)
def test_a_temperature_must_be_finite_and_positive(temperature):
    with pytest.raises(ValueError, match="temperature must be a finite positive number"):
        _mixture().with_temperature(temperature)


def test_good_temperatures_of_every_type_agree_and_a_traced_bad_one_fails():
    dist = _mixture()
    reference = np.asarray(dist.with_temperature(2.0).scale)
    for temperature in (2, np.float32(2.0), jnp.asarray(2.0)):
        np.testing.assert_array_equal(np.asarray(dist.with_temperature(temperature).scale), reference)
    scaled = jax.jit(lambda t: dist.with_temperature(t).scale)
    with pytest.raises(Exception, match="temperature must be a finite positive number"):
        jax.block_until_ready(scaled(-1.0))


def test_metrics_json_is_strict_and_names_what_was_not_finite():
    value = {
        "test": {"psnr": 20.0, "nll": math.inf},
        "history": [{"loss": math.nan}, {"loss": 1.0}],
        "x": np.float32(-np.inf),
    }
    text = strict_json.dumps(value)

    def refuse(constant):
        raise AssertionError(f"non-strict constant {constant}")

    parsed = json.loads(text, parse_constant=refuse)
    assert parsed["test"] == {"psnr": 20.0, "nll": None}
    assert parsed["history"] == [{"loss": None}, {"loss": 1.0}]
    assert parsed["x"] is None
    assert set(parsed["non_finite"]) == {"test.nll", "history[0].loss", "x"}
    assert "inf" in parsed["non_finite"]["test.nll"] and "nan" in parsed["non_finite"]["history[0].loss"]
    assert json.loads(strict_json.dumps({"a": 1.5}), parse_constant=refuse) == {"a": 1.5}


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0", "1e-45", "1e-36", "1e5"])
def test_eval_refuses_a_temperature_outside_its_range(value, tmp_path):
    process = subprocess.run(
        [sys.executable, "-m", "mixnerf_eqx.eval", str(tmp_path), "--uncertainty", "--temperature", value],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert process.returncode == 2
    assert "--temperature must lie in [0.001, 1000]" in process.stderr


def test_eval_refuses_a_temperature_without_uncertainty(tmp_path):
    process = subprocess.run(
        [sys.executable, "-m", "mixnerf_eqx.eval", str(tmp_path), "--temperature", "2"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert process.returncode == 2
    assert "--temperature scales the predictive distribution: it needs --uncertainty" in process.stderr


def test_a_reveal_longer_than_the_run_is_a_warning_and_a_fraction_is_not(tiny_scene, tmp_path):
    from helpers import TINY_OVERRIDES, TINY_SHARED_OVERRIDES

    from mixnerf_eqx._config import replace_setting

    grid = [
        *TINY_SHARED_OVERRIDES,
        'model.field="grid"',
        "grid.levels=2",
        "grid.min_resolution=8",
        "grid.max_resolution=16",
    ]
    long = mx.load_config("builtin", [*grid, "train.max_steps=3", "grid.coarse_to_fine_steps=10"])
    (message,) = mx.config.setting_warnings(long)
    assert message.startswith("grid.coarse_to_fine_steps = 10 is longer than the run (train.max_steps = 3)")
    assert mx.config.setting_warnings(replace_setting(long, "grid", coarse_to_fine_fraction=1.0)) == []
    assert mx.config.setting_warnings(replace_setting(long, "grid", coarse_to_fine_steps=3)) == []
    # The MLP has no levels to reveal: a grid key given to it is an error, not ignored.
    with pytest.raises(mx.ConfigError, match="grid.coarse_to_fine_steps = 10: .grid. does not apply"):
        mx.load_config("builtin", [*TINY_OVERRIDES, "grid.coarse_to_fine_steps=10"])
    # A run with it trains, and says so once at its start.
    long = replace_setting(long, "train", run_dir=str(tmp_path / "run"))
    with pytest.warns(mx.config.SettingWarning, match="the finest levels are never fully revealed"):
        result = mx.fit(long, dataset=tiny_scene, progress=False, write_renders=False)
    assert int(result.state.step) == 3


def test_the_public_api_keeps_its_names():
    assert mx.runs.FolderBusyError is not None and callable(mx.runs.hold_folder)


@pytest.fixture(scope="module")
def tiny_model(tiny_scene):
    from helpers import TINY_OVERRIDES

    config = mx.load_config("builtin", TINY_OVERRIDES)
    return mx.training.init_train_state(config, tiny_scene).model


def _rays(count, near=2.0, far=6.0):
    origins = jnp.zeros((count, 3)).at[:, 2].set(4.0)
    directions = jnp.zeros((count, 3)).at[:, 2].set(-1.0)
    return mx.nn.RayBundle(
        origins=origins,
        directions=directions,
        viewdirs=directions,
        radii=jnp.full((count, 1), 0.002),
        near=jnp.full((count, 1), near),
        far=jnp.full((count, 1), far),
    )


def test_zero_rays_give_empty_summaries_with_the_shapes_of_one(tiny_model):
    one = mx.uncertainty.predict_rays(tiny_model, _rays(1), chunk=8)
    none = mx.uncertainty.predict_rays(tiny_model, _rays(0), chunk=8)
    assert set(none) == set(one)
    for name, value in one.items():
        if name == "masses":
            np.testing.assert_array_equal(none[name], value)
            continue
        axis = 1 if name.endswith(("_lower", "_upper")) else 0
        expected = list(value.shape)
        expected[axis] = 0
        assert none[name].shape == tuple(expected), name


def test_rays_with_near_beyond_far_are_refused(tiny_model):
    with pytest.raises(ValueError, match="and bounds with near <= far: 3 of 3 rays do not"):
        mx.predictive(tiny_model, _rays(3, near=6.0, far=2.0))
    for near, far in ((math.nan, 2.0), (2.0, math.inf), (-math.inf, 2.0)):
        with pytest.raises(ValueError, match="and bounds with near <= far: 3 of 3 rays do not"):
            mx.predictive(tiny_model, _rays(3, near=near, far=far))
    with pytest.raises(Exception, match="near <= far"):
        mx.uncertainty.predict_rays(tiny_model, _rays(3, near=6.0, far=2.0), chunk=4)



def test_colours_of_the_wrong_shape_are_named(tiny_model):
    mixture = mx.predictive(tiny_model, _rays(3)).colour
    for method in ("log_prob", "cdf"):
        with pytest.raises(ValueError, match=rf"{method} takes one colour per ray, shape \(3, 3\).*got shape \(2, 3\)"):
            getattr(mixture, method)(jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"targets takes one colour per ray, shape \(3, 3\).*got shape \(3,\)"):
        mx.uncertainty.predict_rays(tiny_model, _rays(3), chunk=4, targets=np.zeros(3))


@pytest.mark.parametrize("where", ["origins", "directions"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_rays_with_a_nan_or_inf_origin_or_direction_are_refused(tiny_model, where, value):
    # They rendered to plausible numbers (a NaN origin gave the far bound as the depth median).
    rays = _rays(3)
    broken = np.asarray(getattr(rays, where)).copy()
    broken[1, 0] = value
    rays = dataclasses.replace(rays, **{where: jnp.asarray(broken)})
    with pytest.raises(ValueError, match="finite origins, directions and bounds .*: 1 of 3 rays do not"):
        mx.predictive(tiny_model, rays)
    with pytest.raises(ValueError, match="finite origins, directions"):
        mx.uncertainty.predict_rays(tiny_model, rays, chunk=4)


@pytest.mark.parametrize("bad", [{"temperature": math.inf}, {"temperature": -1.0}, {"masses": (0.5, 1.0)}])
def test_predict_rays_checks_its_numbers_before_rendering(tiny_model, bad):
    with pytest.raises(ValueError, match="temperature must be a finite positive number|must lie in"):
        mx.uncertainty.predict_rays(tiny_model, _rays(2), chunk=4, **bad)


@pytest.mark.parametrize("name", ["colour_level", "depth_level"])
def test_a_level_name_that_is_neither_coarse_nor_fine_is_one_line(tiny_model, name):
    with pytest.raises(ValueError, match=f"^{name} must be 'coarse' or 'fine', got 'both'$"):
        mx.predictive(tiny_model, _rays(2), **{name: "both"})
