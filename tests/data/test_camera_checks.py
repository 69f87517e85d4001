"""Cameras are checked at load: finite, a rotation in the matrix, a field of view in (0, pi),
positive focal lengths, each refusal one `DatasetError` naming the file and the camera (they
used to train to NaN metrics with exit status 0, or raise `ZeroDivisionError`)."""

import json

import numpy as np
import pytest
from _writers import homogeneous, write_blender, write_llff, write_transforms
from hypothesis import given, settings
from hypothesis import strategies as st

from mixnerf_eqx.data import DatasetError, load_blender, load_llff, load_transforms
from mixnerf_eqx.data._poses import ROTATION_TOLERANCE, check_camera, check_field_of_view


def _edit_json(path, change):
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("angle", [0, -0.5, float("nan"), float("inf"), 3.5, True])
def test_a_blender_field_of_view_outside_0_and_pi_is_refused(tmp_path, angle):
    write_blender(tmp_path / "toy")

    def change(meta):
        meta["camera_angle_x"] = angle

    _edit_json(tmp_path / "toy" / "transforms_train.json", change)
    with pytest.raises(DatasetError, match=r"transforms_train.json: 'camera_angle_x'"):
        load_blender(tmp_path / "toy", num_train_views=2)


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        (np.zeros((4, 4)), "is not a rotation"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "is not a rotation"),
        (np.full((4, 4), np.nan), "not finite"),
    ],
)
def test_a_blender_camera_that_is_not_a_rotation_is_refused(tmp_path, matrix, message):
    write_blender(tmp_path / "toy")

    def change(meta):
        meta["frames"][1]["transform_matrix"] = matrix.tolist()

    _edit_json(tmp_path / "toy" / "transforms_train.json", change)
    with pytest.raises(DatasetError, match=f"transform_matrix of frame 1.*{message}"):
        load_blender(tmp_path / "toy", num_train_views=2)


def test_llff_focal_zero_and_a_zero_rotation_are_refused(tmp_path):
    written = write_llff(tmp_path / "scene")
    rows = written["rows"].copy()
    rows[:, 14] = 0.0  # the focal length of every camera
    np.save(tmp_path / "scene" / "poses_bounds.npy", rows)
    with pytest.raises(DatasetError, match="focal length are .* each must be positive"):
        load_llff(tmp_path / "scene", num_train_views=3)
    rows = written["rows"].copy()
    pose = rows[4, :15].reshape(3, 5)
    pose[:, :3] = 0.0
    rows[4, :15] = pose.reshape(-1)
    np.save(tmp_path / "scene" / "poses_bounds.npy", rows)
    with pytest.raises(DatasetError, match="camera 4: its 3x3 part is not a rotation"):
        load_llff(tmp_path / "scene", num_train_views=3)
    # Poses saved as integers are read as float numbers: the rounded cameras here are exact
    # axis-aligned rotations, and load into finite float cameras.
    np.save(tmp_path / "scene" / "poses_bounds.npy", written["rows"].round().astype(np.int64))
    dataset = load_llff(tmp_path / "scene", num_train_views=3)
    assert dataset.train.camtoworlds.dtype == np.float32 and np.all(np.isfinite(dataset.train.camtoworlds))


def test_transforms_focal_lengths_must_be_positive(tmp_path):
    write_transforms(tmp_path, num_views=10, intrinsics={"fl_x": 0.0})
    with pytest.raises(DatasetError, match="fl_x of .* is 0.0; a focal length must be finite and positive"):
        load_transforms(tmp_path, num_train_views=3)
    write_transforms(tmp_path, num_views=10, frame_overrides={2: {"transform_matrix": homogeneous(np.zeros((3, 4)))}})
    with pytest.raises(DatasetError, match="not a rotation"):
        load_transforms(tmp_path, num_train_views=3)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-np.pi, np.pi),
    st.floats(-np.pi / 2, np.pi / 2),
    st.floats(-10, 10),
    st.floats(0.0, 5.0),
)
def test_any_rotation_passes_and_any_scaled_one_fails(yaw, pitch, translation, scale_error):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    rotation = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    camera = np.concatenate([rotation, np.full((3, 1), translation)], axis=1)
    check_camera(camera, "camera")  # a rotation with any translation passes
    scaled = camera.copy()
    scaled[:, :3] *= 1.0 + scale_error
    if (1.0 + scale_error) ** 2 - 1.0 > ROTATION_TOLERANCE:
        with pytest.raises(DatasetError, match="not a rotation"):
            check_camera(scaled, "camera")
    else:
        check_camera(scaled, "camera")


@settings(max_examples=60, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5)))
def test_a_field_of_view_is_accepted_exactly_in_0_to_pi(value):
    if np.isfinite(value) and 0 < value < np.pi:
        assert check_field_of_view(value, "fov") == float(value)
    else:
        with pytest.raises(DatasetError, match="fov is"):
            check_field_of_view(value, "fov")


def test_a_garbage_poses_file_is_named_without_numpys_pickle_text(tmp_path):
    write_llff(tmp_path / "scene")
    (tmp_path / "scene" / "poses_bounds.npy").write_bytes(b"not an array at all" * 4)
    with pytest.raises(DatasetError, match="poses_bounds.npy: not a .npy array file") as raised:
        load_llff(tmp_path / "scene", num_train_views=3)
    assert "pickle" not in str(raised.value)
