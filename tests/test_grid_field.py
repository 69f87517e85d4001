"""The grid field: encodings against float64 numpy references, its schedule and regulariser,
and a short run."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY_SHARED_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx import ConfigError
from mixnerf_eqx.inference import Skipping, render_rays
from mixnerf_eqx.nn import GridField, HashEncoding, TriPlaneEncoding
from mixnerf_eqx._config import replace_setting
from mixnerf_eqx._nn.field.grid import density_activation
from mixnerf_eqx._train.loss import LossWeights
from mixnerf_eqx.metrics import psnr

GRID_OVERRIDES = [
    "model.field=grid",
    "grid.levels=3",
    "grid.min_resolution=8",
    "grid.max_resolution=32",
    "grid.features=4",
    "grid.decoder_width=32",
    "grid.view_width=16",
    "grid.box_radius=1.3",
    "grid.coarse_to_fine_steps=100",  # every level revealed within the tests' 150-step runs
    "grid.tv_weight=0.01",  # the quick start's 0.3 is for planes up to 64; these reach 32 with 4 features
    "optim.lr_init=1e-2",
    "optim.lr_final=1e-3",
]


def _field(encoding, **kwargs):
    box = dict(box_min=(-1.0, -2.0, -0.5), box_max=(1.0, 2.0, 1.5), bounded=False)
    return GridField(encoding, **{**box, **kwargs}, key=jax.random.key(1))


# --- float64 numpy references, written from the definitions -------------------------------------


def _np_bilinear(plane, u, v):
    """`plane[row, col, :]` interpolated at `u` (columns) and `v` (rows) in [-1, 1], corners aligned."""
    rows, cols = plane.shape[:2]
    x = (np.clip(u, -1, 1) + 1) / 2 * (cols - 1)
    y = (np.clip(v, -1, 1) + 1) / 2 * (rows - 1)
    total = np.zeros(plane.shape[2])
    for r in range(rows):
        for c in range(cols):
            # The tent function of texel (r, c): zero beyond one texel away.
            weight = max(0.0, 1 - abs(x - c)) * max(0.0, 1 - abs(y - r))
            total += weight * plane[r, c]
    return total


def _np_triplane(encoding, point):
    point = np.asarray(point, np.float64)
    rows = []
    for planes in encoding.planes:
        planes = np.asarray(planes, np.float64)
        yz = _np_bilinear(planes[0], point[1], point[2])
        xz = _np_bilinear(planes[1], point[0], point[2])
        xy = _np_bilinear(planes[2], point[0], point[1])
        rows.append(yz * xz * xy)
    return np.stack(rows)


def _np_hash(corner, resolution, table_size):
    side = resolution + 1
    if side**3 <= table_size:
        return int(corner[0] + side * (corner[1] + side * corner[2]))
    primes = (1, 2654435761, 805459861)
    hashed = 0
    for coordinate, prime in zip(corner, primes, strict=True):
        hashed ^= (int(coordinate) * prime) % 2**32
    return hashed % table_size


def _np_hash_encoding(encoding, point):
    unit = (np.clip(np.asarray(point, np.float64), -1, 1) + 1) / 2
    rows = []
    for table, res in zip(encoding.tables, encoding.resolutions, strict=True):
        table = np.asarray(table, np.float64)
        scaled = unit * res
        low = np.minimum(np.floor(scaled), res - 1)
        total = np.zeros(table.shape[1])
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    corner = low + np.array([dx, dy, dz])
                    weight = np.prod(np.maximum(0.0, 1 - np.abs(scaled - corner)))
                    total += weight * table[_np_hash(corner.astype(int), res, table.shape[0])]
        rows.append(total)
    return np.stack(rows)


def _points(count, seed, spread=1.0):
    return np.random.default_rng(seed).uniform(-spread, spread, (count, 3)).astype(np.float32)


def test_triplane_lookup_matches_a_float64_reference():
    encoding = TriPlaneEncoding((5, 9), 3, key=jax.random.key(0))
    points = _points(40, 0, spread=1.1)  # some outside [-1, 1]: clamped to the surface
    points[0] = [1.0, -1.0, 1.0]  # a corner, where the last texel's weight is exactly 1
    got = np.asarray(jax.vmap(encoding)(jnp.asarray(points)))
    want = np.stack([_np_triplane(encoding, p) for p in points])
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6)


def test_hash_lookup_matches_a_float64_reference_on_dense_and_hashed_levels():
    # Level 2 (7 cells, 512 corners) holds more corners than the 64-entry table: it is hashed;
    # level 3 (3 cells, 64 corners) fits and is indexed one to one.
    encoding = HashEncoding((3, 7), 2, 64, key=jax.random.key(0))
    encoding = eqx.tree_at(
        lambda e: e.tables,
        encoding,
        tuple(jax.random.normal(jax.random.key(i), t.shape) for i, t in enumerate(encoding.tables)),
    )
    assert encoding.tables[0].shape == (64, 2) and encoding.tables[1].shape == (64, 2)
    points = _points(40, 1, spread=1.05)
    got = np.asarray(jax.vmap(encoding)(jnp.asarray(points)))
    want = np.stack([_np_hash_encoding(encoding, p) for p in points])
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)


def test_triplane_returns_texels_at_texel_centres():
    encoding = TriPlaneEncoding((4,), 2, key=jax.random.key(3))
    planes = np.asarray(encoding.planes[0])
    # Grid vertex (i, j, k) of a resolution-4 level sits at -1 + 2/3 (i, j, k).
    i, j, k = 1, 3, 2
    point = jnp.asarray([-1 + 2 * i / 3, -1 + 2 * j / 3, -1 + 2 * k / 3], jnp.float32)
    want = planes[0, k, j] * planes[1, k, i] * planes[2, j, i]
    np.testing.assert_allclose(np.asarray(encoding(point))[0], want, rtol=1e-5)


def test_level_scale_weights_follow_the_closed_form():
    cells = (0.5, 0.1, 0.01)
    half = jnp.asarray([1.0, 2.0, 0.5])
    cov = jnp.asarray([1e-3, 4e-3, 2.5e-4])  # sigma^2 = 1e-3 on every axis in box units
    got = np.asarray(mx.nn.level_scale_weights(cov, half, cells))
    from math import erf, sqrt

    want = [erf(c / (sqrt(8) * sqrt(1e-3))) for c in cells]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert got[0] > got[1] > got[2] > 0
    # A point (no footprint) sees every level at full weight.
    np.testing.assert_allclose(mx.nn.level_scale_weights(jnp.zeros(3), half, cells), 1.0)


def test_total_variation_of_a_linear_ramp():
    encoding = TriPlaneEncoding((5,), 1, key=jax.random.key(0))
    ramp = np.broadcast_to(np.arange(5.0)[None, :, None, None] * 0.5, (3, 5, 5, 1))
    encoding = eqx.tree_at(lambda e: e.planes, encoding, (jnp.asarray(ramp, jnp.float32),))
    # Steps of 0.5 along the rows (4 of 5 differences each 0.25 squared), none along the columns.
    np.testing.assert_allclose(float(encoding.total_variation()), 0.25, rtol=1e-6)
    field = _field(encoding, tv_weight=0.1)
    np.testing.assert_allclose(float(field.regulariser()), 0.025, rtol=1e-6)
    assert float(_field(encoding).regulariser()) == 0.0


@pytest.mark.parametrize("kind", ["triplane", "hash"])
def test_field_shapes_and_finite_gradients(kind):
    key = jax.random.key(0)
    encoding = (
        TriPlaneEncoding((4, 8), 4, key=key) if kind == "triplane" else HashEncoding((4, 16), 2, 256, key=key)
    )
    field = _field(encoding, scale_weighting=True, density_noise=1.0)
    points = jnp.asarray(_points(64, 2, spread=2.5))  # inside and far outside the box
    covs = jnp.concatenate([jnp.zeros((32, 3)), jnp.full((32, 3), 1e-2)])
    dirs = jnp.tile(jnp.asarray([0.0, 0.6, 0.8]), (64, 1))
    # Compiled, as the field is used (eager, op by op, the gradient alone takes many seconds).
    out = eqx.filter_jit(lambda f: jax.vmap(f)(points, covs, dirs))(field)
    assert out.density.shape == (64,) and out.rgb.shape == (64, 3)
    assert out.beta.shape == (64, 3) and out.ray_depth.shape == (64,)
    density = eqx.filter_jit(lambda f: jax.vmap(f.density)(points, covs))(field)
    np.testing.assert_allclose(density, out.density, rtol=1e-6)

    def loss(f):
        keys = jax.random.split(jax.random.key(1), 64)
        o = jax.vmap(lambda p, c, d, k: f(p, c, d, key=k))(points, covs, dirs, keys)
        return jnp.sum(o.density) + jnp.sum(o.rgb) + jnp.sum(o.beta) + jnp.sum(o.ray_depth) + f.regulariser()

    grads = eqx.filter_jit(eqx.filter_grad(loss))(field)
    leaves = jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_array))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    # The shape contracts are checked: a point with two coordinates is refused.
    with pytest.raises(Exception, match="(?i)shape|type"):
        field(jnp.zeros(2), jnp.zeros(3), jnp.zeros(3))


def test_density_noise_is_added_in_training_only():
    field = _field(TriPlaneEncoding((4, 8), 3, key=jax.random.key(0)), density_noise=0.7)
    point, cov, viewdir = jnp.asarray([0.2, -0.5, 0.4]), jnp.full(3, 1e-3), jnp.asarray([0.0, 0.6, 0.8])
    raw = float(field._density_branch(point, cov)[0])
    key = jax.random.key(3)
    # Training (a key): softplus(raw + 0.7 z) with z the key's standard normal draw, in float64.
    z = float(jax.random.normal(key, ()))
    np.testing.assert_allclose(
        float(field(point, cov, viewdir, key=key).density), np.logaddexp(0.0, raw + 0.7 * z), rtol=1e-5
    )
    # Renders (no key) and the density queries of the occupancy grid add none.
    np.testing.assert_allclose(float(field(point, cov, viewdir).density), np.logaddexp(0.0, raw), rtol=1e-6)
    np.testing.assert_allclose(float(field.density(point, cov)), np.logaddexp(0.0, raw), rtol=1e-6)
    # The quick start sets it, and its baseline inherits it.
    for name in ("builtin_grid", "builtin_mipnerf_grid"):
        config = mx.load_config(name)
        assert mx.build_model(config, key=jax.random.key(0)).field.heads.density_noise == 1.0


def test_exponential_density_activation():
    encoding = TriPlaneEncoding((4, 8), 3, key=jax.random.key(0))
    field = _field(encoding, density_activation="exp", density_noise=0.7)
    point, cov, viewdir = jnp.asarray([0.2, -0.5, 0.4]), jnp.full(3, 1e-3), jnp.asarray([0.0, 0.6, 0.8])
    raw = float(field._density_branch(point, cov)[0])
    key = jax.random.key(3)
    z = float(jax.random.normal(key, ()))
    # exp(raw) in renders and density queries, exp(raw + 0.7 z) in training: float64 references.
    np.testing.assert_allclose(float(field.density(point, cov)), np.exp(raw), rtol=1e-5)
    np.testing.assert_allclose(float(field(point, cov, viewdir).density), np.exp(raw), rtol=1e-5)
    np.testing.assert_allclose(
        float(field(point, cov, viewdir, key=key).density), np.exp(raw + 0.7 * z), rtol=1e-5
    )
    # The cap keeps a huge raw density finite, with a finite (zero) gradient above it.
    raw_values = jnp.asarray([-30.0, 0.0, 5.0, 11.0, 500.0])
    values = density_activation(raw_values, "exp")
    np.testing.assert_allclose(
        values, np.exp(np.minimum(np.asarray(raw_values, np.float64), 11.0)), rtol=1e-6
    )
    grads = jax.grad(lambda r: jnp.sum(density_activation(r, "exp")))(raw_values)
    assert bool(jnp.all(jnp.isfinite(grads))) and float(grads[-1]) == 0.0
    np.testing.assert_allclose(
        density_activation(raw_values, "softplus"), np.logaddexp(0.0, raw_values), rtol=1e-6
    )
    with pytest.raises(ValueError, match="density_activation"):
        _field(encoding, density_activation="relu")
    # The quick start uses it, and its baseline inherits it; the MLP-sized default stays softplus.
    for name in ("builtin_grid", "builtin_mipnerf_grid"):
        config = mx.load_config(name)
        assert mx.build_model(config, key=jax.random.key(0)).field.heads.activation == "exp"
    assert mx.load_config(None, ["model.field=grid"]).grid.density_activation == "softplus"


def test_bounded_field_is_empty_outside_its_box():
    encoding = TriPlaneEncoding((4,), 2, key=jax.random.key(0))
    field = _field(encoding, bounded=True)
    inside = jnp.asarray([[0.0, 0.0, 0.5], [0.9, 1.9, 1.4]])
    outside = jnp.asarray([[1.2, 0.0, 0.5], [0.0, 0.0, -0.6]])
    assert bool(jnp.all(jax.vmap(field.density)(inside, jnp.zeros((2, 3))) > 0))
    np.testing.assert_array_equal(jax.vmap(field.density)(outside, jnp.zeros((2, 3))), 0.0)


def test_coarse_to_fine_reveals_levels_and_is_never_trained():
    encoding = TriPlaneEncoding((4, 8, 16), 2, key=jax.random.key(0))
    field = _field(encoding, coarse_to_fine_steps=100)
    np.testing.assert_allclose(field.at_step(0).level_weights, [1, 0, 0])
    np.testing.assert_allclose(field.at_step(25).level_weights, [1, 0.5, 0])
    np.testing.assert_allclose(field.at_step(100).level_weights, [1, 1, 1])
    np.testing.assert_allclose(field.level_weights, 1.0)
    # The stored mask gets no gradient: the step replaces it before rendering.
    point = jnp.asarray([0.1, 0.2, 0.3])
    grads = eqx.filter_grad(lambda f: f.at_step(30).density(point, jnp.zeros(3)))(field)
    np.testing.assert_array_equal(grads.level_weights, 0.0)
    # A masked level contributes nothing: changing its planes leaves the density unchanged.
    early = field.at_step(0)
    changed = eqx.tree_at(lambda f: f.encoding.planes[2], early, early.encoding.planes[2] * 3.0)
    assert float(early.density(point, jnp.zeros(3))) == float(changed.density(point, jnp.zeros(3)))


def test_grid_config_is_checked(tmp_path):
    config = mx.load_config("builtin_grid")
    assert config.model.field == "grid" and config.grid.encoding == "triplane"
    with pytest.raises(ConfigError, match="grid.max_resolution"):
        mx.load_config("builtin_grid", ["grid.min_resolution=64", "grid.max_resolution=32"])
    with pytest.raises(ConfigError, match="grid.encoding"):
        mx.load_config("builtin_grid", ["grid.encoding=octree"])
    unbounded = mx.load_config("builtin_grid", ["grid.box_radius=0"])
    with pytest.raises(ValueError, match="scene_box"):
        mx.build_model(unbounded, key=jax.random.key(0))


@pytest.fixture
def tiny_grid_config(tmp_path):
    config = mx.load_config("builtin_grid", [*TINY_SHARED_OVERRIDES, *GRID_OVERRIDES])
    return dataclasses.replace(config, train=dataclasses.replace(config.train, run_dir=str(tmp_path / "run")))


def test_short_grid_run_learns_and_renders_with_skipping(tiny_grid_config, tiny_scene):
    # The threshold's choice (most of a final report's time here) is tested with the MLP
    # field in test_occupancy.py; this test is about the grid field behind the occupancy grid.
    config = replace_setting(
        tiny_grid_config, "occupancy", enabled=True, resolution=32, choose_threshold=False
    )
    result = mx.fit(config, dataset=tiny_scene, progress=False, write_renders=False, log_every=10)
    losses = [entry["mse_fine"] for entry in result.history]
    assert np.mean(losses[-3:]) < 0.5 * np.mean(losses[:2])
    test_images = tiny_scene.test.images
    constant = np.mean([psnr(np.broadcast_to(img.mean(axis=(0, 1)), img.shape), img) for img in test_images])
    assert result.metrics["test"]["psnr"] > constant + 3.0, (result.metrics["test"], constant)
    # The trained field behind the occupancy grid: a render that skips nothing equals the dense
    # one, and the restored run is the trained one.
    run = mx.runs.restore_run(result.run_dir)
    assert isinstance(run.model.field, GridField)
    rays = mx.nn.camera_rays(tiny_scene.test.camtoworlds[:1], tiny_scene.test.focal * 12 / 32, 12, 12, 2.0, 6.0)
    rays = rays.reshape(-1)
    dense = render_rays(run.model, rays, 64)
    sparse = render_rays(run.model, rays, 64, skipping=Skipping(None, 0.0, 3, min_bucket=64))
    np.testing.assert_allclose(dense.rgb, sparse.rgb, atol=2e-6)
    trained = render_rays(result.model, rays, 64)
    np.testing.assert_array_equal(dense.rgb, trained.rgb)


def test_the_quick_starts_settings_reach_its_baseline():
    """The quick start's schedule, priors and frustum sampling apply to its baseline too (a fair
    comparison), and a field built from either samples the frustum's mean only."""
    configs = [mx.load_config(name) for name in ("builtin_grid", "builtin_mipnerf_grid")]
    weights = [LossWeights.from_config(config.loss, config.method) for config in configs]
    # Chosen on validation views: 1,800 steps, the levels revealed over half, no entropy prior.
    assert [w["opacity_entropy"] for w in weights] == [0.0, 0.0]
    assert [(c.train.max_steps, c.grid.coarse_to_fine_steps, c.grid.tv_weight) for c in configs] == [
        (1800, 900, 0.5)
    ] * 2
    assert not weights[1].uses_mixture  # the baseline: no mixture term, the same priors
    for config in configs:
        assert mx.build_model(config, key=jax.random.key(0)).field.scale_weighting is False


@pytest.mark.parametrize("lookup", ["vmap", "batched"])
def test_the_batched_density_is_the_density_of_each_point(lookup):
    config = mx.load_config("builtin_grid", [f'grid.lookup="{lookup}"'])
    model = mx.build_model(config, key=jax.random.key(0))
    field = model.field
    means = jax.random.uniform(jax.random.key(1), (37, 3), minval=-1.5, maxval=1.5)
    covs = jnp.full((37, 3), 1e-3)
    one_by_one = np.asarray([float(field.density(m, c)) for m, c in zip(means, covs, strict=True)])
    np.testing.assert_allclose(np.asarray(field.density_batch(means, covs)), one_by_one, rtol=1e-5, atol=1e-7)
