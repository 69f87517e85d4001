"""Cameras, ray bundles, ray samples and normalised device coordinates.

Camera convention (NeRF/Blender, OpenGL): a camera-to-world matrix `[R | c]` maps camera
coordinates with x right, y up and the camera looking along -z to world coordinates. The
ray through the centre of pixel `(row, col)` has the unnormalised direction
`R @ ((col + 0.5 - cx) / focal, -(row + 0.5 - cy) / focal, -1)`, so `t` along that direction
is the depth along the camera axis (z-depth), and `||direction|| >= 1`.

Cameras with their own intrinsics (DTU, transforms.json scenes) give them as a pinhole matrix
`K` in the OpenCV pixel convention (`u = fx x / z + s y / z + cx`, `v = fy y / z + cy`, with y
down and z forward), the form that calibration files and `transforms.json` use. The ray
through pixel `(row, col)` is then `K^-1 (col + 0.5, row + 0.5, 1)` with y and z negated into
the OpenGL camera, so its camera z-component is still -1.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._custom_types import PoseStack

# An axis-aligned box: its lowest and highest corner.
Box = tuple[tuple[float, float, float], tuple[float, float, float]]


def radius_box(radius: float) -> Box | None:
    """The box `[-radius, radius]^3` that a config's `box_radius > 0` asks for (the scene
    lies inside it), or `None` for `box_radius = 0` (use the training rays' box instead)."""
    if radius <= 0:
        return None
    return (-float(radius),) * 3, (float(radius),) * 3


class RayBundle(eqx.Module):
    """A bundle of cone-shaped (or cylindrical) rays.

    **Fields:**

    - `origins`: ray origins.
    - `directions`: unnormalised directions; `t = 1` is one unit of camera depth.
    - `viewdirs`: the input of the view-dependent branch: unit view directions, except for
      NDC rays, whose view directions are the unnormalised world-space directions from
      before the NDC mapping (as in the released code; their norm is 1 at the image centre
      and grows towards the corners, about 1.26 at fern's).
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
        """Returns the same rays with the batch dimensions reshaped to `shape` (every field
        keeps its last axis)."""
        return jax.tree_util.tree_map(lambda x: x.reshape(*shape, x.shape[-1]), self)

    def __getitem__(self, index) -> "RayBundle":
        """The rays at `index` of the batch dimensions, every field alike."""
        return jax.tree_util.tree_map(lambda x: x[index], self)


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


def intrinsic_matrix(focal_x: float, focal_y: float, cx: float, cy: float) -> Float[np.ndarray, "3 3"]:
    """The pinhole matrix `K` (OpenCV pixel convention, no skew) of the given intrinsics."""
    return np.array([[focal_x, 0.0, cx], [0.0, focal_y, cy], [0.0, 0.0, 1.0]])


def intrinsic_directions(
    intrinsics: Float[np.ndarray, "*batch 3 3"], height: int, width: int
) -> Float[np.ndarray, "*batch height width 3"]:
    """Camera-space (OpenGL) unnormalised directions through every pixel centre (float64).

    **Arguments:**

    - `intrinsics`: pinhole matrices `K` in the OpenCV pixel convention (see the module
      docstring); skew is allowed, the last row must be `(0, 0, 1)`.
    - `height`, `width`: image size in pixels.

    **Returns:**

    Directions whose camera z-component is -1.
    """
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([cols + 0.5, rows + 0.5, np.ones_like(cols)], axis=-1)
    pixtocams = np.linalg.inv(np.asarray(intrinsics, np.float64))
    opencv_dirs = np.einsum("...ij,hwj->...hwi", pixtocams, pixels)
    # OpenCV (y down, z forward) to OpenGL (y up, z backward).
    return opencv_dirs * np.array([1.0, -1.0, -1.0])


def ndc_rays(
    origins: Float[np.ndarray, "*batch 3"],
    directions: Float[np.ndarray, "*batch 3"],
    focal_x: float,
    focal_y: float,
    width: int,
    height: int,
    near: float = 1.0,
) -> tuple[Float[np.ndarray, "*batch 3"], Float[np.ndarray, "*batch 3"]]:
    """Maps rays of a forward-facing scene into normalised device coordinates (NeRF, appendix C).

    The projection is that of a pinhole camera at the world origin looking along -z, with the
    given intrinsics and a principal point at the image centre; the far plane is at infinity.
    Each ray first moves its origin along itself onto the near plane `z = -near`, which becomes
    the NDC plane `z = -1`; the NDC direction then points from there to the projection of the
    ray's point at infinity, on the plane `z = +1`. So `t = 0` is the near plane and `t = 1`
    infinity, and the NDC sampling bounds are 0 and 1. Rays must point towards -z.

    **Arguments:**

    - `origins`, `directions`: world-space rays (directions need not be unit length).
    - `focal_x`, `focal_y`: focal lengths in pixels.
    - `width`, `height`: image size in pixels.
    - `near`: the world-space near plane's distance from the origin along -z.

    **Returns:**

    The NDC origins (all with z = -1) and the NDC directions (all with z-component 2).
    """
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    to_near = -(near + origins[..., 2]) / directions[..., 2]
    origins = origins + to_near[..., None] * directions
    scale_x = -2.0 * focal_x / width
    scale_y = -2.0 * focal_y / height
    # The shifted origins lie on z = -near, which NDC maps exactly to -1 (1 + 2 near / z);
    # writing -1 keeps the plane exact instead of off by a rounding error.
    origins_ndc = np.stack(
        [
            scale_x * origins[..., 0] / origins[..., 2],
            scale_y * origins[..., 1] / origins[..., 2],
            -np.ones_like(origins[..., 2]),
        ],
        axis=-1,
    )
    infinity_ndc = np.stack(
        [
            scale_x * directions[..., 0] / directions[..., 2],
            scale_y * directions[..., 1] / directions[..., 2],
            np.ones_like(directions[..., 2]),
        ],
        axis=-1,
    )
    return origins_ndc, infinity_ndc - origins_ndc


def shift_origins_to_plane(
    origins: Float[np.ndarray, "*batch 3"], directions: Float[np.ndarray, "*batch 3"], plane_z: float
) -> Float[np.ndarray, "*batch 3"]:
    """Moves every ray's origin along the ray onto the world plane `z = plane_z`.

    RegNeRF's DTU rays start on the plane through the average camera, perpendicular to its
    viewing direction (`z = 0` after recentring), and the protocol's near and far bounds
    (0.5 and 3.5) count from there; rays parallel to the plane must not occur.
    """
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    to_plane = (plane_z - origins[..., 2]) / directions[..., 2]
    return origins + to_plane[..., None] * directions


def camera_rays(
    camtoworlds: PoseStack,
    focal: float,
    height: int,
    width: int,
    near: float,
    far: float,
    *,
    intrinsics: Float[np.ndarray, "num_views 3 3"] | None = None,
    ndc: bool = False,
    ndc_camera: tuple[float, int, int] | None = None,
    origin_plane_z: float | None = None,
) -> RayBundle:
    """The rays through every pixel centre of a stack of pinhole cameras.

    **Arguments:**

    - `camtoworlds`: camera-to-world matrices (OpenGL convention, see the module docstring).
    - `focal`: focal length in pixels (used when `intrinsics` is `None`, and for NDC).
    - `height`, `width`: image size in pixels.
    - `near`, `far`: sampling bounds along the unnormalised directions.
    - `intrinsics`: per-view pinhole matrices `K` (OpenCV pixel convention); `None` for a
      principal point at the image centre and `focal` on both axes.
    - `ndc`: map the rays into normalised device coordinates (`ndc_rays`, near plane 1) for
      forward-facing scenes; the frustums are then cylinders whose radius is the spacing of
      neighbouring NDC origins, as in mip-NeRF's and RegNeRF's LLFF rays.
    - `ndc_camera`: `(focal, width, height)` of the camera that defines the NDC space (the
      scene's training cameras); `None`: these cameras' own. A camera with another field of
      view (a viewer's) must map its rays into the scene's NDC space, not its own.
    - `origin_plane_z`: move the origins along their rays onto the world plane
      `z = origin_plane_z` (RegNeRF's DTU rays); `None` keeps them at the camera centres.

    **Returns:**

    A float32 `RayBundle` with batch shape `(num_views, height, width)`.
    """
    poses = np.asarray(camtoworlds, np.float64)
    if intrinsics is None:
        camera_dirs = pixel_directions(focal, height, width)
        directions = np.einsum("nij,hwj->nhwi", poses[:, :3, :3], camera_dirs)
    else:
        camera_dirs = intrinsic_directions(intrinsics, height, width)
        directions = np.einsum("nij,nhwj->nhwi", poses[:, :3, :3], camera_dirs)
    origins = np.broadcast_to(poses[:, None, None, :3, 3], directions.shape)
    if ndc:
        # The released code feeds the pre-NDC world directions, unnormalised, to the view branch.
        viewdirs = directions
        ndc_focal, ndc_width, ndc_height = (focal, width, height) if ndc_camera is None else ndc_camera
        origins, directions = ndc_rays(origins, directions, ndc_focal, ndc_focal, ndc_width, ndc_height)
        # The NDC rays are nearly parallel, so the frustum's size is set by the spacing of the
        # origins on the near plane, averaged over both image axes.
        dx = np.linalg.norm(origins[:, :-1] - origins[:, 1:], axis=-1)
        dx = np.concatenate([dx, dx[:, -2:-1]], axis=1)
        dy = np.linalg.norm(origins[:, :, :-1] - origins[:, :, 1:], axis=-1)
        dy = np.concatenate([dy, dy[:, :, -2:-1]], axis=2)
        radii = 0.5 * (dx + dy)[..., None] * 2 / np.sqrt(12)
    else:
        viewdirs = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
        # mip-NeRF: the base radius is the distance between neighbouring pixels' directions
        # at t = 1, scaled by 2/sqrt(12) so that the cone's variance matches the pixel's. The
        # neighbour is the next pixel along the image's vertical axis (the next row), as in the
        # released code; the last row reuses the distance above it (for a pinhole camera every
        # row's distance is the same).
        if height < 2:
            raise ValueError(f"cone radii need images of at least 2 rows, got {height}")
        dy = np.linalg.norm(directions[:, :-1] - directions[:, 1:], axis=-1)
        dy = np.concatenate([dy, dy[:, -1:]], axis=1)
        radii = dy[..., None] * 2 / np.sqrt(12)
    if origin_plane_z is not None:
        origins = shift_origins_to_plane(origins, directions, origin_plane_z)
    ones = np.ones(directions.shape[:-1] + (1,))
    return RayBundle(
        origins=jnp.asarray(origins, jnp.float32),
        directions=jnp.asarray(directions, jnp.float32),
        viewdirs=jnp.asarray(viewdirs, jnp.float32),
        radii=jnp.asarray(radii, jnp.float32),
        near=jnp.asarray(near * ones, jnp.float32),
        far=jnp.asarray(far * ones, jnp.float32),
    )
