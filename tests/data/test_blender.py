"""The NeRF synthetic (Blender) loader, on tiny scenes written here and on the real lego.

References: images recomputed with a float64 box average and white compositing, the focal
length from `camera_angle_x` by trigonometry, and the protocols' view ids written out.
"""

import json
import math
import time

import numpy as np
import pytest
from _writers import (
    LEGO,
    blender_reference_image,
    block_average,
    block_centres,
    random_pixels,
    truncate,
    write_blender,
    write_png,
)
from PIL import Image

from mixnerf_eqx.data import DatasetError, load_blender, rays_for_views
from mixnerf_eqx.data.blender import split_ids

DIETNERF_IDS = [26, 86, 2, 55, 75, 93, 16, 73]


@pytest.fixture
def scene(tmp_path):
    scene_dir = tmp_path / "toy"
    return scene_dir, write_blender(scene_dir)


@pytest.mark.parametrize("num_train_views", [1, 4, 8])
def test_split_ids_of_both_protocols(num_train_views, tmp_path):
    source = tmp_path / "transforms_train.json"
    train, test = split_ids("mixnerf", 100, 200, num_train_views, source)
    assert train == list(range(num_train_views)) and test == list(range(200))
    train, test = split_ids("dietnerf", 100, 200, num_train_views, source)
    assert train == DIETNERF_IDS[:num_train_views]
    assert test == [8 * i for i in range(25)]


def test_tiny_scene_images_poses_focal(scene):
    scene_dir, written = scene
    dataset = load_blender(scene_dir, num_train_views=3)
    assert dataset.train.ids == (0, 1, 2)
    assert dataset.test.ids == tuple(range(9))
    assert dataset.train.images.shape == (3, 3, 4, 3)
    assert dataset.train.images.dtype == np.float32
    for views, split in ((dataset.train, "train"), (dataset.test, "test")):
        for position, frame in enumerate(views.ids):
            expected = blender_reference_image(written[split]["pixels"][frame], 2)
            np.testing.assert_allclose(views.images[position], expected, atol=1e-6)
            np.testing.assert_allclose(views.camtoworlds[position], written[split]["poses"][frame], atol=1e-6)
        # A 0.7 rad field of view across the 4-pixel-wide downsampled image.
        assert views.focal == pytest.approx(2.0 / math.tan(0.35), rel=1e-12)
        assert views.intrinsics is None and not views.ndc
    assert (dataset.near, dataset.far, dataset.white_background, dataset.frustum) == (2.0, 6.0, True, "cone")


def test_rays_of_tiny_scene_project_back(tmp_path):
    written = write_blender(tmp_path / "toy", num_train=2, num_test=1, height=8, width=8, camera_angle_x=0.69)
    dataset = load_blender(tmp_path / "toy", num_train_views=2)
    rays = rays_for_views(dataset.train, 2.0, 6.0)
    focal = 0.5 * 4 / math.tan(0.5 * 0.69)
    rows, cols = np.meshgrid(np.arange(4) + 0.5, np.arange(4) + 0.5, indexing="ij")
    for view, pose in enumerate(written["train"]["poses"]):
        points = np.asarray(rays.origins[view], np.float64) + 3.0 * np.asarray(
            rays.directions[view], np.float64
        )
        camera = (points - pose[:, 3]) @ pose[:, :3]  # world to OpenGL camera: R^T (p - c)
        np.testing.assert_allclose(camera[..., 2], -3.0, atol=1e-5)
        np.testing.assert_allclose(2 + focal * camera[..., 0] / -camera[..., 2], cols, atol=1e-4)
        np.testing.assert_allclose(2 - focal * camera[..., 1] / -camera[..., 2], rows, atol=1e-4)


def test_dietnerf_protocol_and_max_test_views(tmp_path):
    write_blender(tmp_path / "toy", num_train=100, num_test=17, height=2, width=2)
    dataset = load_blender(tmp_path / "toy", num_train_views=4, protocol="dietnerf")
    assert dataset.train.ids == (26, 86, 2, 55) and dataset.test.ids == (0, 8, 16)
    dataset = load_blender(tmp_path / "toy", num_train_views=2, max_test_views=5)
    assert dataset.test.ids == (0, 4, 8, 12, 16)
    # round(linspace(0, 16, 3)) = 0, 8, 16
    dataset = load_blender(tmp_path / "toy", num_train_views=1, max_test_views=3)
    assert dataset.test.ids == (0, 8, 16)


def test_downsampled_copies_are_used_when_full_size_images_are_missing(scene):
    scene_dir, written = scene
    # Replace the test images by ready-made half-size copies in test_400/ (as in the shared data).
    half = []
    for index, pixels in enumerate(written["test"]["pixels"]):
        small = np.full((3, 4, 4), 255, np.uint8)
        small[..., :3] = pixels[::2, ::2, :3]
        half.append(small)
        write_png(scene_dir / "test_400" / f"r_{index}.png", small)
        (scene_dir / "test" / f"r_{index}.png").unlink()
    dataset = load_blender(scene_dir, num_train_views=2)
    np.testing.assert_allclose(dataset.test.images, np.stack(half)[..., :3] / 255.0, atol=1e-6)


def test_full_size_images_are_preferred_to_downsampled_copies(scene):
    scene_dir, written = scene
    rng = np.random.default_rng(5)
    small = [random_pixels(rng, 3, 4, 4) for _ in range(9)]
    for index, pixels in enumerate(small):
        write_png(scene_dir / "test_400" / f"r_{index}.png", pixels)
    # All originals present: they are read (and halved).
    dataset = load_blender(scene_dir, num_train_views=1)
    np.testing.assert_allclose(
        dataset.test.images[1], blender_reference_image(written["test"]["pixels"][1], 2), atol=1e-6
    )
    # One original missing: the whole split is read from the copies (RGBA composited on white).
    (scene_dir / "test" / "r_2.png").unlink()
    dataset = load_blender(scene_dir, num_train_views=1)
    for index in (1, 2):
        np.testing.assert_allclose(
            dataset.test.images[index], blender_reference_image(small[index], 1), atol=1e-6
        )


# --- data.image_downscale ---------------------------------------------------------------------


def _check_rays_through_block_centres(views, poses, full_height, full_width, camera_angle_x, factor):
    """Points on each ray project, with the full-size (800x800-like) camera of the written
    scene, onto the centre of the ray's block: `2 x factor` full-size pixels on a side, after
    the documented crop of the half-size image."""
    rays = rays_for_views(views, 2.0, 6.0)
    focal = 0.5 * full_width / math.tan(0.5 * camera_angle_x)
    rows, cols = block_centres(full_height // 2, full_width // 2, factor)
    for position, frame in enumerate(views.ids):
        pose = poses[frame]
        for t in (2.5, 5.0):
            points = np.asarray(rays.origins[position], np.float64) + t * np.asarray(
                rays.directions[position], np.float64
            )
            camera = (points - pose[:, 3]) @ pose[:, :3]  # world to OpenGL camera: R^T (p - c)
            np.testing.assert_allclose(camera[..., 2], -t, atol=1e-5)
            u = full_width / 2 + focal * camera[..., 0] / -camera[..., 2]
            v = full_height / 2 - focal * camera[..., 1] / -camera[..., 2]
            np.testing.assert_allclose(u, 2 * cols, atol=1e-4)
            np.testing.assert_allclose(v, 2 * rows, atol=1e-4)


@pytest.mark.parametrize(
    "height,width,factor,centred",
    [
        (24, 40, 2, True),  # 12x20 after halving: divides both sides
        (24, 40, 3, True),  # remainders 0 and 2: one column off each side
        (32, 40, 5, False),  # 16x20: remainder 1, the odd row off the bottom
    ],
)
def test_downscale(tmp_path, height, width, factor, centred):
    written = write_blender(tmp_path / "toy", num_train=2, num_test=3, height=height, width=width)
    full = load_blender(tmp_path / "toy", num_train_views=2)
    dataset = load_blender(tmp_path / "toy", num_train_views=2, downscale=factor)
    out_shape = (height // 2 // factor, width // 2 // factor, 3)
    for views, full_views, split in ((dataset.train, full.train, "train"), (dataset.test, full.test, "test")):
        assert views.ids == full_views.ids
        assert views.images.shape == (views.num_views, *out_shape)
        for position, frame in enumerate(views.ids):
            # The protocol's image (straight RGBA halved, composited on white), then averaged.
            expected = block_average(blender_reference_image(written[split]["pixels"][frame], 2), factor)
            np.testing.assert_allclose(views.images[position], expected, atol=1e-6)
            expected = block_average(full_views.images[position], factor)
            np.testing.assert_allclose(views.images[position], expected, atol=1e-6)
        # The focal length of the full-size renders over 2 x factor.
        assert views.focal == pytest.approx(0.5 * width / math.tan(0.35) / (2 * factor), rel=1e-12)
        assert (views.intrinsics is None) == centred
        _check_rays_through_block_centres(views, written[split]["poses"], height, width, 0.7, factor)
    assert (dataset.near, dataset.far, dataset.white_background) == (2.0, 6.0, True)


@pytest.mark.parametrize("factor", [1, 3])
def test_downscaled_copies_match_the_full_size_path(scene, factor):
    scene_dir, written = scene
    # Renders whose 2x2 blocks are uniform, so that exact half-size copies exist: the two
    # paths then agree to the last bit, downscaled or not.
    for index, pixels in enumerate(written["test"]["pixels"]):
        small = pixels[::2, ::2]
        write_png(scene_dir / "test" / f"r_{index}.png", np.kron(small, np.ones((2, 2, 1), np.uint8)))
        write_png(scene_dir / "test_400" / f"r_{index}.png", small)
    from_full = load_blender(scene_dir, num_train_views=1, downscale=factor)
    (scene_dir / "test" / "r_0.png").unlink()
    from_copies = load_blender(scene_dir, num_train_views=1, downscale=factor)
    np.testing.assert_array_equal(from_copies.test.images, from_full.test.images)
    assert from_copies.test.focal == from_full.test.focal
    assert from_copies.test.images.shape == (9, 3 // factor, 4 // factor, 3)


@pytest.mark.parametrize(
    "factor,match",
    [(0, "at least 1"), (4, r"r_0\.png: data\.image_downscale = 4 is larger than the 4x3 images")],
)
def test_unusable_downscale(scene, factor, match):
    scene_dir, _ = scene
    with pytest.raises(DatasetError, match=match):
        load_blender(scene_dir, num_train_views=2, downscale=factor)


# --- Bad input: one DatasetError that names the file -----------------------------------------


def test_missing_scene_folder(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere.transforms_train\.json does not exist"):
        load_blender(tmp_path / "nowhere", num_train_views=2)


def test_missing_test_json(scene):
    scene_dir, _ = scene
    (scene_dir / "transforms_test.json").unlink()
    with pytest.raises(DatasetError, match=r"transforms_test\.json does not exist"):
        load_blender(scene_dir, num_train_views=2)


@pytest.mark.parametrize("split", ["train", "test"])
def test_malformed_json(scene, split):
    scene_dir, _ = scene
    (scene_dir / f"transforms_{split}.json").write_text('{"frames": [')
    with pytest.raises(DatasetError, match=rf"transforms_{split}\.json: not valid JSON"):
        load_blender(scene_dir, num_train_views=2)


def test_missing_image(scene):
    scene_dir, _ = scene
    (scene_dir / "train" / "r_1.png").unlink()
    with pytest.raises(DatasetError, match=r"r_1\.png does not exist"):
        load_blender(scene_dir, num_train_views=2)


@pytest.mark.parametrize("path", ["train/r_1.png", "test/r_4.png"])
def test_truncated_image(scene, path):
    scene_dir, _ = scene
    truncate(scene_dir / path)
    name = path.split("/")[1].replace(".", r"\.")
    with pytest.raises(DatasetError, match=rf"{name}: cannot decode the image.*truncated"):
        load_blender(scene_dir, num_train_views=2)


def test_not_an_image(scene):
    scene_dir, _ = scene
    (scene_dir / "test" / "r_3.png").write_bytes(b"not a png at all")
    with pytest.raises(DatasetError, match=r"r_3\.png: cannot decode the image"):
        load_blender(scene_dir, num_train_views=2)


def test_images_of_mixed_sizes(scene):
    scene_dir, _ = scene
    write_png(scene_dir / "train" / "r_2.png", np.zeros((8, 8, 4)))
    with pytest.raises(DatasetError, match=r"r_2\.png: the image is 8x8 but r_0\.png is 8x6"):
        load_blender(scene_dir, num_train_views=3)


def test_image_that_cannot_be_halved(scene):
    scene_dir, _ = scene
    for index in range(9):
        write_png(scene_dir / "test" / f"r_{index}.png", np.zeros((5, 7, 4)))
    with pytest.raises(DatasetError, match=r"r_0\.png: a 7x5 image cannot be halved"):
        load_blender(scene_dir, num_train_views=1)


def test_pose_of_wrong_shape(scene):
    scene_dir, _ = scene
    meta = json.loads((scene_dir / "transforms_train.json").read_text())
    meta["frames"][1]["transform_matrix"] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    (scene_dir / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(
        DatasetError, match=r"transforms_train\.json: the transform_matrix of frame 1 has shape \(3, 3\)"
    ):
        load_blender(scene_dir, num_train_views=2)


def test_frame_without_file_path(scene):
    scene_dir, _ = scene
    meta = json.loads((scene_dir / "transforms_test.json").read_text())
    del meta["frames"][4]["file_path"]
    (scene_dir / "transforms_test.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms_test\.json: frame 4 has no 'file_path'"):
        load_blender(scene_dir, num_train_views=2)


def test_more_training_views_than_frames(scene):
    scene_dir, _ = scene
    with pytest.raises(DatasetError, match=r"transforms_train\.json: 6 training views asked for.*at most 5"):
        load_blender(scene_dir, num_train_views=6)


def test_dietnerf_protocol_needs_the_original_frames(scene):
    scene_dir, _ = scene
    with pytest.raises(DatasetError, match=r"transforms_train\.json: the DietNeRF protocol uses frame 26"):
        load_blender(scene_dir, num_train_views=1, protocol="dietnerf")
    with pytest.raises(DatasetError, match=r"transforms_train\.json.*uses frame 86"):
        load_blender(scene_dir, num_train_views=3, protocol="dietnerf")
    with pytest.raises(DatasetError, match=r"DietNeRF protocol defines 8.*data\.num_train_views"):
        load_blender(scene_dir, num_train_views=9, protocol="dietnerf")


# --- The real lego (skipped when the shared data is absent) ----------------------------------

needs_lego = pytest.mark.skipif(
    not (LEGO / "transforms_train.json").is_file(), reason="shared/data/nerf_synthetic/lego not present"
)


@pytest.fixture(scope="module")
def lego():
    """The MixNeRF protocol's 4-view lego with all 200 test views, loaded once and timed."""
    start = time.perf_counter()
    dataset = load_blender(LEGO, num_train_views=4)
    seconds = time.perf_counter() - start
    print(f"\nloaded lego: 4 train + {dataset.test.num_views} test views at 400x400 in {seconds:.2f} s")
    return dataset


@needs_lego
def test_lego_protocol_counts():
    train_frames = json.loads((LEGO / "transforms_train.json").read_text())["frames"]
    test_frames = json.loads((LEGO / "transforms_test.json").read_text())["frames"]
    assert (len(train_frames), len(test_frames)) == (100, 200)
    assert split_ids("mixnerf", 100, 200, 4, LEGO) == (list(range(4)), list(range(200)))
    assert split_ids("dietnerf", 100, 200, 8, LEGO) == (DIETNERF_IDS, list(range(0, 200, 8)))


@needs_lego
def test_lego_mixnerf_protocol(lego):
    assert lego.train.ids == (0, 1, 2, 3)
    assert lego.test.ids == tuple(range(200))
    assert lego.train.images.shape == (4, 400, 400, 3)
    assert lego.test.images.shape == (200, 400, 400, 3)
    assert np.all(np.isfinite(lego.test.images))
    assert 0.0 <= lego.test.images.min() and lego.test.images.max() <= 1.0
    meta = json.loads((LEGO / "transforms_train.json").read_text())
    assert lego.train.focal == pytest.approx(200.0 / math.tan(0.5 * meta["camera_angle_x"]), rel=1e-12)
    assert lego.train.focal == pytest.approx(555.555, abs=1e-2)
    for position in range(4):
        np.testing.assert_allclose(
            lego.train.camtoworlds[position],
            np.asarray(meta["frames"][position]["transform_matrix"])[:3],
            atol=1e-6,
        )


@needs_lego
def test_lego_cameras_circle_the_origin(lego):
    for views in (lego.train, lego.test):
        poses = views.camtoworlds.astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(poses[:, :, 3], axis=-1), 4.0311, atol=1e-3)
        # Each camera looks at the origin: its viewing axis (-z) passes within 1e-3 of it, and
        # the rotation is orthonormal.
        forward = -poses[:, :, 2]
        closest = poses[:, :, 3] - np.sum(poses[:, :, 3] * forward, axis=-1, keepdims=True) * forward
        assert np.max(np.linalg.norm(closest, axis=-1)) < 1e-3
        np.testing.assert_allclose(
            np.einsum("nji,njk->nik", poses[:, :, :3], poses[:, :, :3]),
            np.eye(3)[None].repeat(len(poses), 0),
            atol=1e-5,
        )


@needs_lego
def test_lego_central_rays_hit_the_object_region(lego):
    rays = rays_for_views(lego.train.select([0]), lego.near, lego.far)
    origins = np.asarray(rays.origins[0, 200, 200], np.float64)
    directions = np.asarray(rays.directions[0, 200, 200], np.float64)
    # The ray through the image centre passes next to the origin at a depth of about 4.03.
    depth = -np.dot(origins, directions) / np.dot(directions, directions)
    assert depth == pytest.approx(4.03, abs=0.05)
    assert np.linalg.norm(origins + depth * directions) < 0.05


@needs_lego
def test_lego_downsampled_copies_match_the_originals(lego):
    # test/ holds every 8th full-size view, test_400/ all 200 pre-halved ones; the loader reads
    # test_400/ for the full set (views 100 and 199 exist only there). A float64 box average of
    # the originals agrees within the copies' rounding (0.5/255 per RGBA channel, so about
    # 1/255 after compositing).
    assert not (LEGO / "test" / "r_100.png").exists() and not (LEGO / "test" / "r_199.png").exists()
    for frame in (0, 96, 192):
        original = np.asarray(Image.open(LEGO / "test" / f"r_{frame}.png"))
        expected = blender_reference_image(original, 2)
        assert np.max(np.abs(lego.test.images[frame] - expected)) < 1.01 / 255


@needs_lego
def test_lego_dietnerf_protocol():
    dataset = load_blender(LEGO, num_train_views=4, protocol="dietnerf", max_test_views=2)
    assert dataset.train.ids == (26, 86, 2, 55)
    # Of the 25 views 0, 8, ..., 192 the two evenly spaced ones are the first and the last.
    assert dataset.test.ids == (0, 192)
    assert dataset.test.images.shape == (2, 400, 400, 3)
    expected = blender_reference_image(np.asarray(Image.open(LEGO / "test" / "r_192.png")), 2)
    np.testing.assert_allclose(dataset.test.images[1], expected, atol=1e-6)


@needs_lego
def test_lego_downscaled_through_the_copies():
    # Test view 199 exists only in test_400/, so the split is read from the copies; training
    # view 0 from the 800x800 render. Both are the factor-1 images averaged over 8x8 blocks.
    full = load_blender(LEGO, num_train_views=1, max_test_views=2)
    dataset = load_blender(LEGO, num_train_views=1, max_test_views=2, downscale=8)
    assert dataset.test.ids == (0, 199)
    for views, full_views in ((dataset.train, full.train), (dataset.test, full.test)):
        assert views.images.shape == (views.num_views, 50, 50, 3)
        expected = full_views.images.astype(np.float64).reshape(-1, 50, 8, 50, 8, 3).mean(axis=(2, 4))
        np.testing.assert_allclose(views.images, expected, atol=1e-6)
        assert views.focal == pytest.approx(full_views.focal / 8, rel=1e-12)
        assert views.intrinsics is None
