"""Tests of the LLFF loader on tiny scenes written here and on the real fern when present.

NDC references follow NeRF's appendix C formula, derived here in float64 from the world rays
of a pinhole camera (independently of `mixnerf_eqx._nn.rays`).

Images pair with the rows of `poses_bounds.npy` in plain sorted name order: LLFF's
`imgs2poses.py` stores the poses in the `np.argsort` order of the image names and the NeRF
loader lists the images with `sorted(os.listdir(...))`, so with unpadded numbers `img10` comes
before `img2`, and each image must keep the pose of its own row.
"""

import numpy as np
import pytest
from _writers import (
    FERN,
    block_average,
    block_centres,
    crop_offsets,
    random_pixels,
    truncate,
    write_llff,
    write_png,
)

from mixnerf_eqx.data import DatasetError, load_llff, rays_for_views
from mixnerf_eqx.data._splits import evenly_spaced, holdout_split
from mixnerf_eqx.data.llff import llff_poses


def _protocol_split(count, num_train):
    test = [i for i in range(count) if i % 8 == 0]
    remaining = [i for i in range(count) if i % 8 != 0]
    return [remaining[round(x)] for x in np.linspace(0, len(remaining) - 1, num_train)], test


def test_evenly_spaced_rounds_ties_to_even():
    # horns: 62 images, 54 left after the holdout; linspace(0, 53, 3) = 0, 26.5, 53.
    assert evenly_spaced(54, 3) == [0, 26, 53]
    # 17 left (fern): linspace(0, 16, 6) = 0, 3.2, 6.4, 9.6, 12.8, 16.
    assert evenly_spaced(17, 6) == [0, 3, 6, 10, 13, 16]


@pytest.mark.parametrize("count,num_train", [(20, 3), (20, 6), (20, 9), (62, 3), (34, 9)])
def test_holdout_split_matches_protocol(tmp_path, count, num_train):
    assert holdout_split(count, 8, num_train, tmp_path) == _protocol_split(count, num_train)


def _world_rays(camtoworlds, focal, height, width):
    """Float64 pinhole rays through pixel centres (OpenGL camera, z-depth directions)."""
    rows, cols = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    camera = np.stack([(cols - width / 2) / focal, -(rows - height / 2) / focal, -np.ones_like(cols)], -1)
    directions = np.einsum("vij,hwj->vhwi", camtoworlds[:, :3, :3], camera)
    origins = np.broadcast_to(camtoworlds[:, None, None, :, 3], directions.shape)
    return origins, directions


def _nerf_ndc(origins, directions, focal, height, width, near=1.0):
    """NeRF's `ndc_rays` (appendix C), float64."""
    t = -(near + origins[..., 2]) / directions[..., 2]
    o = origins + t[..., None] * directions
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = directions[..., 0], directions[..., 1], directions[..., 2]
    o_ndc = np.stack([-focal / (width / 2) * ox / oz, -focal / (height / 2) * oy / oz, 1 + 2 * near / oz], -1)
    d_ndc = np.stack(
        [
            -focal / (width / 2) * (dx / dz - ox / oz),
            -focal / (height / 2) * (dy / dz - oy / oz),
            -2 * near / oz,
        ],
        -1,
    )
    return o_ndc, d_ndc


def _check_ndc(views):
    rays = rays_for_views(views, 0.0, 1.0)
    camtoworlds = views.camtoworlds.astype(np.float64)
    origins, directions = _world_rays(camtoworlds, views.focal, views.height, views.width)
    o_ref, d_ref = _nerf_ndc(origins, directions, views.focal, views.height, views.width)
    np.testing.assert_allclose(np.asarray(rays.origins), o_ref, atol=2e-5)
    np.testing.assert_allclose(np.asarray(rays.directions), d_ref, atol=2e-5)
    np.testing.assert_array_equal(np.asarray(rays.origins)[..., 2], -1.0)
    np.testing.assert_allclose(np.asarray(rays.directions)[..., 2], 2.0, atol=1e-6)
    # View directions stay the world directions from before the NDC mapping, unnormalised
    # (camera depth 1), as in the released code.
    np.testing.assert_allclose(np.asarray(rays.viewdirs), directions, atol=1e-6)


def test_llff_poses_follow_nerf_loader(tmp_path):
    rows = write_llff(tmp_path / "scene")["rows"]
    camtoworlds, bounds, (height, width, focal) = llff_poses(rows, tmp_path / "poses_bounds.npy")
    assert (height, width, focal) == (48.0, 64.0, 40.0)
    scale = 1.0 / (0.75 * rows[:, 15:].min())
    np.testing.assert_allclose(bounds, rows[:, 15:] * scale, rtol=1e-12)
    assert bounds.min() == pytest.approx(1 / 0.75)
    llff = rows[:, :15].reshape(-1, 3, 5)
    # OpenGL axes: right = LLFF's second column, up = minus its first (down), backward = third.
    rotations = np.stack([llff[:, :, 1], -llff[:, :, 0], llff[:, :, 2]], axis=2)
    centres = scale * llff[:, :, 3]
    # The loaded cameras are one rigid motion of these (the recentring).
    change = camtoworlds[:, :, :3] @ np.transpose(rotations, (0, 2, 1))
    np.testing.assert_allclose(change, np.broadcast_to(change[0], change.shape), atol=1e-12)
    np.testing.assert_allclose(change[0] @ change[0].T, np.eye(3), atol=1e-12)
    shift = camtoworlds[:, :, 3] - centres @ change[0].T
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-12)
    # Recentred on the average pose: mean centre at the origin, summed backward axis along +z.
    np.testing.assert_allclose(camtoworlds[:, :, 3].mean(axis=0), 0.0, atol=1e-12)
    backward = camtoworlds[:, :, 2].sum(axis=0)
    np.testing.assert_allclose(backward / np.linalg.norm(backward), [0, 0, 1], atol=1e-12)


def test_load_llff_tiny(tmp_path):
    rows = write_llff(tmp_path / "scene")["rows"]
    dataset = load_llff(tmp_path / "scene", num_train_views=3)
    train, test = _protocol_split(20, 3)
    assert dataset.train.ids == tuple(train) == (1, 10, 19)
    assert dataset.test.ids == tuple(test) == (0, 8, 16)
    assert dataset.train.images.shape == (3, 6, 8, 3)
    assert dataset.train.focal == pytest.approx(40.0 / 8)
    assert (dataset.near, dataset.far, dataset.frustum, dataset.white_background) == (
        0.0,
        1.0,
        "cylinder",
        False,
    )
    assert dataset.train.ndc and dataset.test.ndc
    assert rows.shape == (20, 17)
    _check_ndc(dataset.train)


def test_unpadded_names_keep_their_poses(tmp_path):
    names = [f"img{i}.png" for i in range(1, 13)]
    written = write_llff(tmp_path, names=names)
    assert written["names"][:3] == ["img1.png", "img10.png", "img11.png"]
    dataset = load_llff(tmp_path, num_train_views=10)
    assert dataset.test.ids == (0, 8) and dataset.train.ids == (1, 2, 3, 4, 5, 6, 7, 9, 10, 11)
    for views in (dataset.train, dataset.test):
        for position, view in enumerate(views.ids):
            np.testing.assert_allclose(views.images[position], written["pixels"][view] / 255.0, atol=1e-6)
    # The poses are the rows in file order: the translations keep their order through the
    # rigid recentring, so compare pairwise distances, which it preserves (up to the scale).
    centres = written["rows"][:, :15].reshape(-1, 3, 5)[:, :, 3]
    loaded = np.concatenate([dataset.test.camtoworlds, dataset.train.camtoworlds])[:, :, 3].astype(np.float64)
    order = list(dataset.test.ids) + list(dataset.train.ids)
    true_distances = np.linalg.norm(centres[order][:, None] - centres[order][None], axis=-1)
    loaded_distances = np.linalg.norm(loaded[:, None] - loaded[None], axis=-1)
    scale = loaded_distances[0, 1] / true_distances[0, 1]
    np.testing.assert_allclose(loaded_distances, scale * true_distances, atol=1e-5)


# --- data.image_downscale ---------------------------------------------------------------------


def _unit(vectors):
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def _check_block_rays(small, full, factor, near=1.0):
    """The rays of `small` (`full` downscaled by `factor`) are the rays through the centres of
    their blocks in `full`: the same world directions as the mean of the block's camera
    directions in `full`, and the NDC rays of a float64 pinhole camera through those centres."""
    rays = rays_for_views(small, 0.0, 1.0)
    full_rays = rays_for_views(full, 0.0, 1.0)
    camtoworlds = full.camtoworlds.astype(np.float64)
    # Full-image directions rescaled to a camera depth of 1 (affine in the pixel position).
    directions = _unit(np.asarray(full_rays.viewdirs, np.float64))
    forward = -camtoworlds[:, None, None, :, 2]
    directions = directions / np.sum(directions * forward, axis=-1, keepdims=True)
    expected = np.stack([block_average(d, factor) for d in directions])
    np.testing.assert_allclose(_unit(np.asarray(rays.viewdirs, np.float64)), _unit(expected), atol=1e-6)
    # An independent pinhole camera at the full image's resolution, principal point at its centre.
    rows, cols = block_centres(full.height, full.width, factor)
    camera = np.stack(
        [
            (cols - full.width / 2) / full.focal,
            -(rows - full.height / 2) / full.focal,
            -np.ones_like(cols),
        ],
        axis=-1,
    )
    world = np.einsum("vij,hwj->vhwi", camtoworlds[:, :3, :3], camera)
    origins = np.broadcast_to(camtoworlds[:, None, None, :, 3], world.shape)
    o_ref, d_ref = _nerf_ndc(origins, world, full.focal / factor, small.height, small.width, near)
    np.testing.assert_allclose(np.asarray(rays.origins), o_ref, atol=2e-5)
    np.testing.assert_allclose(np.asarray(rays.directions), d_ref, atol=2e-5)


@pytest.mark.parametrize(
    "height,width,factor,centred",
    [
        (12, 18, 3, True),  # divides both sides
        (14, 20, 4, True),  # remainders 2 and 0: one row off the top and one off the bottom
        (13, 20, 3, False),  # remainders 1 and 2: the odd row comes off the bottom
    ],
)
def test_downscale(tmp_path, height, width, factor, centred):
    written = write_llff(tmp_path / "scene", height=height, width=width)
    full = load_llff(tmp_path / "scene", num_train_views=3)
    dataset = load_llff(tmp_path / "scene", num_train_views=3, downscale=factor)
    assert (dataset.near, dataset.far, dataset.frustum) == (0.0, 1.0, "cylinder")
    for views, full_views in ((dataset.train, full.train), (dataset.test, full.test)):
        assert views.ids == full_views.ids and views.ndc
        assert views.images.shape == (3, height // factor, width // factor, 3)
        assert views.images.dtype == np.float32
        for position, view in enumerate(views.ids):
            expected = block_average(written["pixels"][view], factor) / 255.0
            np.testing.assert_allclose(views.images[position], expected, atol=1e-6)
        assert views.focal == pytest.approx(40.0 / 8 / factor, rel=1e-12)
        if centred:
            assert views.intrinsics is None
        else:
            top, left = crop_offsets(height, width, factor)
            # The principal point stays at the centre of the 8x image, shifted by the crop.
            cx, cy = (width / 2 - left) / factor, (height / 2 - top) / factor
            k = [[5.0 / factor, 0.0, cx], [0.0, 5.0 / factor, cy]]
            np.testing.assert_allclose(views.intrinsics[:, :2], np.broadcast_to(k, (3, 2, 3)), rtol=1e-6)
            assert views.intrinsics[0, 1, 2] != views.height / 2
        np.testing.assert_array_equal(views.camtoworlds, full_views.camtoworlds)
        _check_block_rays(views, full_views, factor)


@pytest.mark.parametrize("factor", [0, -2, 7])
def test_unusable_downscale(tmp_path, factor):
    write_llff(tmp_path / "scene")
    match = "at least 1" if factor < 1 else r"image001\.png: data\.image_downscale = 7 is larger than the 8x6"
    with pytest.raises(DatasetError, match=match):
        load_llff(tmp_path / "scene", num_train_views=3, downscale=factor)


# --- Bad input -------------------------------------------------------------------------------


def test_missing_scene(tmp_path):
    with pytest.raises(DatasetError, match="images_8"):
        load_llff(tmp_path / "nothing", num_train_views=3)


def test_missing_poses_file(tmp_path):
    write_llff(tmp_path / "scene")
    (tmp_path / "scene" / "poses_bounds.npy").unlink()
    with pytest.raises(DatasetError, match="poses_bounds.npy"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_counts_differ(tmp_path):
    write_llff(tmp_path / "scene")
    (tmp_path / "scene" / "images_8" / "image019.png").unlink()
    with pytest.raises(DatasetError, match=r"images_8.*19 images.*poses_bounds.npy.*20 poses"):
        load_llff(tmp_path / "scene", num_train_views=3)


@pytest.mark.parametrize("shape", [(20, 15), (20, 3, 5), (0, 17)])
def test_pose_array_of_wrong_shape(tmp_path, shape):
    write_llff(tmp_path / "scene")
    np.save(tmp_path / "scene" / "poses_bounds.npy", np.ones(shape))
    with pytest.raises(DatasetError, match=r"poses_bounds.npy.*shape"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_truncated_pose_file(tmp_path):
    write_llff(tmp_path / "scene")
    truncate(tmp_path / "scene" / "poses_bounds.npy", keep=200)
    with pytest.raises(DatasetError, match="poses_bounds.npy"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_truncated_image(tmp_path):
    write_llff(tmp_path / "scene")
    truncate(tmp_path / "scene" / "images_8" / "image010.png")
    with pytest.raises(DatasetError, match="image010.png"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_images_of_mixed_sizes(tmp_path):
    write_llff(tmp_path / "scene")
    write_png(
        tmp_path / "scene" / "images_8" / "image010.png", random_pixels(np.random.default_rng(1), 5, 8, 3)
    )
    with pytest.raises(DatasetError, match="image010.png"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_images_not_matching_poses(tmp_path):
    write_llff(tmp_path / "scene", height=6, width=8)
    for index in range(20):
        write_png(tmp_path / "scene" / "images_8" / f"image{index:03d}.png", np.zeros((12, 16, 3)))
    with pytest.raises(DatasetError, match=r"image001.png.*16x12"):
        load_llff(tmp_path / "scene", num_train_views=3)


def test_too_many_training_views(tmp_path):
    write_llff(tmp_path / "scene")
    with pytest.raises(DatasetError, match=r"images_8.*at most 17"):
        load_llff(tmp_path / "scene", num_train_views=18)


# The real fern.

needs_fern = pytest.mark.skipif(
    not (FERN / "poses_bounds.npy").is_file(), reason="shared fern data not present"
)


@needs_fern
def test_real_fern():
    dataset = load_llff(FERN, num_train_views=3)
    assert dataset.train.ids == (1, 10, 19) and dataset.test.ids == (0, 8, 16)
    assert dataset.train.images.shape == (3, 378, 504, 3)
    assert dataset.test.images.shape == (3, 378, 504, 3)
    rows = np.load(FERN / "poses_bounds.npy")
    assert rows.shape == (20, 17)
    assert dataset.train.focal == pytest.approx(rows[0, 14] / 8)
    _check_ndc(dataset.train)


@needs_fern
def test_real_fern_downscaled_by_4():
    # 504x378 over 4: 126 columns; 378 = 4 * 94 + 2 loses row 0 and row 377.
    full = load_llff(FERN, num_train_views=1, max_test_views=1)
    dataset = load_llff(FERN, num_train_views=1, max_test_views=1, downscale=4)
    rows = np.load(FERN / "poses_bounds.npy")
    for views, full_views in ((dataset.train, full.train), (dataset.test, full.test)):
        assert views.images.shape == (1, 94, 126, 3)
        assert views.focal == pytest.approx(rows[0, 14] / 32, rel=1e-12)
        assert views.intrinsics is None
        expected = full_views.images[0, 1:377].astype(np.float64).reshape(94, 4, 126, 4, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(views.images[0], expected, atol=1e-6)
    _check_block_rays(dataset.train, full.train, 4)
