"""Camera rays against closed forms: cone radii, NDC view directions."""

import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx._nn.rays import intrinsic_matrix


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_cone_radii_come_from_the_vertical_neighbour():
    """With focal lengths fx != fy, neighbouring rows' directions differ by exactly
    `R (0, 1/fy, 0)`, so every base radius is `2 / (sqrt(12) fy)` (the released code's rule);
    the horizontal neighbour would give `1/fx` instead."""
    fx, fy, height, width = 20.0, 32.0, 6, 9
    pose = np.eye(4)
    pose[:3, :3] = _rotation(0)
    pose[:3, 3] = [0.3, -1.0, 4.0]
    k = intrinsic_matrix(fx, fy, 4.1, 2.7)
    rays = mx.nn.camera_rays(pose[None, :3], fx, height, width, 2.0, 6.0, intrinsics=k[None])
    np.testing.assert_allclose(np.asarray(rays.radii), 2 / (np.sqrt(12) * fy), rtol=1e-5)


def test_ndc_view_directions_are_the_unnormalised_world_directions():
    """LLFF rays feed the view branch the world-space directions from before the NDC mapping,
    unnormalised (`R (x/f, -y/f, -1)`), as the released code does."""
    focal, height, width = 30.0, 8, 12
    rotation = _rotation(1)
    # A forward-facing camera: looks roughly along -z.
    rotation = rotation if rotation[2, 2] > 0.5 else np.eye(3)
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = [0.1, 0.2, 0.0]
    rays = mx.nn.camera_rays(pose[None, :3], focal, height, width, 0.0, 1.0, ndc=True)
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    camera = np.stack(
        [(cols + 0.5 - width / 2) / focal, -(rows + 0.5 - height / 2) / focal, -np.ones(rows.shape)], -1
    )
    expected = camera @ rotation.T
    np.testing.assert_allclose(np.asarray(rays.viewdirs[0]), expected, rtol=1e-6, atol=1e-6)
    norms = np.linalg.norm(np.asarray(rays.viewdirs[0]), axis=-1)
    assert norms.min() >= 1.0 - 1e-6 and norms.max() > 1.02


def test_bounded_view_directions_are_unit_vectors():
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 4.0]
    rays = mx.nn.camera_rays(pose[None, :3], 10.0, 5, 7, 2.0, 6.0)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(rays.viewdirs), axis=-1), 1.0, rtol=1e-6)
