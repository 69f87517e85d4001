"""The reprojection ceiling of the built-in scene (benchmarks/builtin_ceiling.py)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import builtin_ceiling  # noqa: E402

from mixnerf_eqx.data import procedural as scene  # noqa: E402


def test_projection_inverts_the_pixel_rays():
    # A point on a pixel's ray projects back onto that pixel's centre, and bilinear sampling
    # at a pixel centre returns the pixel itself.
    resolution = 12
    poses = scene._train_poses(2)
    origins, directions = builtin_ceiling._test_rays(poses, resolution)
    depths = np.random.default_rng(0).uniform(2.0, 6.0, origins.shape[:-1])
    points = origins + depths[..., None] * directions
    coords, in_front = builtin_ceiling._project(points[1], poses[1], scene._focal(resolution), resolution)
    cols, rows = np.meshgrid(np.arange(resolution) + 0.5, np.arange(resolution) + 0.5)
    assert in_front.all()
    # The stored poses are float32, so their rotations are orthonormal to about 1e-7 only.
    np.testing.assert_allclose(coords[..., 0], cols, atol=1e-5)
    np.testing.assert_allclose(coords[..., 1], rows, atol=1e-5)
    image = np.random.default_rng(1).uniform(size=(resolution, resolution, 3))
    centres = np.stack([cols, rows], axis=-1)
    np.testing.assert_allclose(builtin_ceiling._bilinear(image, centres), image, atol=1e-12)
    # Half a pixel to the right: the mean of neighbouring columns.
    shifted = builtin_ceiling._bilinear(image, centres[:, :-1] + np.array([0.5, 0.0]))
    np.testing.assert_allclose(shifted, 0.5 * (image[:, :-1] + image[:, 1:]), atol=1e-12)


def test_ceiling_bounds(monkeypatch):
    # The exact reprojection is far better than the bilinear one, and almost every object
    # pixel is seen by some training camera.
    result = builtin_ceiling.ceiling(24, 4, 4)
    assert 0 <= result["unseen_fraction_of_objects"] < 0.05
    assert result["exact"]["psnr"] > result["bilinear"]["psnr"] + 3.0
    assert result["exact"]["psnr_if_unseen_were_right"] >= result["exact"]["psnr"]
    # Reprojected from the held-out poses themselves, the exact estimate reproduces the truth
    # up to float rounding: the same function with training cameras = test cameras.
    monkeypatch.setattr(scene, "_train_poses", scene._test_poses)
    same = builtin_ceiling.ceiling(24, 4, 4)
    assert same["unseen_fraction_of_objects"] == 0.0
    assert same["exact"]["psnr"] > 60.0 and same["bilinear"]["psnr"] > 60.0
