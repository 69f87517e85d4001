"""Cameras, ray bundles and ray samples.

Camera convention (NeRF/Blender, OpenGL): a camera-to-world matrix `[R | c]` maps camera
coordinates with x right, y up and the camera looking along -z to world coordinates. The
ray through the centre of pixel `(row, col)` has the unnormalised direction
`R @ ((col + 0.5 - cx) / focal, -(row + 0.5 - cy) / focal, -1)`, so `t` along that direction
is the depth along the camera axis (z-depth), and `||direction|| >= 1`.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._custom_types import PoseStack


class RayBundle(eqx.Module):
    """A bundle of cone-shaped (or cylindrical) rays.

    **Fields:**

    - `origins`: ray origins.
    - `directions`: unnormalised directions; `t = 1` is one unit of camera depth.
    - `viewdirs`: unit view directions, the input of the view-dependent branch.
    - `radii`: base radii of the cones (mip-NeRF: pixel footprint at `t = 1` times 2/sqrt(12)).
    - `near`, `far`: the sampling bounds in units of `t`.
    """

    origins: Float[Array, "*batch 3"]
    directions: Float[Array, "*batch 3"]
    viewdirs: Float[Array, "*batch 3"]
    radii: Float[Array, "*batch 1"]
    near: Float[Array, "*batch 1"]
    far: Float[Array, "*batch 1"]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.origins.shape[:-1]

    def reshape(self, *shape: int) -> "RayBundle":
        """Returns the same rays with the batch dimensions reshaped to `shape`."""
        return RayBundle(
            origins=self.origins.reshape(*shape, 3),
            directions=self.directions.reshape(*shape, 3),
            viewdirs=self.viewdirs.reshape(*shape, 3),
            radii=self.radii.reshape(*shape, 1),
            near=self.near.reshape(*shape, 1),
            far=self.far.reshape(*shape, 1),
        )

    def __getitem__(self, index) -> "RayBundle":
        return RayBundle(
            origins=self.origins[index],
            directions=self.directions[index],
            viewdirs=self.viewdirs[index],
            radii=self.radii[index],
            near=self.near[index],
            far=self.far[index],
        )


class RaySamples(eqx.Module):
    """Samples along one ray (or a batch of rays): interval edges and frustum Gaussians.

    **Fields:**

    - `means`: means of the frustum Gaussians, in world space.
    - `covs`: diagonals of the frustum Gaussians' covariances.
    - `t_edges`: sorted interval edges; sample `i` is the frustum between edges `i` and `i+1`.
    """

    means: Float[Array, "*batch num_samples 3"]
    covs: Float[Array, "*batch num_samples 3"]
    t_edges: Float[Array, "*batch num_samples+1"]


def pixel_directions(
    focal: float, height: int, width: int, cx: float | None = None, cy: float | None = None
) -> Float[np.ndarray, "height width 3"]:
    """Camera-space unnormalised directions through every pixel centre (float64)."""
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(cols + 0.5 - cx) / focal, -(rows + 0.5 - cy) / focal, -np.ones_like(cols)], axis=-1)


def camera_rays(
    camtoworlds: PoseStack,
    focal: float,
    height: int,
    width: int,
    near: float,
    far: float,
) -> RayBundle:
    """The rays through every pixel centre of a stack of pinhole cameras.

    **Arguments:**

    - `camtoworlds`: camera-to-world matrices (OpenGL convention, see the module docstring).
    - `focal`: focal length in pixels.
    - `height`, `width`: image size in pixels.
    - `near`, `far`: sampling bounds along the unnormalised directions.

    **Returns:**

    A float32 `RayBundle` with batch shape `(num_views, height, width)`.
    """
    camera_dirs = pixel_directions(focal, height, width)
    rotations = np.asarray(camtoworlds, np.float64)[:, :3, :3]
    directions = np.einsum("nij,hwj->nhwi", rotations, camera_dirs)
    origins = np.broadcast_to(np.asarray(camtoworlds, np.float64)[:, None, None, :3, 3], directions.shape)
    viewdirs = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    # mip-NeRF: the base radius is the distance between neighbouring pixels' directions
    # at t = 1, scaled by 2/sqrt(12) so that the cone's variance matches the pixel's.
    dx = np.linalg.norm(directions[:, :, :-1] - directions[:, :, 1:], axis=-1)
    dx = np.concatenate([dx, dx[:, :, -2:-1]], axis=2)
    radii = dx[..., None] * 2 / np.sqrt(12)
    ones = np.ones(directions.shape[:-1] + (1,))
    return RayBundle(
        origins=jnp.asarray(origins, jnp.float32),
        directions=jnp.asarray(directions, jnp.float32),
        viewdirs=jnp.asarray(viewdirs, jnp.float32),
        radii=jnp.asarray(radii, jnp.float32),
        near=jnp.asarray(near * ones, jnp.float32),
        far=jnp.asarray(far * ones, jnp.float32),
    )
