"""What a user takes away from the predictive pass: depth and its spread as float arrays in
scene units, and a coloured point cloud with each point's uncertainty.

The renderer's depth is a distance along the ray in the ray space the scene trains in. For
bounded scenes that is the world (the camera's unnormalised directions: a camera z-depth);
for forward-facing LLFF scenes it is the NDC ray parameter `t` in [0, 1), which maps back to
the world through the inverse of `mixnerf_eqx._nn.rays.ndc_rays` (`z = -near / (1 - t)` on
the NDC frame's axis). Here every depth is converted to world points and to the camera's
z-depth in scene units (the convention of `Views.depths`). Quantiles are carried through the
conversion exactly (it is monotone along each ray); a standard deviation would not be, so
the spread exported is the central interval's two ends.
"""

from pathlib import Path

import numpy as np
from jaxtyping import Float
from plyfile import PlyData, PlyElement

from ..data import Views, rays_for_views

# NDC rays are built with the near plane at distance 1 (`ndc_rays`' default).
_NDC_NEAR = 1.0


def world_points(
    views: Views, index: int, t: Float[np.ndarray, "*batch height width"], near: float, far: float
) -> tuple[Float[np.ndarray, "*batch height width 3"], Float[np.ndarray, "*batch height width"]]:
    """The world points at ray distance `t` along view `index`'s rays (any stack of maps in
    front: the rays are built once), and their camera z-depths (distance along the camera's
    viewing axis, scene units). For an NDC scene, `t = 1` (the far bound, infinitely far)
    gives a NaN point and an infinite depth."""
    one = views.select([index])
    rays = rays_for_views(one, near, far)
    origins = np.asarray(rays.origins[0], np.float64)
    directions = np.asarray(rays.directions[0], np.float64)
    t = np.asarray(t, np.float64)
    points = origins + t[..., None] * directions
    camtoworld = np.asarray(one.camtoworlds[0], np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if views.ndc:
            # Inverse NDC: z' = 1 + 2 near / z, x' = -(2 f / W) x / z, y' = -(2 f / H) y / z.
            # t = 1 (a ray that reports its far bound) is the point at infinity: no point.
            z = 2.0 * _NDC_NEAR / (points[..., 2] - 1.0)
            x = points[..., 0] * z / (-2.0 * views.focal / views.width)
            y = points[..., 1] * z / (-2.0 * views.focal / views.height)
            points = np.where((t < 1.0)[..., None], np.stack([x, y, z], axis=-1), np.nan)
        local = (points - camtoworld[:, 3]) @ camtoworld[:, :3]
    depth = np.where(np.isfinite(local[..., 2]), -local[..., 2], np.inf)
    return points, depth


def _interval_index(masses: np.ndarray, wanted: float = 0.9) -> int:
    """The interval mass exported as the spread: `wanted` if asked for, else the nearest."""
    return int(np.argmin(np.abs(np.asarray(masses) - wanted)))


def write_depth_exports(
    folder: Path, views: Views, maps: dict[str, np.ndarray], *, near: float, far: float, min_opacity: float = 0.5
) -> list[Path]:
    """Per view, `test_NNN_depth.npy` (the median termination distance as a camera z-depth,
    float32, scene units), `test_NNN_depth_interval.npy` (shape `(masses, 2, height, width)`:
    each interval's lower and upper end, the same units; the masses are `maps["masses"]`) and
    `test_NNN_points.ply`: one vertex per pixel whose opacity is at least `min_opacity` and
    whose depth is finite, with `x y z`, the rendered colour (`red green blue`, 0-255), its
    colour spread (`colour_std`, the mixture's standard deviation averaged over channels),
    `depth_lower` and `depth_upper` (the 0.9 interval's ends, or the nearest mass's) and
    `opacity`. Returns the paths written."""
    written = []
    chosen = _interval_index(maps["masses"])
    for index, view_id in enumerate(views.ids):
        stem = folder / f"test_{view_id:03d}"
        # One conversion for the median and every interval's ends: (1 + 2 masses, H, W).
        stack = np.concatenate(
            [maps["depth_median"][index][None], maps["depth_lower"][:, index], maps["depth_upper"][:, index]]
        )
        all_points, all_depths = world_points(views, index, stack, near, far)
        points, depth = all_points[0], all_depths[0]
        count = len(maps["masses"])
        ends = np.stack([all_depths[1 : 1 + count], all_depths[1 + count :]], axis=1)  # (masses, 2, H, W)
        np.save(f"{stem}_depth.npy", depth.astype(np.float32))
        np.save(f"{stem}_depth_interval.npy", ends.astype(np.float32))
        keep = (maps["acc"][index] >= min_opacity) & np.all(np.isfinite(points), axis=-1) & np.isfinite(depth)
        colours = np.clip(np.rint(maps["rgb"][index][keep] * 255.0), 0, 255).astype(np.uint8)
        vertex = np.empty(
            int(keep.sum()),
            dtype=[
                ("x", "f4"),
                ("y", "f4"),
                ("z", "f4"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
                ("colour_std", "f4"),
                ("depth_lower", "f4"),
                ("depth_upper", "f4"),
                ("opacity", "f4"),
            ],
        )
        for axis, name in enumerate("xyz"):
            vertex[name] = points[keep][:, axis]
        for channel, name in enumerate(("red", "green", "blue")):
            vertex[name] = colours[:, channel]
        vertex["colour_std"] = maps["colour_std"][index][keep].mean(axis=-1)
        vertex["depth_lower"] = ends[chosen, 0][keep]
        vertex["depth_upper"] = ends[chosen, 1][keep]
        vertex["opacity"] = maps["acc"][index][keep]
        path = Path(f"{stem}_points.ply")
        PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))
        written += [Path(f"{stem}_depth.npy"), Path(f"{stem}_depth_interval.npy"), path]
    return written
