"""Tests of the DTU loader (pixelNeRF's rs_dtu_4 layout) on tiny scans written here.

Camera references are independent float64 computations: the projection `P = K [R | t]` built
from known parts, the camera centre `-R^T t`, and pinhole reprojection of points on the rays.
"""

import numpy as np
import pytest
from _writers import (
    block_average,
    block_centres,
    crop_offsets,
    dtu_cameras_known,
    projection,
    truncate,
    write_dtu,
    write_png,
)

from mixnerf_eqx.data import DatasetError, load_dtu, rays_for_views
from mixnerf_eqx.data._poses import decompose_projection
from mixnerf_eqx.data.dtu import dtu_cameras, protocol_ids

PROTOCOL_TRAIN = [25, 22, 28, 40, 44, 48, 0, 8, 13]
PROTOCOL_EXCLUDED = [3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39]


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("dtu")
    scan_dir, written = write_dtu(root)
    return root, scan_dir, written


def _load(root, scan_dir, num_train_views=3, **kwargs):
    return load_dtu(scan_dir, num_train_views=num_train_views, mask_roots=[root / "idrmasks"], **kwargs)


@pytest.mark.parametrize("num_train_views", [1, 3, 6, 9])
def test_protocol_ids(num_train_views):
    train, test = protocol_ids(num_train_views)
    assert train == PROTOCOL_TRAIN[:num_train_views]
    expected_test = sorted(set(range(49)) - set(PROTOCOL_TRAIN) - set(PROTOCOL_EXCLUDED))
    assert test == expected_test
    assert len(test) == 25
    assert test[:6] == [1, 2, 9, 10, 11, 12]


def test_decompose_projection_recovers_parts():
    ks, rs, ts = dtu_cameras_known(6)
    for k, rotation, translation, scale in zip(ks, rs, ts, [1.0, -1.0, 3.7, -0.02, 250.0, -9.0], strict=True):
        intrinsics, camtoworld = decompose_projection(projection(k, rotation, translation, scale))
        np.testing.assert_allclose(intrinsics, k, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(camtoworld[:, 3], -rotation.T @ translation, atol=1e-10)
        # OpenGL axes: x right (OpenCV x), y up (-OpenCV y), z backward (-OpenCV z).
        np.testing.assert_allclose(camtoworld[:, :3], rotation.T * np.array([1.0, -1.0, -1.0]), atol=1e-10)


def test_dtu_cameras_normalisation(scan):
    _, _, written = scan
    projections = [written["P"][f"world_mat_{i}"] for i in range(49)]
    intrinsics, camtoworlds = dtu_cameras(projections, scan[1] / "cameras.npz")
    np.testing.assert_allclose(intrinsics, written["K"], rtol=1e-10, atol=1e-10)
    centres = camtoworlds[:, :, 3]
    # Recentred on the average pose (mean centre at the origin, mean backward axis along +z),
    # then scaled so that the largest camera coordinate is 1.
    np.testing.assert_allclose(centres.mean(axis=0), 0.0, atol=1e-12)
    assert np.max(np.abs(centres)) == pytest.approx(1.0, abs=1e-12)
    backward = camtoworlds[:, :, 2].sum(axis=0)
    np.testing.assert_allclose(backward / np.linalg.norm(backward), [0.0, 0.0, 1.0], atol=1e-12)
    # A similarity of the true centres: their pairwise distance ratios are kept.
    true_centres = np.stack([-r.T @ t for r, t in zip(written["R"], written["t"], strict=True)])
    ratio = np.linalg.norm(centres[1:] - centres[0], axis=-1) / np.linalg.norm(
        true_centres[1:] - true_centres[0], axis=-1
    )
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-10)


def test_load_dtu_images_split_masks(scan):
    root, scan_dir, written = scan
    dataset = _load(root, scan_dir, num_train_views=3)
    train_ids, test_ids = [25, 22, 28], protocol_ids(3)[1]
    assert dataset.train.ids == tuple(train_ids) and dataset.test.ids == tuple(test_ids)
    assert dataset.train.images.shape == (3, 12, 16, 3)
    assert dataset.test.images.shape == (25, 12, 16, 3)
    for views, ids in ((dataset.train, train_ids), (dataset.test, test_ids)):
        expected = np.stack([written["images"][i] for i in ids]) / 255.0
        np.testing.assert_allclose(views.images, expected, atol=1e-6)
        np.testing.assert_allclose(views.intrinsics, written["K"][ids], rtol=1e-6)
        assert views.origin_plane_z == 0.0 and not views.ndc
    assert dataset.train.masks is None
    np.testing.assert_array_equal(dataset.test.masks, np.stack([written["masks"][i] for i in test_ids]))
    assert (dataset.near, dataset.far, dataset.white_background) == (0.5, 3.5, False)


def _similarity(source, target):
    """Scale, rotation and shift with `target = scale * rotation @ source + shift` (Umeyama, float64)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    a, b = source - source_mean, target - target_mean
    u, sigma, vt = np.linalg.svd(b.T @ a)
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(sigma) @ sign) / np.sum(a**2)
    return scale, rotation, target_mean - scale * rotation @ source_mean


def test_dtu_rays_reproject_to_their_pixels(scan):
    root, scan_dir, written = scan
    dataset = _load(root, scan_dir, num_train_views=9)
    for views in (dataset.train, dataset.test):
        ids = list(views.ids)
        rays = rays_for_views(views, dataset.near, dataset.far)
        origins = np.asarray(rays.origins, np.float64)
        directions = np.asarray(rays.directions, np.float64)
        # RegNeRF's rays start on the plane z = 0 of the normalised world.
        np.testing.assert_allclose(origins[..., 2], 0.0, atol=1e-6)
        # The loaded world is a similarity of the calibration's world: recover it from the centres.
        true_centres = np.stack([-written["R"][i].T @ written["t"][i] for i in ids])
        scale, rotation, shift = _similarity(true_centres, views.camtoworlds[:, :, 3].astype(np.float64))
        np.testing.assert_allclose(
            scale * true_centres @ rotation.T + shift, views.camtoworlds[:, :, 3], atol=1e-5
        )
        rows, cols = np.meshgrid(np.arange(views.height), np.arange(views.width), indexing="ij")
        for t in (0.7, 3.0):
            points = origins + t * directions
            world = (points - shift) @ rotation / scale  # back to the calibration's world
            for index, view in enumerate(ids):
                homogeneous = np.concatenate([world[index], np.ones(world.shape[1:3] + (1,))], axis=-1)
                pixels = homogeneous @ written["P"][f"world_mat_{view}"][:3].T
                np.testing.assert_allclose(pixels[..., 0] / pixels[..., 2], cols + 0.5, atol=2e-3)
                np.testing.assert_allclose(pixels[..., 1] / pixels[..., 2], rows + 0.5, atol=2e-3)
                # In front of the camera (positive depth for the unscaled P: sign of the scale).
                sign = -1.0 if view % 2 else 1.0
                assert np.all(sign * pixels[..., 2] > 0)


def test_full_size_images_are_downsampled(tmp_path):
    scan_dir, written = write_dtu(tmp_path, width=16, height=12, mask_layout=None)
    with pytest.warns(UserWarning, match="no DTU object masks"):
        dataset = load_dtu(scan_dir, num_train_views=2, full_size=(16, 12), factor=4)
    assert dataset.train.images.shape == (2, 3, 4, 3)
    raw = written["images"][25].astype(np.float64) / 255.0
    np.testing.assert_allclose(
        dataset.train.images[0], raw.reshape(3, 4, 4, 4, 3).mean(axis=(1, 3)), atol=1e-6
    )
    expected_k = written["K"][25].copy()
    expected_k[:2] /= 4
    np.testing.assert_allclose(dataset.train.intrinsics[0], expected_k, rtol=1e-6)


@pytest.fixture(scope="module")
def odd_scan(tmp_path_factory):
    """A scan of 22x17 images, whose sides leave remainders for most factors."""
    root = tmp_path_factory.mktemp("dtu_odd")
    scan_dir, written = write_dtu(root, width=22, height=17, seed=3)
    return root, scan_dir, written


def _check_rays_through_block_centres(views, written, factor, near, far):
    """Points on the rays project, with the written projection matrices, onto the centres of
    the rays' blocks in the 22x17 images (after the documented crop)."""
    rays = rays_for_views(views, near, far)
    origins = np.asarray(rays.origins, np.float64)
    directions = np.asarray(rays.directions, np.float64)
    true_centres = np.stack([-written["R"][i].T @ written["t"][i] for i in views.ids])
    scale, rotation, shift = _similarity(true_centres, views.camtoworlds[:, :, 3].astype(np.float64))
    rows, cols = block_centres(17, 22, factor)
    for t in (0.7, 3.0):
        world = (origins + t * directions - shift) @ rotation / scale
        for index, view in enumerate(views.ids):
            homogeneous = np.concatenate([world[index], np.ones(world.shape[1:3] + (1,))], axis=-1)
            pixels = homogeneous @ written["P"][f"world_mat_{view}"][:3].T
            np.testing.assert_allclose(pixels[..., 0] / pixels[..., 2], cols, atol=2e-3)
            np.testing.assert_allclose(pixels[..., 1] / pixels[..., 2], rows, atol=2e-3)


# Remainders of 17 and 22: (1, 0), (2, 1), (1, 2) and (2, 2).
@pytest.mark.parametrize("factor", [2, 3, 4, 5])
def test_downscale(odd_scan, factor):
    root, scan_dir, written = odd_scan
    full = _load(root, scan_dir, num_train_views=3, max_test_views=5)
    dataset = _load(root, scan_dir, num_train_views=3, max_test_views=5, downscale=factor)
    top, left = crop_offsets(17, 22, factor)
    for views, full_views in ((dataset.train, full.train), (dataset.test, full.test)):
        ids = list(views.ids)
        assert ids == list(full_views.ids)
        assert views.images.shape == (len(ids), 17 // factor, 22 // factor, 3)
        expected = np.stack([block_average(written["images"][i], factor) for i in ids]) / 255.0
        np.testing.assert_allclose(views.images, expected, atol=1e-6)
        # The principal point moves with the crop; rows 0 and 1 shrink by the factor.
        k = written["K"][ids].copy()
        k[:, 0, 2] -= left
        k[:, 1, 2] -= top
        k[:, :2] /= factor
        np.testing.assert_allclose(views.intrinsics, k, rtol=1e-6)
        assert views.focal == pytest.approx(float(np.mean(k[:, 0, 0])), rel=1e-6)
        np.testing.assert_array_equal(views.camtoworlds, full_views.camtoworlds)
        assert views.origin_plane_z == 0.0
        _check_rays_through_block_centres(views, written, factor, dataset.near, dataset.far)
    assert dataset.train.masks is None
    # On the object where more than half of the block is.
    expected = np.stack([block_average(written["masks"][i], factor) > 0.5 for i in dataset.test.ids])
    np.testing.assert_array_equal(dataset.test.masks, expected)
    np.testing.assert_array_equal(
        dataset.test.masks, np.stack([block_average(m, factor) > 0.5 for m in full.test.masks])
    )


def test_full_size_images_are_downsampled_then_downscaled(tmp_path):
    scan_dir, written = write_dtu(tmp_path, width=32, height=24, mask_layout=None)
    with pytest.warns(UserWarning, match="no DTU object masks"):
        dataset = load_dtu(scan_dir, num_train_views=2, full_size=(32, 24), factor=4, downscale=2)
    assert dataset.train.images.shape == (2, 3, 4, 3)
    raw = written["images"][25].astype(np.float64) / 255.0
    np.testing.assert_allclose(
        dataset.train.images[0], raw.reshape(3, 8, 4, 8, 3).mean(axis=(1, 3)), atol=1e-6
    )
    expected_k = written["K"][25].copy()
    expected_k[:2] /= 8
    np.testing.assert_allclose(dataset.train.intrinsics[0], expected_k, rtol=1e-6)


@pytest.mark.parametrize(
    "factor,match",
    [(0, "at least 1"), (13, r"000025\.png: data\.image_downscale = 13 is larger than the 16x12 images")],
)
def test_unusable_downscale(scan, factor, match):
    root, scan_dir, _ = scan
    with pytest.raises(DatasetError, match=match):
        _load(root, scan_dir, downscale=factor)


def test_missing_masks_warn_or_fail(tmp_path):
    scan_dir, _ = write_dtu(tmp_path, mask_layout=None)
    with pytest.warns(UserWarning, match="no DTU object masks for scan8"):
        dataset = load_dtu(scan_dir, num_train_views=3, max_test_views=2)
    assert dataset.test.masks is None
    with pytest.raises(DatasetError, match="idrmasks"):
        load_dtu(scan_dir, num_train_views=3, mask_roots=[tmp_path / "idrmasks"], masks_required=True)


# Bad input: each case is one DatasetError naming the file at fault.


@pytest.fixture
def scan_copy(tmp_path):
    scan_dir, _ = write_dtu(tmp_path)
    return tmp_path, scan_dir


def test_missing_image_folder(tmp_path):
    with pytest.raises(DatasetError, match="scan99.image"):
        load_dtu(tmp_path / "scan99", num_train_views=3)


def test_missing_camera_file(scan_copy):
    root, scan_dir = scan_copy
    (scan_dir / "cameras.npz").unlink()
    with pytest.raises(DatasetError, match="cameras.npz"):
        _load(root, scan_dir)


def test_too_few_images(scan_copy):
    root, scan_dir = scan_copy
    (scan_dir / "image" / "000048.png").unlink()
    with pytest.raises(DatasetError, match=r"image.*holds 48 images"):
        _load(root, scan_dir)


def test_missing_projection_matrix(scan_copy):
    root, scan_dir = scan_copy
    cameras = dict(np.load(scan_dir / "cameras.npz"))
    del cameras["world_mat_30"]
    np.savez(scan_dir / "cameras.npz", **cameras)
    with pytest.raises(DatasetError, match=r"cameras.npz.*world_mat_30"):
        _load(root, scan_dir)


def test_projection_of_wrong_shape(scan_copy):
    root, scan_dir = scan_copy
    cameras = dict(np.load(scan_dir / "cameras.npz"))
    cameras["world_mat_4"] = np.eye(3)
    np.savez(scan_dir / "cameras.npz", **cameras)
    with pytest.raises(DatasetError, match=r"cameras.npz.*world_mat_4 has shape \(3, 3\)"):
        _load(root, scan_dir)


def test_truncated_camera_file(scan_copy):
    root, scan_dir = scan_copy
    truncate(scan_dir / "cameras.npz", keep=100)
    with pytest.raises(DatasetError, match="cameras.npz"):
        _load(root, scan_dir)


def test_truncated_image(scan_copy):
    root, scan_dir = scan_copy
    truncate(scan_dir / "image" / "000022.png")
    with pytest.raises(DatasetError, match="000022.png"):
        _load(root, scan_dir)


def test_images_of_mixed_sizes(scan_copy):
    root, scan_dir = scan_copy
    write_png(scan_dir / "image" / "000028.png", np.zeros((10, 16, 3)))
    with pytest.raises(DatasetError, match="000028.png"):
        _load(root, scan_dir)


def test_too_many_training_views(scan_copy):
    root, scan_dir = scan_copy
    with pytest.raises(DatasetError, match="at most 9"):
        _load(root, scan_dir, num_train_views=10)


def test_missing_mask_of_one_view(scan_copy):
    root, scan_dir = scan_copy
    (root / "idrmasks" / "scan8" / "mask" / "010.png").unlink()
    with pytest.raises(DatasetError, match="010.png"):
        _load(root, scan_dir)
