"""The occupancy grid and the renderer that skips empty space and finished rays.

References: a sphere of known density whose occupied cells and renders follow from geometry,
numpy re-implementations of the cell lookup, and the dense renderer.
"""

import dataclasses
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, Float

import mixnerf_eqx as mx
from mixnerf_eqx import ConfigError, fit
from mixnerf_eqx._inference.occupancy import (
    empty_grid,
    frustum_box,
    refresh_occupancy,
    update_occupancy,
)
from mixnerf_eqx._inference.skipping import _render_level, _sample_coarse
from mixnerf_eqx._inference.threshold import psnr_drop, psnr_drop_bound
from mixnerf_eqx.inference import Skipping, render_rays
from mixnerf_eqx.metrics import psnr


class SphereField(mx.nn.AbstractField):
    """Density `inside` in a ball, zero outside; a colour that varies with position."""

    centre: Float[Array, "3"]
    inside: Float[Array, ""]
    radius: float = eqx.field(static=True)

    @property
    def has_mixture_heads(self) -> bool:
        return False

    def density(self, mean, cov):
        del cov
        return jnp.where(jnp.linalg.norm(mean - self.centre) < self.radius, self.inside, 0.0)

    def __call__(self, mean, cov, viewdir, *, key=None):
        del key
        rgb = 0.5 + 0.4 * jnp.sin(3.0 * mean + viewdir)
        return mx.nn.FieldOutputs(density=self.density(mean, cov), rgb=rgb, beta=None, ray_depth=None)

    def density_batch(self, means, covs):
        return mx.nn.vmap_density(self, means, covs)

    def evaluate_batch(self, means, covs, viewdirs, keys=None):
        return mx.nn.vmap_field(self, means, covs, viewdirs, keys)

    def regulariser(self):
        return jnp.zeros(())

    def at_step(self, step):
        return self


def _sphere(inside=20.0, radius=0.6):
    return SphereField(centre=jnp.array([0.1, -0.05, 0.0]), inside=jnp.asarray(inside), radius=radius)


def _sphere_model(field, samples=64):
    return mx.MixNeRF(
        field=field,
        coarse_sampler=mx.nn.StratifiedSampler(samples),
        fine_sampler=mx.nn.HierarchicalSampler(samples),
        renderer=mx.nn.VolumeRenderer((1.0, 1.0, 1.0)),
        mixture=None,
    )


def _camera_rays(size=32, distance=4.0, zoom=1.2):
    """A camera on the +z axis looking at the origin, near 2, far 6 (focal `zoom * size`)."""
    pose = np.array([[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, distance]]], np.float32)
    return mx.nn.camera_rays(pose, zoom * size, size, size, 2.0, 6.0).reshape(-1)


def _cell_centres(grid):
    res = grid.resolution
    cell = np.asarray(grid.cell_size, np.float64)
    index = np.stack(np.meshgrid(*(np.arange(res),) * 3, indexing="ij"), axis=-1)
    return np.asarray(grid.box_min, np.float64) + (index + 0.5) * cell, cell


def test_refreshed_grid_marks_exactly_the_cells_the_sphere_decides():
    field = _sphere()
    grid = empty_grid((-1.5,) * 3, (1.5,) * 3, resolution=24, threshold=1.0, dilation=0)
    grid = refresh_occupancy(grid, field, key=jax.random.key(0))
    centres, cell = _cell_centres(grid)
    distance = np.linalg.norm(centres - np.asarray(field.centre, np.float64), axis=-1)
    half_diagonal = 0.5 * np.linalg.norm(cell)
    mask = np.asarray(grid.mask())
    # A cell wholly inside the ball is occupied wherever its random point falls; one wholly
    # outside is empty. Cells the surface cuts may go either way.
    inside = distance < field.radius - half_diagonal
    outside = distance > field.radius + half_diagonal
    assert inside.sum() > 20 and outside.sum() > 1000
    assert mask[inside].all()
    assert not mask[outside].any()
    assert not np.isinf(np.asarray(grid.density)).any()


def test_dilation_marks_the_neighbours_of_occupied_cells():
    density = np.zeros((9, 9, 9), np.float32)
    density[4, 4, 4] = 1.0
    density[0, 8, 0] = 1.0
    grid = mx.inference.OccupancyGrid(
        density=jnp.asarray(density),
        box_min=jnp.zeros(3),
        box_max=jnp.ones(3),
        threshold=jnp.asarray(0.5),
        dilation=1,
        outside_occupied=False,
    )
    expected = np.zeros((9, 9, 9), bool)
    expected[3:6, 3:6, 3:6] = True
    expected[0:2, 7:9, 0:2] = True
    np.testing.assert_array_equal(np.asarray(grid.mask()), expected)


@pytest.mark.parametrize("outside_occupied", [False, True])
def test_lookup_matches_a_numpy_reference(outside_occupied):
    rng = np.random.default_rng(0)
    mask = rng.uniform(size=(7, 7, 7)) < 0.4
    box_min, box_max = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 3.0, 2.5])
    grid = mx.inference.OccupancyGrid(
        density=jnp.asarray(mask.astype(np.float32)),
        box_min=jnp.asarray(box_min, jnp.float32),
        box_max=jnp.asarray(box_max, jnp.float32),
        threshold=jnp.asarray(0.5),
        dilation=0,
        outside_occupied=outside_occupied,
    )
    points = rng.uniform(box_min - 0.3, box_max + 0.3, size=(5000, 3)).astype(np.float32)
    cells = np.floor((points - box_min) / ((box_max - box_min) / 7)).astype(int)
    inside = np.all((cells >= 0) & (cells < 7), axis=-1)
    clipped = np.clip(cells, 0, 6)
    expected = np.where(inside, mask[clipped[:, 0], clipped[:, 1], clipped[:, 2]], outside_occupied)
    # Points within float32 rounding of a cell wall may land on either side.
    scaled = (points - box_min) / ((box_max - box_min) / 7)
    clear = np.all(np.abs(scaled - np.round(scaled)) > 1e-4, axis=-1)
    got = np.asarray(grid.occupied(jnp.asarray(points)))
    assert (~inside).sum() > 500
    np.testing.assert_array_equal(got[clear], expected[clear])


def test_partial_updates_visit_every_cell_once_per_cycle():
    field = _sphere()
    grid = empty_grid((-1.0,) * 3, (1.0,) * 3, resolution=10, dilation=0)
    unevaluated = []
    for offset in range(4):
        grid = update_occupancy(grid, field, key=jax.random.key(offset), fraction=0.25, offset=offset)
        unevaluated.append(int(np.isinf(np.asarray(grid.density)).sum()))
    assert unevaluated == [750, 500, 250, 0]


def test_updates_keep_the_decayed_maximum():
    ball = SphereField(centre=jnp.zeros(3), inside=jnp.asarray(8.0), radius=100.0)
    grid = refresh_occupancy(empty_grid((-1.0,) * 3, (1.0,) * 3, resolution=4), ball, key=jax.random.key(0))
    np.testing.assert_allclose(np.asarray(grid.density), 8.0)
    weaker = eqx.tree_at(lambda f: f.inside, ball, jnp.asarray(1.0))
    decayed = update_occupancy(grid, weaker, key=jax.random.key(1), decay=0.5)
    np.testing.assert_allclose(np.asarray(decayed.density), 4.0)
    stronger = eqx.tree_at(lambda f: f.inside, ball, jnp.asarray(6.0))
    raised = update_occupancy(decayed, stronger, key=jax.random.key(2), decay=0.5)
    np.testing.assert_allclose(np.asarray(raised.density), 6.0)
    replaced = refresh_occupancy(raised, weaker, key=jax.random.key(3))
    np.testing.assert_allclose(np.asarray(replaced.density), 1.0)


def test_every_evaluated_cell_decays_at_each_update_visited_or_not():
    # A quarter of the cells visited per update; the rest still decay, so that density the
    # field has lost leaves the grid within a few updates (not only when a cell is revisited).
    ball = SphereField(centre=jnp.zeros(3), inside=jnp.asarray(8.0), radius=100.0)
    grid = refresh_occupancy(empty_grid((-1.0,) * 3, (1.0,) * 3, resolution=4), ball, key=jax.random.key(0))
    empty = eqx.tree_at(lambda f: f.inside, ball, jnp.asarray(0.0))
    expected = np.full(64, 8.0)
    for update in range(3):
        grid = update_occupancy(grid, empty, key=jax.random.key(update + 1), decay=0.5, fraction=0.25, offset=update)
        expected = 0.5 * expected
        expected[update::4] = np.maximum(expected[update::4], 0.0)
        np.testing.assert_allclose(np.asarray(grid.density).reshape(-1), expected)
    assert float(np.max(np.asarray(grid.density))) == 1.0  # 8 halved three times
    # Cells never evaluated stay unevaluated (inf), however many updates pass.
    fresh = update_occupancy(empty_grid((-1.0,) * 3, (1.0,) * 3, resolution=4), empty, key=jax.random.key(9), decay=0.5, fraction=0.25)
    assert int(np.isinf(np.asarray(fresh.density)).sum()) == 48


def test_frustum_box_holds_every_sample_and_ndc_depth_spans_minus_one_to_one():
    rng = np.random.default_rng(1)
    poses = np.concatenate([np.eye(3)[None].repeat(3, 0), rng.normal(0, 0.2, (3, 3, 1))], axis=-1)
    rays = mx.nn.camera_rays(poses.astype(np.float32), 20.0, 16, 24, 2.0, 6.0)
    low, high = frustum_box(rays)
    t = np.linspace(2.0, 6.0, 17)
    flat = rays.reshape(-1)
    points = np.asarray(flat.origins)[:, None] + np.asarray(flat.directions)[:, None] * t[:, None]
    assert np.all(points >= low) and np.all(points <= high)
    ndc = mx.nn.camera_rays(poses.astype(np.float32), 20.0, 16, 24, 0.0, 1.0, ndc=True)
    low, high = frustum_box(ndc)
    np.testing.assert_allclose([low[2], high[2]], [-1.02, 1.02], atol=1e-4)


@pytest.mark.parametrize("chunk", [None, 64])
def test_skipping_nothing_equals_the_dense_render(tiny_config, chunk):
    model = mx.build_model(tiny_config, key=jax.random.key(0))
    rays = _camera_rays(size=12)
    dense = render_rays(model, rays, 100)
    sparse = render_rays(model, rays, 100, skipping=Skipping(None, 0.0, 3, min_bucket=64, chunk=chunk))
    for name in ("rgb", "depth", "acc"):
        np.testing.assert_allclose(getattr(dense, name), getattr(sparse, name), atol=2e-6)
    counts = sparse.counts
    assert counts.rays == 144 and counts.field_evaluations == counts.dense_evaluations == 144 * 32


class TintedRenderer(mx.nn.AbstractRenderer):
    """A different renderer: the volume renderer over a grey background, colours tinted.

    Swapped into a model, both the dense and the skipping render must follow it."""

    inner: mx.nn.VolumeRenderer
    tint: Float[Array, "3"]

    def __call__(self, outputs, t_edges, ray):
        level = self.inner(outputs, t_edges, ray)
        return eqx.tree_at(lambda lv: lv.rgb, level, level.rgb * self.tint)


def test_swapped_renderer_and_sampler_are_followed_by_the_skipping_render(tiny_config):
    model = mx.build_model(tiny_config, key=jax.random.key(0))
    rays = _camera_rays(size=10)
    tinted = TintedRenderer(mx.nn.VolumeRenderer((0.5, 0.5, 0.5)), jnp.array([1.0, 0.5, 0.25]))
    swapped = eqx.tree_at(lambda m: m.renderer, model, tinted)
    swapped = eqx.tree_at(lambda m: m.coarse_sampler, swapped, mx.nn.StratifiedSampler(24, "cone", lindisp=True))
    nothing_skipped = Skipping(None, 0.0, 3, min_bucket=64)
    dense = render_rays(swapped, rays, 100)
    sparse = render_rays(swapped, rays, 100, skipping=nothing_skipped)
    for name in ("rgb", "depth", "acc"):
        np.testing.assert_allclose(getattr(dense, name), getattr(sparse, name), atol=2e-6)
    # The swap changed the image (so the agreement above is about the swapped parts).
    original = render_rays(model, rays, 100)
    assert np.max(np.abs(original.rgb - dense.rgb)) > 0.05
    assert sparse.counts.dense_evaluations == 100 * (24 + 16)


def test_grid_threshold_is_an_array_leaf():
    grid = empty_grid((-1.0,) * 3, (1.0,) * 3, resolution=4, threshold=0.5)
    leaves = jax.tree_util.tree_leaves(grid)
    assert any(leaf is grid.threshold for leaf in leaves)
    raised = grid.with_threshold(2.0)
    assert float(raised.threshold) == 2.0
    # Same structure: a render compiled for one threshold serves every other.
    assert jax.tree_util.tree_structure(raised) == jax.tree_util.tree_structure(grid)


def test_stopping_finished_rays_changes_a_level_by_at_most_the_threshold():
    model = _sphere_model(_sphere(inside=5.0))
    rays = _camera_rays(size=16, zoom=5.0)  # the sphere fills the frame
    samples = _sample_coarse(model, rays)
    valid = jnp.ones(rays.batch_shape, bool)
    dense, _ = _render_level(model, rays, samples, valid, Skipping(None, 0.0, 1))
    stop = 0.05
    cut, counts = _render_level(model, rays, samples, valid, Skipping(None, stop, 16, min_bucket=16))
    # The dropped samples come after transmittance fell below `stop`, so their weights sum to
    # less than it, and each moves the colour by at most |c - background| <= 1 per unit weight.
    assert float(jnp.max(jnp.abs(cut.acc - dense.acc))) <= stop
    assert float(jnp.max(jnp.abs(cut.rgb - dense.rgb))) <= stop
    assert counts.field_evaluations < 0.8 * 256 * 64


@pytest.mark.parametrize("chunk", [None, 256])
def test_skipping_renders_the_sphere_within_a_tenth_of_a_db_with_a_third_of_the_work(chunk):
    field = _sphere()
    model = _sphere_model(field)
    rays = _camera_rays(size=40)
    grid = empty_grid((-1.5,) * 3, (1.5,) * 3, resolution=48, threshold=0.01, outside_occupied=False)
    grid = refresh_occupancy(grid, field, key=jax.random.key(0))
    dense = render_rays(model, rays, 512)
    dense_rgb, dense_depth = dense.rgb, dense.depth
    skipped = render_rays(model, rays, 512, skipping=Skipping(grid, 1e-4, 4, chunk=chunk))
    rgb, depth, counts = skipped.rgb, skipped.depth, skipped.counts
    # The dense render is the reference image: the PSNR of the skipped render against it must
    # be high enough that a 0.1 dB change of any test PSNR below 40 dB is impossible.
    assert psnr(rgb.reshape(40, 40, 3), dense_rgb.reshape(40, 40, 3)) > 60.0
    hit = np.isfinite(dense_depth) & (np.asarray(dense_depth) < 5.5)
    assert hit.sum() > 100
    np.testing.assert_allclose(depth[hit], dense_depth[hit], atol=2e-3)
    assert counts.padded_evaluations * 3 <= counts.dense_evaluations


def _assert_same_parameters(a, b):
    """Every array leaf of two models equal, bit for bit."""
    leaves = [jax.tree_util.tree_leaves(eqx.filter(m, eqx.is_array)) for m in (a, b)]
    for x, y in zip(*leaves, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_training_with_a_grid_trains_the_same_parameters_and_reports_render_cost(tiny_config, tiny_scene):
    steps = dict(max_steps=20, eval_every=0)
    plain = dataclasses.replace(tiny_config, train=dataclasses.replace(tiny_config.train, **steps))
    with_grid = dataclasses.replace(
        plain,
        occupancy=dataclasses.replace(plain.occupancy, enabled=True, resolution=16, update_every=5),
        train=dataclasses.replace(plain.train, run_dir=plain.train.run_dir + "_grid"),
    )
    a = fit(plain, dataset=tiny_scene, progress=False, write_renders=False)
    b = fit(with_grid, dataset=tiny_scene, progress=False, write_renders=False)
    _assert_same_parameters(a.model, b.model)
    render = b.metrics["render"]
    assert render["skipping"] and 0 <= render["occupied_fraction"] <= 1
    pixels = tiny_scene.test.height * tiny_scene.test.width
    assert render["dense_evaluations_per_frame"] == pixels * 32
    assert 0 < render["needed_evaluations_per_frame"] <= render["dense_evaluations_per_frame"]
    assert a.metrics["render"]["evaluation_reduction"] <= 1.0
    # The threshold keeps the PSNR lost on validation pixels within 0.1 dB; on the test views
    # that is an estimate, which this deterministic run holds to.
    assert abs(b.metrics["test"]["psnr"] - a.metrics["test"]["psnr"]) < 0.1
    # The threshold was chosen on validation pixels (the tiny scene has them) and within its
    # tolerance there.
    choice = render["threshold_choice"]
    assert tiny_scene.val is not None and choice["views"] == "val"
    assert choice["trials"] and choice["tolerance_db"] == 0.1
    assert render["density_threshold"] == choice["threshold"]
    # By the PSNR lost there (the default measure on validation pixels), not by the bound.
    assert choice["measure"] == "psnr"
    assert choice["within_tolerance"] == (choice["psnr_drop_db"] <= 0.1)
    kept = [t for t in choice["trials"] if t["threshold"] == choice["threshold"]]
    assert choice["threshold"] == 0.0 or kept[0]["psnr_drop_db"] == choice["psnr_drop_db"]
    # `render_skipping` alone: training keeps no grid (and trains the same parameters), and the
    # final evaluation skips with a grid built from the trained model, its threshold chosen
    # the same way.
    rendering_only = dataclasses.replace(
        plain,
        occupancy=dataclasses.replace(plain.occupancy, render_skipping=True, resolution=16),
        train=dataclasses.replace(plain.train, run_dir=plain.train.run_dir + "_render"),
    )
    c = fit(rendering_only, dataset=tiny_scene, progress=False, write_renders=False)
    assert c.state.grid is None
    _assert_same_parameters(a.model, c.model)
    render = c.metrics["render"]
    assert render["skipping"] and render["threshold_choice"]["views"] == "val"
    assert 0 < render["needed_evaluations_per_frame"] <= render["dense_evaluations_per_frame"]
    assert abs(c.metrics["test"]["psnr"] - a.metrics["test"]["psnr"]) < 0.1
    assert render["grid_seconds"] > 0 and b.metrics["render"]["grid_seconds"] > 0
    assert a.metrics["render"]["grid_seconds"] == 0 and not a.metrics["render"]["skipping"]
    # `eval --skipping auto` (the default) of that run skips too, with a grid of its own.
    from mixnerf_eqx.cli.eval import main as eval_main

    out = Path(rendering_only.train.run_dir) / "eval_auto"
    flags = ["--no-lpips", "--no-renders", "--no-progress", "--out", str(out)]
    assert eval_main([rendering_only.train.run_dir, *flags]) == 0
    written = json.loads((out / "metrics.json").read_text())["render"]
    assert written["skipping"] and written["grid_seconds"] > 0


@pytest.mark.parametrize(
    "override, message",
    [
        ("occupancy.resolution=1", "occupancy.resolution"),
        ("occupancy.decay=1.5", "occupancy.decay"),
        ("occupancy.update_fraction=0", "occupancy.update_fraction"),
        ("occupancy.stop_transmittance=1", "occupancy.stop_transmittance"),
        ("occupancy.grid_size=3", "unknown key 'grid_size'"),
        ("occupancy.density_threshold=0", "occupancy.choose_threshold needs"),
        ("occupancy.threshold_rays=0", "occupancy.threshold_rays"),
        ("occupancy.threshold_tolerance_db=-1", "occupancy.threshold_tolerance_db"),
        ('occupancy.threshold_views="test"', "occupancy.threshold_views"),
    ],
)
def test_bad_occupancy_settings_are_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        mx.load_config(None, [override])


# --- Calibrating the density threshold -------------------------------------------------


def _psnr64(a, b):
    return -10 * np.log10(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def test_psnr_drop_bound_bounds_the_drop_and_is_tight_along_the_error():
    rng = np.random.default_rng(0)
    for _ in range(200):
        target = rng.uniform(size=(50, 3))
        dense = np.clip(target + rng.normal(scale=rng.uniform(0.01, 0.2), size=target.shape), 0, 1)
        skipped = dense + rng.normal(scale=rng.uniform(1e-4, 0.1), size=target.shape)
        drop = _psnr64(dense, target) - _psnr64(skipped, target)
        assert drop <= psnr_drop_bound(dense, skipped, target) + 1e-9
    # A change along the error, skipped = dense + c (dense - target), loses exactly 20 log10(1 + c).
    target = rng.uniform(size=(50, 3))
    dense = target + 0.05 * rng.normal(size=target.shape)
    for c in (0.01, 0.3, 2.0):
        skipped = dense + c * (dense - target)
        expected = 20 * np.log10(1 + c)
        assert psnr_drop_bound(dense, skipped, target) == pytest.approx(expected, rel=1e-9)
        assert _psnr64(dense, target) - _psnr64(skipped, target) == pytest.approx(expected, rel=1e-9)
    assert psnr_drop_bound(dense, dense, target) == 0.0
    assert psnr_drop_bound(target, dense, target) == np.inf


def test_psnr_drop_is_the_measured_loss_and_never_above_its_bound():
    rng = np.random.default_rng(1)
    for _ in range(100):
        target = rng.uniform(size=(40, 3))
        dense = target + rng.normal(scale=rng.uniform(0.01, 0.2), size=target.shape)
        skipped = dense + rng.normal(scale=rng.uniform(1e-4, 0.1), size=target.shape)
        drop = psnr_drop(dense, skipped, target)
        assert drop == pytest.approx(_psnr64(dense, target) - _psnr64(skipped, target), rel=1e-9, abs=1e-12)
        assert drop <= psnr_drop_bound(dense, skipped, target) + 1e-9
    # A render closer to the target than the dense one gains: a negative loss.
    target = rng.uniform(size=(40, 3))
    dense = target + 0.1
    assert psnr_drop(dense, target + 0.05, target) == pytest.approx(-20 * np.log10(2.0), rel=1e-9)
    assert psnr_drop(dense, dense, target) == 0.0
    assert psnr_drop(target, dense, target) == np.inf and psnr_drop(dense, target, target) == -np.inf


class FoggySphereField(SphereField):
    """The sphere inside a uniform fog of density `fog` (in the whole box)."""

    fog: float = eqx.field(static=True, default=0.02)

    def density(self, mean, cov):
        inside_box = jnp.all(jnp.abs(mean) < 1.5)
        return jnp.where(inside_box, jnp.maximum(super().density(mean, cov), self.fog), 0.0)


def _choose_for_foggy_sphere(tolerance_db, measure="bound"):
    foggy = FoggySphereField(centre=jnp.array([0.1, -0.05, 0.0]), inside=jnp.asarray(20.0), radius=0.6)
    model = _sphere_model(foggy, samples=48)
    rays = _camera_rays(size=24)
    # The truth has no fog: the dense render of the foggy model is off by the fog's colour.
    target = render_rays(_sphere_model(_sphere(), samples=48), rays, 576).rgb
    grid = empty_grid((-1.5,) * 3, (1.5,) * 3, resolution=32, threshold=1e-3, outside_occupied=False)
    grid = refresh_occupancy(grid, foggy, key=jax.random.key(0))
    skipping = Skipping(grid, 1e-4, 4)
    chosen, choice = mx.inference.choose_threshold(
        model, grid, skipping, rays, target, tolerance_db=tolerance_db, doublings=16, chunk=576, measure=measure
    )
    dense = render_rays(model, rays, 576).rgb

    def bound(threshold):
        candidate = grid.with_threshold(threshold)
        rgb = render_rays(model, rays, 576, skipping=dataclasses.replace(skipping, grid=candidate)).rgb
        return psnr_drop_bound(dense, rgb, target)

    return chosen, choice, bound


def test_the_threshold_choice_keeps_the_fog_for_a_tight_tolerance_and_picks_the_largest_threshold():
    chosen, choice, bound = _choose_for_foggy_sphere(tolerance_db=0.5)
    assert choice.within_tolerance and float(chosen.threshold) == pytest.approx(choice.threshold, rel=1e-7)
    # Removing the fog moves the image all the way to the truth: a 6 dB bound. So the chosen
    # threshold stays below the fog's density, and the next candidate up is above it.
    assert 0.01 < choice.threshold < 0.02 <= 2 * choice.threshold
    assert bound(choice.threshold) == pytest.approx(choice.bound_db, abs=1e-3)
    assert choice.bound_db <= 0.5 < bound(2 * choice.threshold)
    assert len(choice.trials) <= 6  # bisection over 17 candidates


def test_the_measured_loss_skips_the_fog_that_the_bound_keeps_but_not_the_sphere():
    # The truth has no fog, so removing it brings the image closer: no loss measured, while
    # the bound (above) counts the change as a possible loss and keeps the fog.
    chosen, choice, bound = _choose_for_foggy_sphere(tolerance_db=0.5, measure="psnr")
    assert choice.measure == "psnr" and choice.within_tolerance
    assert 0.02 <= choice.threshold < 20.0 and choice.psnr_drop_db < 0  # above the fog, below the sphere
    # The bound on the same render is far above the tolerance: the fog's removal is a change.
    assert choice.bound_db > 0.5
    assert choice.reduction > 2.0
    # Every candidate refused lost more than the tolerance; the next one up from the choice did.
    assert all(t.psnr_drop_db > 0.5 for t in choice.trials if t.threshold > choice.threshold)
    with pytest.raises(ValueError, match="measure"):
        _choose_for_foggy_sphere(tolerance_db=0.5, measure="mean")


def test_the_threshold_choice_skips_the_fog_but_not_the_sphere_for_a_loose_tolerance():
    chosen, choice, bound = _choose_for_foggy_sphere(tolerance_db=7.0)
    assert choice.within_tolerance
    assert 0.02 < choice.threshold < 20.0
    assert bound(choice.threshold) <= 7.0 < bound(32.0)  # skipping the sphere too
    assert choice.reduction > 2.0


@pytest.mark.parametrize("split", ["train", "val"])
def test_threshold_rays_are_distinct_pixels_of_the_split_asked_for(tiny_scene, split):
    rays, colours = mx.inference.threshold_rays(tiny_scene, 300, key=jax.random.key(3), split=split)
    views = tiny_scene.split(split)
    assert rays.batch_shape == (300,) and colours.shape == (300, 3)
    all_rays = mx.data.rays_for_views(views, tiny_scene.near, tiny_scene.far).reshape(-1)
    table = np.concatenate([np.asarray(all_rays.origins), np.asarray(all_rays.directions)], axis=-1)
    picked = np.concatenate([np.asarray(rays.origins), np.asarray(rays.directions)], axis=-1)
    index = [int(np.flatnonzero(np.all(table == row, axis=-1))[0]) for row in picked]
    assert len(set(index)) == 300
    np.testing.assert_array_equal(colours, np.asarray(views.images, np.float32).reshape(-1, 3)[index])
    with pytest.raises(ValueError, match="num_rays"):
        mx.inference.threshold_rays(tiny_scene, 0, key=jax.random.key(3), split=split)


def test_threshold_rays_never_come_from_the_test_views_and_need_validation_views_to_use_them(tiny_scene):
    with pytest.raises(ValueError, match='"train" or "val"'):
        mx.inference.threshold_rays(tiny_scene, 10, key=jax.random.key(0), split="test")
    no_val = dataclasses.replace(tiny_scene, val=None)
    with pytest.raises(ValueError, match="no validation views"):
        mx.inference.threshold_rays(no_val, 10, key=jax.random.key(0), split="val")


@pytest.mark.parametrize(
    "has_val, asked, asked_measure, used, used_measure",
    [
        (True, "val", "psnr", "val", "psnr"),
        (True, "val", "bound", "val", "bound"),
        # Training pixels, fitted closely, are held to the bound whatever is asked.
        (False, "val", "psnr", "train", "bound"),
        (True, "train", "psnr", "train", "bound"),
    ],
)
def test_the_threshold_is_chosen_on_the_views_asked_for_and_says_which(
    short_run, tiny_scene, has_val, asked, asked_measure, used, used_measure
):
    _, model = short_run
    dataset = tiny_scene if has_val else dataclasses.replace(tiny_scene, val=None)
    occupancy = dataclasses.replace(
        mx.load_config(None, []).occupancy,
        enabled=True,
        resolution=16,
        threshold_rays=256,
        threshold_views=asked,
        threshold_measure=asked_measure,
    )
    grid, choice = mx.runs.grid_for_rendering(occupancy, dataset, model, key=jax.random.key(1))
    assert choice.views == used and choice.measure == used_measure
    assert float(grid.threshold) == choice.threshold
    # The same choice as `choose_threshold` makes on those views' pixels, drawn with the same key.
    _, threshold_key = jax.random.split(jax.random.key(1))
    rays, colours = mx.inference.threshold_rays(dataset, 256, key=threshold_key, split=used)
    skipping = mx.runs.make_skipping(occupancy, grid)
    first = grid.with_threshold(occupancy.density_threshold)
    _, direct = mx.inference.choose_threshold(
        model, first, skipping, rays, colours, chunk=256, measure=used_measure
    )
    assert direct.threshold == choice.threshold
    assert direct.bound_db == pytest.approx(choice.bound_db, rel=1e-6)
    assert direct.psnr_drop_db == pytest.approx(choice.psnr_drop_db, rel=1e-6, abs=1e-9)
    assert [t.threshold for t in direct.trials] == [t.threshold for t in choice.trials]
