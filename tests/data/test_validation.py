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
from mixnerf_eqx.data.procedural import make_builtin_scene


def _poses_disjoint(*views):
    poses = [np.asarray(v.camtoworlds, np.float64) for v in views]
    for i, a in enumerate(poses):
        for b in poses[i + 1 :]:
            gaps = np.abs(a[:, None] - b[None]).max(axis=(2, 3))
            assert gaps.min() > 1e-3


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


def test_llff_validation_is_every_image_left_over(tmp_path):
    written = write_llff(tmp_path / "scene")
    dataset = load_llff(tmp_path / "scene", num_train_views=3)
    # 20 images: test 0, 8, 16; train 1, 10, 19; the other 14 validate.
    assert dataset.val.ids == (2, 3, 4, 5, 6, 7, 9, 11, 12, 13, 14, 15, 17, 18)
    for position, view in enumerate(dataset.val.ids):
        np.testing.assert_allclose(dataset.val.images[position], written["pixels"][view] / 255.0, atol=1e-6)
    assert dataset.val.ndc
    # Fewer, evenly spaced; the test subsample does not change them.
    few = load_llff(tmp_path / "scene", num_train_views=3, max_test_views=1, max_val_views=3)
    assert few.val.ids == (2, 9, 18)
    # 9 training views leave 8.
    assert load_llff(tmp_path / "scene", num_train_views=9).val.num_views == 8
    # Every image used: no validation views.
    full = load_llff(tmp_path / "scene", num_train_views=17)
    assert full.val is None and "every image" in full.val_source


def test_blender_validation_from_the_val_split(tmp_path):
    scene_dir = tmp_path / "toy"
    write_blender(scene_dir)
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


def test_blender_validation_without_val_images(tmp_path):
    scene_dir = tmp_path / "toy"
    written = write_blender(scene_dir, num_train=7)
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
    diet = load_blender(tmp_path / "many", num_train_views=4, protocol="dietnerf", max_val_views=0)
    assert set(diet.val.ids) == set(range(100)) - {26, 86, 2, 55}


def test_dtu_validation_is_outside_the_protocol(tmp_path):
    scan_dir, _ = write_dtu(tmp_path, mask_layout=None)
    with pytest.warns(UserWarning, match="no DTU object masks"):
        dataset = load_dtu(scan_dir, num_train_views=3, full_size=(16, 12), factor=4, max_val_views=0)
    # Train 25, 22, 28; test: the 25 views outside the 9 training and 15 excluded ids.
    assert dataset.val.ids == (0, 3, 4, 5, 6, 7, 8, 13, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39, 40, 44, 48)
    assert not set(dataset.val.ids) & (set(dataset.train.ids) | set(dataset.test.ids))
    assert dataset.val.masks is None


def test_transforms_validation(tmp_path):
    write_transforms(tmp_path, num_views=10)
    dataset = load_transforms(tmp_path, num_train_views=3)
    # Test 0, 8; the remaining 1-7, 9 give train 1, 5 (round(3.5) = 4 -> position 4), 9.
    assert set(dataset.val.ids) == set(range(10)) - set(dataset.train.ids) - set(dataset.test.ids)
    assert len(dataset.val.ids) == 5
    _poses_disjoint(dataset.train, dataset.test, dataset.val)


@pytest.mark.skipif(not (FERN / "poses_bounds.npy").is_file(), reason="shared fern data not present")
def test_real_fern_has_fourteen_validation_views():
    dataset = load_llff(FERN, num_train_views=3, max_val_views=0, downscale=8)
    assert dataset.val.num_views == 14
    assert not set(dataset.val.ids) & {0, 8, 16, 1, 10, 19}
