"""The validation split of every loader: disjoint from the training and test views, read from
the right files, subsampled as asked, and absent (with a clear error) when nothing is left.

Each expected id list is written out from the protocol's rule, not computed by the loader's
helpers.
"""

import json

import numpy as np
import pytest
from _writers import (
    FERN,
    blender_reference_image,
    homogeneous,
    orbit_poses,
    random_pixels,
    write_blender,
    write_dtu,
    write_llff,
    write_png,
    write_transforms,
)

from mixnerf_eqx.data import load_blender, load_dtu, load_llff, load_transforms
from mixnerf_eqx.data._splits import MIN_TEST_GAP, near_test
from mixnerf_eqx.data.procedural import make_builtin_scene, split_angles


def _reference_far_ids(centres, train_ids, test_ids, candidates):
    """Float64 loops: the candidates whose centre is at least half the median test-to-nearest-
    training distance from every test centre."""
    def distance(a, b):
        return float(np.sqrt(sum((centres[a][k] - centres[b][k]) ** 2 for k in range(3))))

    scale = float(np.median([min(distance(t, r) for r in train_ids) for t in test_ids]))
    return [c for c in candidates if min(distance(c, t) for t in test_ids) >= 0.5 * scale]


def _assert_away_from_test(dataset):
    """Every validation camera lies at least half the test cameras' median distance to the
    nearest training camera away from every test camera."""
    def centres(views):
        return np.asarray(views.camtoworlds, np.float64)[:, :3, 3]

    train, test, val = centres(dataset.train), centres(dataset.test), centres(dataset.val)
    scale = np.median(np.linalg.norm(test[:, None] - train[None], axis=-1).min(axis=1))
    gaps = np.linalg.norm(val[:, None] - test[None], axis=-1).min(axis=1)
    assert gaps.min() >= 0.5 * scale - 1e-5, (gaps, scale)


def _poses_disjoint(*views):
    poses = [np.asarray(v.camtoworlds, np.float64) for v in views]
    for i, a in enumerate(poses):
        for b in poses[i + 1 :]:
            gaps = np.abs(a[:, None] - b[None]).max(axis=(2, 3))
            assert gaps.min() > 1e-3


def test_builtin_validation_is_away_from_test_at_the_default_counts():
    dataset = make_builtin_scene(resolution=8)  # 4 training, 8 test, 4 validation views
    angles = split_angles(dataset)
    # Each validation camera lies more than 25 degrees from every test camera (27.7 to 28.9)...
    assert angles["val_to_test"].min() > 25.0
    # ... and as far from the training cameras as the test cameras are (17.4 to 27.8 degrees).
    assert angles["test_to_train"].min() <= angles["val_to_train"].min()
    assert angles["val_to_train"].max() <= angles["test_to_train"].max()
    # The same by an independent computation from the stored poses, seen from the origin.
    def directions(views):
        centres = np.asarray(views.camtoworlds, np.float64)[:, :3, 3]
        return centres / np.linalg.norm(centres, axis=1, keepdims=True)

    cosines = directions(dataset.val) @ directions(dataset.test).T
    assert np.degrees(np.arccos(cosines.max())) > 25.0
    _assert_away_from_test(dataset)
    # Other counts keep the validation cameras away from the test cameras too.
    for train, test, val in ((3, 5, 4), (9, 8, 4), (4, 8, 8), (6, 30, 4)):
        other = make_builtin_scene(resolution=8, num_train_views=train, num_test_views=test, num_val_views=val)
        assert split_angles(other)["val_to_test"].min() > 10.0, (train, test, val)


def test_builtin_validation_cameras():
    dataset = make_builtin_scene(resolution=16, num_train_views=3, num_test_views=5, num_val_views=4)
    assert dataset.val is not None and dataset.val.num_views == 4
    assert dataset.val.ids == (8, 9, 10, 11)
    assert dataset.val.depths is not None and dataset.val.images.shape == (4, 16, 16, 3)
    _poses_disjoint(dataset.train, dataset.test, dataset.val)
    # The other splits do not move when validation views are added.
    plain = make_builtin_scene(resolution=16, num_train_views=3, num_test_views=5, num_val_views=0)
    np.testing.assert_array_equal(plain.test.images, dataset.test.images)
    np.testing.assert_array_equal(plain.train.images, dataset.train.images)
    assert plain.val is None
    with pytest.raises(ValueError, match="has no validation views"):
        plain.split("val")
    with pytest.raises(ValueError, match="unknown split 'valid'"):
        dataset.split("valid")


def test_llff_validation_is_every_image_left_over_away_from_test(tmp_path):
    written = write_llff(tmp_path / "scene")
    dataset = load_llff(tmp_path / "scene", num_train_views=3)
    # 20 images: test 0, 8, 16; train 1, 10, 19; of the other 14, image 6 lies near a test camera.
    centres = [np.asarray(r[:15], np.float64).reshape(3, 5)[:, 3] for r in written["rows"]]
    others = [2, 3, 4, 5, 6, 7, 9, 11, 12, 13, 14, 15, 17, 18]
    assert _reference_far_ids(centres, [1, 10, 19], [0, 8, 16], others) == [2, 3, 4, 5, 7, 9, 11, 12, 13, 14, 15, 17, 18]
    assert dataset.val.ids == (2, 3, 4, 5, 7, 9, 11, 12, 13, 14, 15, 17, 18)
    assert "1 left out for lying near a test view" in dataset.val_source
    _assert_away_from_test(dataset)
    for position, view in enumerate(dataset.val.ids):
        np.testing.assert_allclose(dataset.val.images[position], written["pixels"][view] / 255.0, atol=1e-6)
    assert dataset.val.ndc
    # Fewer, evenly spaced; the test subsample does not change them.
    few = load_llff(tmp_path / "scene", num_train_views=3, max_test_views=1, max_val_views=3)
    assert few.val.ids == (2, 11, 18)  # of 2, 3, 4, 5, 7, 9, 11, 12, 13, 14, 15, 17, 18 (test 0 only)
    # 9 training views leave 8.
    assert load_llff(tmp_path / "scene", num_train_views=9).val.num_views == 8
    # Every image used: no validation views.
    full = load_llff(tmp_path / "scene", num_train_views=17)
    assert full.val is None and "every image" in full.val_source


def test_blender_validation_from_the_val_split(tmp_path):
    scene_dir = tmp_path / "toy"
    written = write_blender(scene_dir, num_test=2)
    rng = np.random.default_rng(5)
    poses = orbit_poses(6, radius=4.0, phase=1.1)
    pixels = [random_pixels(rng, 6, 8, 4) for _ in range(6)]
    frames = []
    for index in range(6):
        write_png(scene_dir / "val" / f"r_{index}.png", pixels[index])
        frames.append({"file_path": f"./val/r_{index}", "transform_matrix": homogeneous(poses[index])})
    (scene_dir / "transforms_val.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    dataset = load_blender(scene_dir, num_train_views=3, max_val_views=3)
    assert dataset.val_source == "transforms_val.json"
    assert dataset.val.ids == (0, 2, 5)  # round(linspace(0, 5, 3)) = 0, 2 (2.5 to even), 5
    for position, frame in enumerate(dataset.val.ids):
        np.testing.assert_allclose(
            dataset.val.images[position], blender_reference_image(pixels[frame], 2), atol=1e-6
        )
        np.testing.assert_allclose(dataset.val.camtoworlds[position], poses[frame], atol=1e-6)
    _assert_away_from_test(dataset)
    # A val camera placed on a test camera is left out, and the source says so.
    frames[1]["transform_matrix"] = homogeneous(written["test"]["poses"][0])
    (scene_dir / "transforms_val.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    moved = load_blender(scene_dir, num_train_views=3, max_val_views=0)
    assert moved.val.ids == (0, 2, 3, 4, 5)
    assert moved.val_source == "transforms_val.json; 1 left out for lying near a test view"


def test_blender_validation_without_val_images(tmp_path):
    scene_dir = tmp_path / "toy"
    written = write_blender(scene_dir, num_train=7, num_test=2)
    # A val file whose images are missing (as in the project's shared lego) is passed over.
    (scene_dir / "transforms_val.json").write_text(
        json.dumps(
            {
                "camera_angle_x": 0.7,
                "frames": [{"file_path": "./val/r_0", "transform_matrix": np.eye(4).tolist()}],
            }
        )
    )
    dataset = load_blender(scene_dir, num_train_views=3)
    assert dataset.val.ids == (3, 4, 5, 6)
    assert "not trained on" in dataset.val_source
    for position, frame in enumerate(dataset.val.ids):
        expected = blender_reference_image(written["train"]["pixels"][frame], 2)
        np.testing.assert_allclose(dataset.val.images[position], expected, atol=1e-6)
    # DietNeRF's training frames are not consecutive: the others validate.
    write_blender(tmp_path / "many", num_train=100, num_test=9, height=2, width=2)
    many = write_blender(tmp_path / "many", num_train=100, num_test=9, height=2, width=2)
    diet = load_blender(tmp_path / "many", num_train_views=4, protocol="dietnerf", max_val_views=0)
    # Test frames 0 and 8 on the training ring: the unused frames next to them are left out.
    centres = [pose[:, 3] for pose in many["train"]["poses"]] + [pose[:, 3] for pose in many["test"]["poses"]]
    unused = sorted(set(range(100)) - {26, 86, 2, 55})
    expected = _reference_far_ids(centres, [26, 86, 2, 55], [100, 108], unused)
    assert len(expected) == 90
    assert diet.val.ids == tuple(expected)
    assert "6 left out for lying near a test view" in diet.val_source
    _assert_away_from_test(diet)


def test_dtu_validation_is_outside_the_protocol(tmp_path):
    scan_dir, _ = write_dtu(tmp_path, mask_layout=None)
    with pytest.warns(UserWarning, match="no DTU object masks"):
        dataset = load_dtu(scan_dir, num_train_views=3, full_size=(16, 12), factor=4, max_val_views=0)
    # Train 25, 22, 28; test: the 25 views outside the 9 training and 15 excluded ids. Of the
    # 21 views left, 10 lie near a test camera.
    left = [0, 3, 4, 5, 6, 7, 8, 13, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39, 40, 44, 48]
    centres = np.asarray(dataset.test.camtoworlds)  # noqa: F841 (the cameras are read back below)
    assert dataset.val.ids == (0, 6, 7, 13, 16, 17, 20, 21, 36, 44, 48)
    assert set(dataset.val.ids) <= set(left)
    assert "10 left out for lying near a test view" in dataset.val_source
    _assert_away_from_test(dataset)
    assert not set(dataset.val.ids) & (set(dataset.train.ids) | set(dataset.test.ids))
    assert dataset.val.masks is None


def test_transforms_validation(tmp_path):
    write_transforms(tmp_path, num_views=10)
    dataset = load_transforms(tmp_path, num_train_views=3)
    # Test 0, 8; the remaining 1-7, 9 give train 1, 5 (round(3.5) = 4 -> position 4), 9.
    # Of 2, 3, 4, 6, 7 none lies near test 0 or 8.
    assert dataset.val.ids == (2, 3, 4, 6, 7)
    assert set(dataset.val.ids) == set(range(10)) - set(dataset.train.ids) - set(dataset.test.ids)
    _assert_away_from_test(dataset)
    _poses_disjoint(dataset.train, dataset.test, dataset.val)


@pytest.mark.skipif(not (FERN / "poses_bounds.npy").is_file(), reason="shared fern data not present")
def test_real_fern_has_thirteen_validation_views_away_from_test():
    dataset = load_llff(FERN, num_train_views=3, max_val_views=0, downscale=8)
    # 14 images are neither trained on nor tested; image 13 sits next to test image 16.
    assert dataset.val.ids == (2, 3, 4, 5, 6, 7, 9, 11, 12, 14, 15, 17, 18)
    assert not set(dataset.val.ids) & {0, 8, 16, 1, 10, 19}
    _assert_away_from_test(dataset)
    # The benchmarks' 8 views.
    assert load_llff(FERN, num_train_views=3, max_val_views=8, downscale=8).val.ids == (2, 4, 5, 7, 11, 14, 15, 18)


def test_near_test_against_a_hand_made_layout():
    # Training at x = 0 and 10, test at x = 4 and 6: the median test-to-training distance is 4,
    # so a validation camera must lie at least 2 from x = 4 and x = 6.
    train = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    test = np.array([[4.0, 0, 0], [6.0, 0, 0]])
    candidates = np.array([[2.1, 0, 0], [1.9, 0, 0], [5.0, 0, 0], [8.0, 0, 0], [6.0, 1.99, 0], [6.0, 0, 2.01]])
    assert MIN_TEST_GAP == 0.5
    assert near_test(candidates, train, test).tolist() == [True, False, True, False, True, False]
