"""The transforms.json (nerfstudio / instant-ngp) loader, on tiny scenes written here.

Ray references are independent: points on each world ray are taken into the frame of the
camera that was written (not the loaded one) and projected with the float64 pinhole formula
`u = fx x / z + s y / z + cx`, `v = fy y / z + cy` (OpenCV axes), which must land on the centre
of the ray's own pixel.
"""

import json
import math

import numpy as np
import pytest
from _writers import block_average, truncate, write_png, write_transforms

from mixnerf_eqx.data import DatasetError, load_transforms, rays_for_views

# Ten frames: every 8th (positions 0 and 8) is held out; the 8 others are 1..7 and 9, of
# which 3 evenly spaced are round(linspace(0, 7, 3)) = 0, 4 (3.5 rounds to even), 7.
TEST_IDS = (0, 8)
TRAIN_IDS_3 = (1, 5, 9)


def _rewrite(scene_dir, edit):
    path = scene_dir / "transforms.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def _frame(meta, name):
    return next(frame for frame in meta["frames"] if frame["file_path"] == f"images/{name}")


def _reprojection(views, rays, poses, k):
    """Pixel coordinates of points at two depths on each ray, projected with the true poses
    (`poses`, 3x4 by frame) and intrinsics `k` (float64); also their camera depths."""
    origins = np.asarray(rays.origins, np.float64)
    directions = np.asarray(rays.directions, np.float64)
    results = []
    for position, frame in enumerate(views.ids):
        pose = poses[frame]
        for t in (0.5, 2.0):
            camera = (origins[position] + t * directions[position] - pose[:, 3]) @ pose[:, :3]
            x, y, z = camera[..., 0], -camera[..., 1], -camera[..., 2]  # OpenGL to OpenCV axes
            results.append(((k[0, 0] * x + k[0, 1] * y) / z + k[0, 2], k[1, 1] * y / z + k[1, 2], z))
    return results


def _check_rays_project_back(views, rays, poses, k):
    rows, cols = np.meshgrid(np.arange(views.height) + 0.5, np.arange(views.width) + 0.5, indexing="ij")
    for u, v, z in _reprojection(views, rays, poses, k):
        assert np.all(z > 0)  # in front of the camera
        np.testing.assert_allclose(u, cols, atol=1e-4)
        np.testing.assert_allclose(v, rows, atol=1e-4)
    np.testing.assert_allclose(
        np.asarray(rays.origins),
        np.broadcast_to(views.camtoworlds[:, None, None, :, 3], rays.origins.shape),
        atol=1e-6,
    )


def test_frames_split_images_and_intrinsics(tmp_path):
    written = write_transforms(tmp_path)
    dataset = load_transforms(tmp_path, num_train_views=3)
    # Frames are ordered by name with numbers by value (frame_2 before frame_10), whatever
    # their order in the file.
    assert dataset.train.ids == TRAIN_IDS_3 and dataset.test.ids == TEST_IDS
    expected_k = np.array([[7.0, 0.0, 3.1], [0.0, 7.5, 3.4], [0.0, 0.0, 1.0]])
    for views in (dataset.train, dataset.test):
        for position, frame in enumerate(views.ids):
            np.testing.assert_allclose(views.images[position], written["pixels"][frame] / 255.0, atol=1e-6)
            np.testing.assert_allclose(views.camtoworlds[position], written["poses"][frame][:3], atol=1e-6)
            np.testing.assert_allclose(views.intrinsics[position], expected_k, rtol=1e-6)
    # Bounds from the camera distances: all cameras are sqrt(3^2 + 1^2) from the origin.
    assert dataset.near == pytest.approx(0.5 * math.sqrt(10.0), rel=1e-9)
    assert dataset.far == pytest.approx(1.5 * math.sqrt(10.0), rel=1e-9)
    assert (dataset.white_background, dataset.frustum) == (False, "cone")


def test_off_centre_rays_project_back_to_their_pixels(tmp_path):
    written = write_transforms(tmp_path, intrinsics={"fl_x": 6.0, "fl_y": 9.0, "cx": 5.2, "cy": 1.7})
    dataset = load_transforms(tmp_path, num_train_views=4)
    k = np.array([[6.0, 0.0, 5.2], [0.0, 9.0, 1.7], [0.0, 0.0, 1.0]])
    for views in (dataset.train, dataset.test):
        rays = rays_for_views(views, dataset.near, dataset.far)
        _check_rays_project_back(views, rays, written["poses"], k)


def test_per_frame_intrinsics_and_field_of_view(tmp_path):
    # Frame 3 (frame_4.png) carries its own focal length and principal point; the others have
    # only instant-ngp's fields of view and the default (central) principal point.
    write_transforms(tmp_path, frame_overrides={3: {"fl_x": 9.0, "cx": 4.5}})

    def edit(meta):
        for key in ("fl_x", "fl_y", "cx", "cy"):
            del meta[key]
        meta["camera_angle_x"] = 1.2
        meta["camera_angle_y"] = 0.9

    _rewrite(tmp_path, edit)
    dataset = load_transforms(tmp_path, num_train_views=8)
    views = dataset.train
    assert views.ids == (1, 2, 3, 4, 5, 6, 7, 9)
    focal_x, focal_y = 4.0 / math.tan(0.6), 3.0 / math.tan(0.45)
    for position, frame in enumerate(views.ids):
        expected = np.array([[focal_x, 0.0, 4.0], [0.0, focal_y, 3.0], [0.0, 0.0, 1.0]])
        if frame == 3:
            expected[0, 0], expected[0, 2] = 9.0, 4.5
        np.testing.assert_allclose(views.intrinsics[position], expected, rtol=1e-6)


def test_distortion_is_ignored_with_a_warning(tmp_path):
    write_transforms(tmp_path, intrinsics={"k1": 0.01, "k2": 0.0, "p1": -0.002})
    with pytest.warns(UserWarning, match=r"transforms\.json: lens distortion \(k1, p1\) is ignored"):
        dataset = load_transforms(tmp_path, num_train_views=2)
    assert dataset.train.num_views == 2


def test_camera_angle_x_alone_gives_square_pixels(tmp_path):
    # instant-ngp's camera_angle_x without camera_angle_y: fy = fx, principal point central.
    write_transforms(tmp_path)

    def edit(meta):
        for key in ("fl_x", "fl_y", "cx", "cy"):
            del meta[key]
        meta["camera_angle_x"] = 1.1

    _rewrite(tmp_path, edit)
    dataset = load_transforms(tmp_path, num_train_views=2)
    focal = 0.5 * 8 / math.tan(0.55)
    k = np.array([[focal, 0.0, 4.0], [0.0, focal, 3.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(dataset.train.intrinsics, np.broadcast_to(k, (2, 3, 3)), rtol=1e-6)


def test_zero_distortion_does_not_warn(tmp_path):
    # pytest turns warnings into errors: a spurious warning fails this test.
    write_transforms(tmp_path, intrinsics={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    load_transforms(tmp_path, num_train_views=2)


def test_rgba_images_are_composited_on_white(tmp_path):
    written = write_transforms(tmp_path, channels=4)
    dataset = load_transforms(tmp_path, num_train_views=2)
    rgba = written["pixels"][TEST_IDS[1]].astype(np.float64) / 255.0
    expected = rgba[..., :3] * rgba[..., 3:] + 1.0 - rgba[..., 3:]
    np.testing.assert_allclose(dataset.test.images[1], expected, atol=1e-6)
    assert dataset.white_background


def test_downscale_and_explicit_bounds(tmp_path):
    written = write_transforms(
        tmp_path, height=12, width=16, intrinsics={"fl_x": 14.0, "fl_y": 15.0, "cx": 6.2, "cy": 6.8}
    )
    dataset = load_transforms(tmp_path, num_train_views=1, downscale=2, bounds=(0.25, 9.0))
    assert dataset.train.images.shape == (1, 6, 8, 3)
    raw = written["pixels"][1].astype(np.float64) / 255.0
    np.testing.assert_allclose(
        dataset.train.images[0], raw.reshape(6, 2, 8, 2, 3).mean(axis=(1, 3)), atol=1e-6
    )
    np.testing.assert_allclose(
        dataset.train.intrinsics[0], [[7.0, 0.0, 3.1], [0.0, 7.5, 3.4], [0.0, 0.0, 1.0]], rtol=1e-6
    )
    assert (dataset.near, dataset.far) == (0.25, 9.0)
    k = np.array([[7.0, 0.0, 3.1], [0.0, 7.5, 3.4], [0.0, 0.0, 1.0]])
    rays = rays_for_views(dataset.train, dataset.near, dataset.far)
    _check_rays_project_back(dataset.train, rays, written["poses"], k)


def test_downscale_that_does_not_divide_the_image(tmp_path):
    # 17x13 over 3: remainders 1 (the odd row off the bottom) and 2 (a column off each side).
    written = write_transforms(
        tmp_path, height=13, width=17, intrinsics={"fl_x": 14.0, "fl_y": 15.0, "cx": 8.2, "cy": 6.1}
    )
    dataset = load_transforms(tmp_path, num_train_views=3, downscale=3)
    assert dataset.train.images.shape == (3, 4, 5, 3)
    for position, frame in enumerate(dataset.train.ids):
        expected = block_average(written["pixels"][frame], 3) / 255.0
        np.testing.assert_allclose(dataset.train.images[position], expected, atol=1e-6)
    k = np.array([[14.0 / 3, 0.0, (8.2 - 1) / 3], [0.0, 5.0, 6.1 / 3], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(dataset.train.intrinsics, np.broadcast_to(k, (3, 3, 3)), rtol=1e-6)
    rays = rays_for_views(dataset.train, dataset.near, dataset.far)
    _check_rays_project_back(dataset.train, rays, written["poses"], k)


# --- Bad input: one DatasetError that names the file -----------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match=r"transforms\.json not found: .*transforms\.json does not exist"):
        load_transforms(tmp_path, num_train_views=2)


def test_malformed_json(tmp_path):
    (tmp_path / "transforms.json").write_text('{"frames": [}')
    with pytest.raises(DatasetError, match=r"transforms\.json: not valid JSON \(line 1"):
        load_transforms(tmp_path, num_train_views=2)


def test_no_frames(tmp_path):
    (tmp_path / "transforms.json").write_text('{"fl_x": 3.0, "frames": []}')
    with pytest.raises(
        DatasetError, match=r"transforms\.json: expected an object with a non-empty 'frames' list"
    ):
        load_transforms(tmp_path, num_train_views=2)


def test_missing_image(tmp_path):
    write_transforms(tmp_path)
    (tmp_path / "images" / "frame_6.png").unlink()
    with pytest.raises(DatasetError, match=r"frame_6\.png does not exist"):
        load_transforms(tmp_path, num_train_views=3)


def test_truncated_image(tmp_path):
    write_transforms(tmp_path)
    truncate(tmp_path / "images" / "frame_9.png")
    with pytest.raises(DatasetError, match=r"frame_9\.png: cannot decode the image.*truncated"):
        load_transforms(tmp_path, num_train_views=3)


def test_images_of_mixed_sizes(tmp_path):
    write_transforms(tmp_path)
    write_png(tmp_path / "images" / "frame_10.png", np.zeros((6, 10, 3)))
    with pytest.raises(DatasetError, match=r"frame_10\.png: the image is 10x6 but frame_2\.png is 8x6"):
        load_transforms(tmp_path, num_train_views=3)


def test_stated_size_differs_from_the_image(tmp_path):
    write_transforms(tmp_path, intrinsics={"w": 16, "h": 12})
    with pytest.raises(
        DatasetError, match=r"frame_2\.png: the image is 8x6 but transforms\.json says w=16, h=12"
    ):
        load_transforms(tmp_path, num_train_views=3)


def test_pose_of_wrong_shape(tmp_path):
    write_transforms(tmp_path)
    _rewrite(tmp_path, lambda meta: _frame(meta, "frame_5.png").update(transform_matrix=[1.0, 2.0, 3.0]))
    with pytest.raises(
        DatasetError, match=r"transforms\.json: the transform_matrix of images/frame_5\.png has shape \(3,\)"
    ):
        load_transforms(tmp_path, num_train_views=3)


def test_frame_without_pose(tmp_path):
    write_transforms(tmp_path)
    _rewrite(tmp_path, lambda meta: _frame(meta, "frame_5.png").pop("transform_matrix"))
    with pytest.raises(
        DatasetError, match=r"transforms\.json: frame \d+ \(images/frame_5\.png\) has no 'transform_matrix'"
    ):
        load_transforms(tmp_path, num_train_views=3)


def test_no_focal_length(tmp_path):
    write_transforms(tmp_path)
    _rewrite(tmp_path, lambda meta: meta.pop("fl_x"))
    with pytest.raises(DatasetError, match=r"transforms\.json: no focal length for frame_\d+\.png"):
        load_transforms(tmp_path, num_train_views=3)


def test_intrinsic_that_is_not_a_number(tmp_path):
    write_transforms(tmp_path, intrinsics={"cx": "centre"})
    with pytest.raises(DatasetError, match=r"transforms\.json: 'cx' must be a number"):
        load_transforms(tmp_path, num_train_views=3)


def test_fisheye_camera(tmp_path):
    write_transforms(tmp_path)
    _rewrite(tmp_path, lambda meta: meta.update(camera_model="OPENCV_FISHEYE"))
    with pytest.raises(
        DatasetError, match=r"transforms\.json: camera_model 'OPENCV_FISHEYE' is not a pinhole"
    ):
        load_transforms(tmp_path, num_train_views=3)


def test_more_training_views_than_frames(tmp_path):
    write_transforms(tmp_path)
    with pytest.raises(
        DatasetError, match=r"transforms\.json: 9 training views asked for, but only 8 of its 10"
    ):
        load_transforms(tmp_path, num_train_views=9)


@pytest.mark.parametrize(
    "factor,match", [(0, "at least 1"), (7, r"frame_2\.png: .*= 7 is larger than the 8x6")]
)
def test_unusable_downscale(tmp_path, factor, match):
    write_transforms(tmp_path)
    with pytest.raises(DatasetError, match=match):
        load_transforms(tmp_path, num_train_views=3, downscale=factor)


def test_cameras_at_the_origin_need_bounds(tmp_path):
    write_transforms(tmp_path)

    def edit(meta):
        for frame in meta["frames"]:
            frame["transform_matrix"] = np.eye(4).tolist()

    _rewrite(tmp_path, edit)
    with pytest.raises(
        DatasetError, match=r"transforms\.json: sampling bounds .* set data\.near and data\.far"
    ):
        load_transforms(tmp_path, num_train_views=3)
