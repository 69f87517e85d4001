"""Volume-rendering math (paper eqs. 2 and 8) against float64 numpy references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    as_f32,
    make_ray,
    random_ray,
    ref_accumulation,
    ref_blend_weights,
    ref_composite_rgb,
    ref_expected_depth,
)

import mixnerf_eqx as mx
from mixnerf_eqx.nn import FieldOutputs, VolumeRenderer, blend_weights, composite_rgb, expected_depth
from mixnerf_eqx._nn.compositing import accumulation

# float32 compositing of ~16 samples: a few ulp per product, relative to values of order one.
RTOL, ATOL = 1e-5, 1e-6


def _jnp(*arrays):
    return tuple(jnp.asarray(as_f32(a)) for a in arrays)


@pytest.mark.parametrize("seed", range(4))
def test_blend_weights_match_reference(seed):
    rng = np.random.default_rng(seed)
    t_edges, density, _ = random_ray(rng, 16)
    direction_norm = float(as_f32(rng.uniform(1.0, 1.5)))
    got = np.asarray(blend_weights(*_jnp(density, t_edges), jnp.float32(direction_norm)))
    expected = ref_blend_weights(density, t_edges, direction_norm)
    np.testing.assert_allclose(got, expected, rtol=RTOL, atol=ATOL)
    assert 0.0 <= got.sum() <= 1.0 + 1e-6


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("background", [None, (1.0, 1.0, 1.0), (0.2, 0.5, 0.9)])
def test_composite_accumulation_depth_match_reference(seed, background):
    rng = np.random.default_rng(10 + seed)
    # Low densities leave visible transmittance, so the background term matters.
    t_edges, density, rgb = random_ray(rng, 12, max_density=0.2)
    weights = ref_blend_weights(density, t_edges, 1.0)
    assert weights.sum() < 0.95
    weights_j, rgb_j, edges_j = _jnp(weights, rgb, t_edges)
    background_j = None if background is None else jnp.asarray(background, jnp.float32)
    got_rgb = np.asarray(composite_rgb(weights_j, rgb_j, background_j))
    expected_rgb = ref_composite_rgb(as_f32(weights), rgb, background)
    np.testing.assert_allclose(got_rgb, expected_rgb, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(float(accumulation(weights_j)), ref_accumulation(as_f32(weights)), rtol=RTOL)
    np.testing.assert_allclose(
        float(expected_depth(weights_j, edges_j)), ref_expected_depth(as_f32(weights), t_edges), rtol=RTOL
    )


def test_zero_density_ray_is_empty():
    t_edges = as_f32(np.linspace(2.0, 6.0, 9))
    density = np.zeros(8, np.float32)
    weights = blend_weights(*_jnp(density, t_edges), jnp.float32(1.3))
    np.testing.assert_array_equal(np.asarray(weights), 0.0)
    assert float(expected_depth(weights, jnp.asarray(t_edges))) == pytest.approx(6.0)
    assert float(accumulation(weights)) == 0.0
    rgb = jnp.asarray(np.random.default_rng(0).uniform(size=(8, 3)), jnp.float32)
    background = jnp.asarray([0.1, 0.2, 0.3], jnp.float32)
    np.testing.assert_allclose(np.asarray(composite_rgb(weights, rgb, background)), [0.1, 0.2, 0.3])


@pytest.mark.parametrize("opaque_index", [0, 3, 7])
def test_one_opaque_sample_takes_all_weight(opaque_index):
    t_edges = as_f32(np.linspace(2.0, 6.0, 9))
    density = np.zeros(8, np.float32)
    density[opaque_index] = 1e10
    density[opaque_index + 1 :] = 5.0  # hidden behind the opaque sample
    weights = np.asarray(blend_weights(*_jnp(density, t_edges), jnp.float32(1.0)))
    expected = np.zeros(8)
    expected[opaque_index] = 1.0
    np.testing.assert_allclose(weights, expected, atol=1e-6)
    mid = 0.5 * (t_edges[opaque_index] + t_edges[opaque_index + 1])
    assert float(expected_depth(jnp.asarray(weights), jnp.asarray(t_edges))) == pytest.approx(mid, rel=1e-6)


# --- regenerated weights (eq. 8) --------------------------------------------------------


def test_regenerated_weights_with_constant_ray_depth_equal_ordinary_weights():
    rng = np.random.default_rng(20)
    t_edges, density, _ = random_ray(rng, 16)
    norm = np.float32(1.27)
    ordinary = np.asarray(blend_weights(*_jnp(density, t_edges), jnp.asarray(norm)))
    regenerated = np.asarray(blend_weights(*_jnp(density, t_edges), jnp.full((16,), norm)))
    np.testing.assert_allclose(regenerated, ordinary, rtol=1e-6, atol=1e-7)


def test_regenerated_weights_follow_per_sample_ray_depth():
    rng = np.random.default_rng(21)
    t_edges, density, _ = random_ray(rng, 16)
    ray_depth = as_f32(rng.uniform(0.2, 2.5, 16))
    regenerated = np.asarray(blend_weights(*_jnp(density, t_edges, ray_depth)))
    np.testing.assert_allclose(
        regenerated, ref_blend_weights(density, t_edges, ray_depth), rtol=RTOL, atol=ATOL
    )
    ordinary = np.asarray(blend_weights(*_jnp(density, t_edges), jnp.float32(1.0)))
    assert np.max(np.abs(regenerated - ordinary)) > 1e-2


# --- the renderer Module ----------------------------------------------------------------


@pytest.mark.parametrize("background", [None, (1.0, 1.0, 1.0)])
def test_volume_renderer_matches_reference(background):
    rng = np.random.default_rng(30)
    t_edges, density, rgb = random_ray(rng, 16, max_density=0.3)
    direction = as_f32([0.3, -0.2, -1.0])
    norm = np.linalg.norm(direction.astype(np.float64))
    outputs = FieldOutputs(
        density=jnp.asarray(as_f32(density)), rgb=jnp.asarray(as_f32(rgb)), beta=None, ray_depth=None
    )
    renderer = VolumeRenderer(background=background)
    level = renderer(outputs, jnp.asarray(as_f32(t_edges)), make_ray(direction=direction))
    weights = ref_blend_weights(density, t_edges, norm)
    np.testing.assert_allclose(np.asarray(level.weights), weights, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(
        np.asarray(level.rgb), ref_composite_rgb(weights, rgb, background), rtol=RTOL, atol=ATOL
    )
    np.testing.assert_allclose(float(level.depth), ref_expected_depth(weights, t_edges), rtol=RTOL)
    np.testing.assert_allclose(float(level.acc), ref_accumulation(weights), rtol=RTOL)
    np.testing.assert_array_equal(np.asarray(level.t_edges), as_f32(t_edges))
    if background is not None:
        # A translucent ray over white is brighter than the same ray over nothing.
        assert np.all(np.asarray(level.rgb) > ref_composite_rgb(weights, rgb) + 0.1)


def test_a_batch_renders_each_ray_as_render_ray_does(tiny_config, tiny_scene):
    model = mx.build_model(tiny_config, key=jax.random.key(0))
    rays = mx.data.rays_for_views(tiny_scene.train.select([0]), tiny_scene.near, tiny_scene.far)
    rays = rays.reshape(-1)[::97][:6].reshape(2, 3)
    key = jax.random.key(11)
    # Compiled, as the model is used (an eager render of each ray alone takes seconds).
    render_batch = eqx.filter_jit(lambda m, r, k: m(r, key=k))
    render_one = eqx.filter_jit(lambda m, r, k: m.render_ray(r, key=k))
    for batch_key in (None, key):
        batch = render_batch(model, rays, batch_key)
        flat = rays.reshape(-1)
        ray_keys = None if batch_key is None else jax.random.split(batch_key, 6)
        for i in range(6):
            one = render_one(model, flat[i], None if ray_keys is None else ray_keys[i])
            for level in ("coarse", "fine"):
                a, b = getattr(batch, level), getattr(one, level)
                np.testing.assert_allclose(a.rgb.reshape(6, 3)[i], b.rgb, atol=1e-5)
                np.testing.assert_allclose(a.t_edges.reshape(6, -1)[i], b.t_edges, atol=1e-5)
                np.testing.assert_allclose(a.weights.reshape(6, -1)[i], b.weights, atol=1e-5)
    # Training randomness changes the samples; without a key they are evenly spaced.
    keyed, plain = render_batch(model, rays, key), render_batch(model, rays, None)
    assert not np.allclose(keyed.coarse.t_edges, plain.coarse.t_edges)
