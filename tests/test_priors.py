"""The priors on unseen views (RegNeRF's depth smoothness, the opacity entropy): cameras, patches, terms.

References: a hand-written sum of squared neighbour differences in float64, the geometry of
the orbit (distance and elevation of the training cameras), and the full-image rays of the
same camera for the patches.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx._inference.camera_path import orbit_centre
from mixnerf_eqx._nn.model import RenderOutputs
from mixnerf_eqx._nn.renderer import LevelOutputs
from mixnerf_eqx._train.loss import depth_smoothness
from mixnerf_eqx._train.state import (
    draw_batch,
    init_train_state,
    make_train_step,
    training_rays,
    unseen_cameras,
    unseen_patches,
)

SMOOTH = ["loss.depth_smoothness_weight=2.0", "loss.smoothness_patches=2", "loss.smoothness_patch_size=4"]


def _level_with_depth(depth):
    count = depth.shape[0]
    return LevelOutputs(
        weights=jnp.zeros((count, 2)),
        t_edges=jnp.zeros((count, 3)),
        field=mx.nn.FieldOutputs(
            density=jnp.zeros((count, 2)), rgb=jnp.zeros((count, 2, 3)), beta=None, ray_depth=None
        ),
        rgb=jnp.zeros((count, 3)),
        depth=jnp.asarray(depth, jnp.float32),
        acc=jnp.zeros(count),
    )


def _rays(count, near, far):
    return mx.nn.RayBundle(
        origins=jnp.zeros((count, 3)),
        directions=jnp.tile(jnp.asarray([[0.0, 0.0, -1.0]]), (count, 1)),
        viewdirs=jnp.tile(jnp.asarray([[0.0, 0.0, -1.0]]), (count, 1)),
        radii=jnp.full((count, 1), 1e-3),
        near=jnp.full((count, 1), near),
        far=jnp.full((count, 1), far),
    )


def test_depth_smoothness_is_the_sum_of_squared_neighbour_differences():
    rng = np.random.default_rng(0)
    size, patches, near, far = 4, 3, 2.0, 6.0
    coarse = rng.uniform(near, far, (patches, size, size))
    fine = rng.uniform(near, far, (patches, size, size))
    outputs = RenderOutputs(
        coarse=_level_with_depth(coarse.reshape(-1)), fine=_level_with_depth(fine.reshape(-1))
    )
    got = float(depth_smoothness(outputs, _rays(patches * size * size, near, far), size))

    def reference(depth):
        s = (np.asarray(depth, np.float64) - near) / (far - near)
        total = 0.0
        for patch in s:
            for i in range(size):
                for j in range(size):
                    if i + 1 < size:
                        total += (patch[i + 1, j] - patch[i, j]) ** 2
                    if j + 1 < size:
                        total += (patch[i, j + 1] - patch[i, j]) ** 2
        return total / len(s)

    assert got == pytest.approx(reference(coarse) + reference(fine), rel=1e-5)


def test_a_plane_tilted_along_rows_costs_its_slope_squared_per_pair():
    # Depth rising by g per row and constant along rows: (size - 1) * size pairs of g^2.
    size, near, far, g = 5, 2.0, 6.0, 0.2
    depth = near + g * np.arange(size)[:, None] * np.ones((1, size))
    level = _level_with_depth(depth.reshape(-1))
    got = float(
        depth_smoothness(RenderOutputs(coarse=level, fine=level), _rays(size * size, near, far), size)
    )
    assert got == pytest.approx(2 * (size - 1) * size * (g / (far - near)) ** 2, rel=1e-5)


@pytest.fixture(scope="module")
def smooth_setup():
    config = mx.load_config("builtin", [*TINY_OVERRIDES, *SMOOTH])
    return config, mx.data.load_dataset(config.data)


def test_unseen_cameras_orbit_the_training_cameras_and_look_at_their_centre(smooth_setup):
    _, dataset = smooth_setup
    train = np.asarray(dataset.train.camtoworlds, np.float64)
    cameras = unseen_cameras(dataset, 16).astype(np.float64)
    centre = orbit_centre(train)
    distances = np.linalg.norm(cameras[:, :, 3] - centre, axis=-1)
    np.testing.assert_allclose(distances, np.linalg.norm(train[:, :, 3] - centre, axis=-1).mean(), rtol=1e-5)
    # Each camera's -z axis points at the centre.
    to_centre = (centre - cameras[:, :, 3]) / distances[:, None]
    np.testing.assert_allclose(np.sum(-cameras[:, :, 2] * to_centre, axis=-1), 1.0, atol=1e-5)
    # The test cameras do not enter: replacing them changes nothing.
    other = dataclasses.replace(dataset, test=dataset.train)
    np.testing.assert_array_equal(unseen_cameras(other, 16), unseen_cameras(dataset, 16))


def test_the_patches_are_pieces_of_their_cameras_images(smooth_setup):
    _, dataset = smooth_setup
    size, per_view = 4, 3
    pool = unseen_patches(dataset, 2, size, patches_per_view=per_view, seed=1)
    assert pool.batch_shape == (2 * per_view, size, size)
    train = dataset.train
    for view, pose in enumerate(unseen_cameras(dataset, 2)):
        full = mx.nn.camera_rays(pose[None], train.focal, train.height, train.width, dataset.near, dataset.far)
        pixels = np.asarray(full.directions[0]).reshape(-1, 3)
        for patch in range(per_view):
            directions = np.asarray(pool.directions[view * per_view + patch])
            # Find the patch's top-left pixel in the full image, then compare the whole patch.
            corner = np.flatnonzero(np.all(np.isclose(pixels, directions[0, 0], atol=1e-7), axis=-1))
            assert corner.size == 1
            row, col = divmod(int(corner[0]), train.width)
            expected = np.asarray(full.directions[0, row : row + size, col : col + size])
            np.testing.assert_allclose(directions, expected, atol=1e-7)


def test_a_patch_larger_than_the_images_is_refused(smooth_setup):
    _, dataset = smooth_setup
    with pytest.raises(ValueError, match="smoothness_patch_size"):
        unseen_patches(dataset, 2, dataset.train.height + 1)


def test_a_step_with_the_prior_draws_patches_and_reports_the_term(smooth_setup):
    config, dataset = smooth_setup
    data = training_rays(dataset, config.loss)
    state = init_train_state(config, dataset)
    batch = draw_batch(data, state, 32)
    assert batch.patches is not None and batch.patches.batch_shape == (2 * 4 * 4,)
    step = make_train_step(config)
    new_state, metrics = step(state, batch)
    assert float(metrics.terms["smoothness"]) > 0
    assert np.isfinite(float(metrics.terms.total)) and not bool(metrics.skipped)
    # The prior enters the total with its weight: the total less every other weighted term
    # (the objective of test_loss.py) is the smoothness term.
    terms, weights = metrics.terms, config.loss
    others = (
        3 * (terms["mse_fine"] + weights.coarse_mse_weight * terms["mse_coarse"])
        + metrics.lambda_colour * terms["nll_colour"]
        + weights.lambda_depth * terms["nll_depth"]
        + weights.lambda_regen * terms["nll_regen"]
    )
    smoothness = weights.depth_smoothness_weight * float(terms["smoothness"])
    assert float(terms.total - others) == pytest.approx(smoothness, rel=1e-3), float(terms.total)
    assert int(new_state.step) == 1
    # Without the prior no patches are drawn.
    assert draw_batch(training_rays(dataset), state, 32).patches is None


def test_the_unseen_entropy_alone_draws_patches_and_enters_with_its_weight():
    """`loss.unseen_entropy_weight` without the smoothness prior: the patches are drawn and
    rendered, and the total is the objective plus the weighted binary entropy of their opacities."""
    overrides = [
        "loss.unseen_entropy_weight=0.5",
        "loss.smoothness_patches=2",
        "loss.smoothness_patch_size=4",
    ]
    config = mx.load_config("builtin", [*TINY_OVERRIDES, *overrides])
    dataset = mx.data.load_dataset(config.data)
    data = training_rays(dataset, config.loss)
    state = init_train_state(config, dataset)
    batch = draw_batch(data, state, 32)
    assert batch.patches is not None and batch.patches.batch_shape == (2 * 4 * 4,)
    _, metrics = make_train_step(config)(state, batch)
    terms, weights = metrics.terms, config.loss
    # Each level's mean entropy lies in (0, log 2]; the smoothness term is not computed.
    assert 0 < float(terms["unseen_entropy"]) <= 2 * np.log(2.0) + 1e-6
    assert float(terms["smoothness"]) == 0.0 and float(terms["opacity_entropy"]) == 0.0
    others = (
        3 * (terms["mse_fine"] + weights.coarse_mse_weight * terms["mse_coarse"])
        + metrics.lambda_colour * terms["nll_colour"]
        + weights.lambda_depth * terms["nll_depth"]
        + weights.lambda_regen * terms["nll_regen"]
    )
    expected = 0.5 * float(terms["unseen_entropy"])
    assert float(terms.total - others) == pytest.approx(expected, rel=1e-3), float(terms.total)
