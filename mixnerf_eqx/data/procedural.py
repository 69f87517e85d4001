"""The built-in procedural scene: a few analytic shapes rendered exactly by ray casting.

The scene needs no files and is generated deterministically in float64 numpy, so it serves
both as the default training scene and as the fixture of the tests. It is Blender-like: a
textured sphere, a box with coloured faces and a banded cylinder stand on a finite
checkerboard disc, seen by cameras on a sphere of radius 4 around the origin against a white
background. Every pixel is rendered by intersecting its pixel-centre ray with the analytic
shapes (no anti-aliasing), so colour and depth are exact for that ray.

Shading is ambient + Lambertian + Blinn-Phong with hard shadows from one directional light.
The specular term makes the appearance view dependent, the textures give photometric cues,
and the occlusions make the geometry ambiguous from a few views, which is what a few-shot
NeRF has to cope with.
"""

from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

from .._custom_types import DepthStack, ImageStack
from .._nn.rays import pixel_directions
from ._dataset import Dataset, Views

__all__ = ["make_builtin_scene", "split_angles"]

NEAR = 2.0
FAR = 6.0
FOV_DEGREES = 40.0
CAMERA_RADIUS = 4.0
LOOK_AT = np.array([0.0, 0.0, 0.3])
MAX_VIEWS = 64

GROUND_RADIUS = 1.2
GROUND_CELL = 0.25
SPHERE_CENTER = np.array([0.35, -0.35, 0.42])
SPHERE_RADIUS = 0.42
BOX_MIN = np.array([-0.75, -0.1, 0.0])
BOX_MAX = np.array([-0.2, 0.45, 0.6])
CYLINDER_CENTER = np.array([0.4, 0.55])
CYLINDER_RADIUS = 0.18
CYLINDER_HEIGHT = 0.85

LIGHT_DIRECTION = np.array([0.45, -0.55, 1.0]) / np.linalg.norm([0.45, -0.55, 1.0])
AMBIENT = 0.3
DIFFUSE = 0.7
SPECULAR = 0.35
SHININESS = 40.0

# Elevations (degrees) cycled through by the training and test cameras. The sets are
# disjoint, so the two splits cannot share a pose whatever the numbers of views.
_TRAIN_ELEVATIONS = (28.0, 40.0)
_TEST_ELEVATIONS = (20.0, 34.0, 46.0)
# Validation cameras are picked from a 1-degree grid over this band of elevations (that of the
# test cameras) and every azimuth.
_VAL_ELEVATION_BAND = (20.0, 46.0)
# An azimuth offset that keeps the cameras off the scene's axes, where the box faces would
# be seen exactly edge-on.
_AZIMUTH_OFFSET = np.deg2rad(17.0)

# Shape ids, in the order `_intersect_scene` stacks them.
_GROUND, _SPHERE, _BOX, _CYLINDER = range(4)


def intersect_sphere(
    origins: Float[np.ndarray, "*batch 3"],
    directions: Float[np.ndarray, "*batch 3"],
    center: Float[np.ndarray, "3"],
    radius: float,
) -> tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"]]:
    """Intersects rays with a sphere.

    **Arguments:**

    - `origins`, `directions`: the rays (directions need not be unit length).
    - `center`, `radius`: the sphere.

    **Returns:**

    The nearest positive `t` (`inf` for a miss) and the outward unit normals there.
    """
    offsets = origins - center
    a = np.sum(directions * directions, axis=-1)
    half_b = np.sum(offsets * directions, axis=-1)
    c = np.sum(offsets * offsets, axis=-1) - radius**2
    discriminant = half_b**2 - a * c
    root = np.sqrt(np.maximum(discriminant, 0.0))
    t_near = (-half_b - root) / a
    t_far = (-half_b + root) / a
    # The far root only matters for an origin inside the sphere.
    t = np.where(t_near > 0, t_near, t_far)
    t = np.where((discriminant >= 0) & (t > 0), t, np.inf)
    normals = (origins + _finite(t)[..., None] * directions - center) / radius
    return t, normals


def intersect_box(
    origins: Float[np.ndarray, "*batch 3"],
    directions: Float[np.ndarray, "*batch 3"],
    box_min: Float[np.ndarray, "3"],
    box_max: Float[np.ndarray, "3"],
) -> tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"]]:
    """Intersects rays with an axis-aligned box (the slab method).

    **Arguments:**

    - `origins`, `directions`: the rays (directions need not be unit length).
    - `box_min`, `box_max`: opposite corners of the box.

    **Returns:**

    The entry `t` (`inf` for a miss or an origin inside the box) and the outward unit
    normals of the entry faces.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo = (box_min - origins) / directions
        t_hi = (box_max - origins) / directions
    # fmin/fmax drop the NaN of a ray lying exactly in a slab's plane.
    t_enter_axes = np.fmin(t_lo, t_hi)
    t_exit_axes = np.fmax(t_lo, t_hi)
    t_enter = np.max(t_enter_axes, axis=-1)
    t_exit = np.min(t_exit_axes, axis=-1)
    t = np.where((t_enter <= t_exit) & (t_enter > 0), t_enter, np.inf)
    axis = np.argmax(t_enter_axes, axis=-1)
    hit_axis = np.arange(3) == axis[..., None]
    normals = np.where(hit_axis, -np.sign(directions), 0.0)
    return t, normals


def intersect_cylinder(
    origins: Float[np.ndarray, "*batch 3"],
    directions: Float[np.ndarray, "*batch 3"],
    center_xy: Float[np.ndarray, "2"],
    radius: float,
    height: float,
) -> tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"]]:
    """Intersects rays with a vertical cylinder standing on the plane `z = 0`.

    The cylinder has a top cap but no bottom cap: the bottom rests on the ground and can
    never be seen.

    **Arguments:**

    - `origins`, `directions`: the rays (directions need not be unit length).
    - `center_xy`: the axis' position in the ground plane.
    - `radius`, `height`: the cylinder's size.

    **Returns:**

    The nearest positive `t` (`inf` for a miss) and the outward unit normals there.
    """
    offsets = origins[..., :2] - center_xy
    flat_dirs = directions[..., :2]
    a = np.sum(flat_dirs * flat_dirs, axis=-1)
    half_b = np.sum(offsets * flat_dirs, axis=-1)
    c = np.sum(offsets * offsets, axis=-1) - radius**2
    discriminant = half_b**2 - a * c
    root = np.sqrt(np.maximum(discriminant, 0.0))
    # A vertical ray (a = 0) never meets the side wall; the cap handles it.
    safe_a = np.where(a > 0, a, 1.0)
    side_valid = (discriminant >= 0) & (a > 0)
    t_side = np.full(a.shape, np.inf)
    for sign in (1.0, -1.0):
        t_root = (-half_b - sign * root) / safe_a
        z = origins[..., 2] + t_root * directions[..., 2]
        valid = side_valid & (t_root > 0) & (z >= 0) & (z <= height)
        t_side = np.where(valid & (t_root < t_side), t_root, t_side)

    with np.errstate(divide="ignore", invalid="ignore"):
        t_cap = (height - origins[..., 2]) / directions[..., 2]
    cap_xy = offsets + _finite(t_cap)[..., None] * flat_dirs
    cap_valid = (t_cap > 0) & (np.sum(cap_xy * cap_xy, axis=-1) <= radius**2)
    t_cap = np.where(cap_valid, t_cap, np.inf)

    t = np.minimum(t_side, t_cap)
    side_xy = (offsets + _finite(t)[..., None] * flat_dirs) / radius
    side_normals = np.concatenate([side_xy, np.zeros_like(side_xy[..., :1])], axis=-1)
    cap_normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), side_normals.shape)
    normals = np.where((t_cap < t_side)[..., None], cap_normals, side_normals)
    return t, normals


def intersect_ground(
    origins: Float[np.ndarray, "*batch 3"],
    directions: Float[np.ndarray, "*batch 3"],
    radius: float,
) -> tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"]]:
    """Intersects rays with the ground: a disc of `radius` in the plane `z = 0`.

    The disc is one-sided: it is only seen from above, which all cameras are. A finite
    ground lets the rays past its edge reach the white background, as in Blender scenes.

    **Arguments:**

    - `origins`, `directions`: the rays (directions need not be unit length).
    - `radius`: the disc's radius, centred on the origin.

    **Returns:**

    The positive `t` of the hit (`inf` for a miss) and the unit normals (`+z`).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origins[..., 2] / directions[..., 2]
    points_xy = origins[..., :2] + _finite(t)[..., None] * directions[..., :2]
    valid = (directions[..., 2] < 0) & (t > 0)
    valid &= np.sum(points_xy * points_xy, axis=-1) <= radius**2
    t = np.where(valid, t, np.inf)
    normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), directions.shape)
    return t, normals


def nearest_hit(
    hits: list[tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"]]],
) -> tuple[Float[np.ndarray, "*batch"], Float[np.ndarray, "*batch 3"], np.ndarray]:
    """Combines the hits of several shapes into the nearest one per ray.

    **Arguments:**

    - `hits`: one `(t, normals)` pair per shape, as returned by the `intersect_*` functions.

    **Returns:**

    The nearest `t` (`inf` where every shape is missed), its normals, and the index of the
    shape hit (`-1` for a miss).
    """
    ts = np.stack([t for t, _ in hits])
    normals = np.stack([np.broadcast_to(n, ts.shape[1:] + (3,)) for _, n in hits])
    index = np.argmin(ts, axis=0)
    t = np.take_along_axis(ts, index[None], axis=0)[0]
    normal = np.take_along_axis(normals, index[None, ..., None], axis=0)[0]
    index = np.where(np.isfinite(t), index, -1)
    return t, normal, index


def _finite(t: np.ndarray) -> np.ndarray:
    # Misses carry t = inf; zeroing them keeps the dependent arithmetic free of inf/NaN.
    return np.where(np.isfinite(t), t, 0.0)


def _intersect_scene(
    origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return nearest_hit(
        [
            intersect_ground(origins, directions, GROUND_RADIUS),
            intersect_sphere(origins, directions, SPHERE_CENTER, SPHERE_RADIUS),
            intersect_box(origins, directions, BOX_MIN, BOX_MAX),
            intersect_cylinder(origins, directions, CYLINDER_CENTER, CYLINDER_RADIUS, CYLINDER_HEIGHT),
        ]
    )


def _checker(*coords: np.ndarray) -> np.ndarray:
    return np.sum([np.floor(c) for c in coords], axis=0) % 2


def _mix(mask: np.ndarray, colour_a, colour_b) -> np.ndarray:
    return np.where(mask[..., None] > 0, np.asarray(colour_b), np.asarray(colour_a))


def _albedo(points: np.ndarray, normals: np.ndarray, shape_ids: np.ndarray) -> np.ndarray:
    """The textured base colour of every hit point (white for misses)."""
    albedo = np.ones(points.shape)

    ground = _checker(points[..., 0] / GROUND_CELL, points[..., 1] / GROUND_CELL)
    ground_rgb = _mix(ground, (0.9, 0.86, 0.74), (0.2, 0.45, 0.5))
    albedo = np.where((shape_ids == _GROUND)[..., None], ground_rgb, albedo)

    local = (points - SPHERE_CENTER) / SPHERE_RADIUS
    longitude = np.arctan2(local[..., 1], local[..., 0])
    colatitude = np.arccos(np.clip(local[..., 2], -1.0, 1.0))
    sphere = _checker(longitude * 8 / (2 * np.pi), colatitude * 5 / np.pi)
    sphere_rgb = _mix(sphere, (0.85, 0.15, 0.12), (0.95, 0.8, 0.2))
    albedo = np.where((shape_ids == _SPHERE)[..., None], sphere_rgb, albedo)

    # One colour per face, modulated by a checker in the face's own coordinates so that
    # every face carries texture.
    face_colours = np.array(
        [
            [0.2, 0.35, 0.85],  # -x
            [0.25, 0.7, 0.3],  # +x
            [0.6, 0.3, 0.75],  # -y
            [0.95, 0.55, 0.15],  # +y
            [0.5, 0.5, 0.5],  # -z
            [0.92, 0.92, 0.88],  # +z
        ]
    )
    axis = np.argmax(np.abs(normals), axis=-1)
    face = 2 * axis + (np.take_along_axis(normals, axis[..., None], -1)[..., 0] > 0)
    # The coordinate along the normal sits exactly on a checker edge for some faces, where
    # rounding would make the texture flicker from pixel to pixel: leave it out.
    in_face = np.where(np.abs(normals) > 0.5, 0.0, points / 0.15)
    box = _checker(*(in_face[..., i] for i in range(3)))
    box_rgb = face_colours[face] * (1.0 - 0.3 * box[..., None])
    albedo = np.where((shape_ids == _BOX)[..., None], box_rgb, albedo)

    offsets = points[..., :2] - CYLINDER_CENTER
    angle = np.arctan2(offsets[..., 1], offsets[..., 0])
    bands = _checker(points[..., 2] / 0.14, angle * 6 / (2 * np.pi))
    cylinder_rgb = _mix(bands, (0.95, 0.95, 0.95), (0.15, 0.55, 0.25))
    albedo = np.where((shape_ids == _CYLINDER)[..., None], cylinder_rgb, albedo)
    return albedo


def shade(
    albedo: Float[np.ndarray, "*batch channels"],
    normals: Float[np.ndarray, "*batch 3"],
    viewdirs: Float[np.ndarray, "*batch 3"],
    visibility: Float[np.ndarray, "*batch"],
    specular_strength: float = SPECULAR,
) -> Float[np.ndarray, "*batch channels"]:
    """Ambient + Lambertian + Blinn-Phong shading from the scene's directional light.

    **Arguments:**

    - `albedo`: base colours.
    - `normals`: unit surface normals.
    - `viewdirs`: unit directions from the camera towards the surface.
    - `visibility`: 1 where the light reaches the point, 0 in shadow.
    - `specular_strength`: the weight of the (white) highlight; 0 makes the shading
      view-independent.

    **Returns:**

    Colours clipped to [0, 1].
    """
    facing = _facing(normals, viewdirs)
    n_dot_l = np.sum(facing * LIGHT_DIRECTION, axis=-1)
    lit = visibility * (n_dot_l > 0)
    diffuse = DIFFUSE * lit * np.maximum(n_dot_l, 0.0)
    halfway = LIGHT_DIRECTION - viewdirs
    halfway = halfway / np.linalg.norm(halfway, axis=-1, keepdims=True)
    n_dot_h = np.maximum(np.sum(facing * halfway, axis=-1), 0.0)
    specular = specular_strength * lit * n_dot_h**SHININESS
    rgb = albedo * (AMBIENT + diffuse)[..., None] + specular[..., None]
    return np.clip(rgb, 0.0, 1.0)


def _facing(normals: np.ndarray, viewdirs: np.ndarray) -> np.ndarray:
    # The side of the surface that faces the camera, whichever way the stored normal points.
    return np.where(np.sum(normals * viewdirs, -1, keepdims=True) > 0, -normals, normals)


def _look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """An OpenGL camera-to-world matrix at `position` looking at `target`, `+z` up."""
    backward = position - target
    backward = backward / np.linalg.norm(backward)
    right = np.cross(np.array([0.0, 0.0, 1.0]), backward)
    right = right / np.linalg.norm(right)
    up = np.cross(backward, right)
    return np.concatenate([np.stack([right, up, backward], axis=1), position[:, None]], axis=1)


def _orbit_poses(azimuths: np.ndarray, elevations: np.ndarray) -> np.ndarray:
    """Cameras on the sphere of radius `CAMERA_RADIUS`, all looking at `LOOK_AT`."""
    positions = CAMERA_RADIUS * np.stack(
        [
            np.cos(elevations) * np.cos(azimuths),
            np.cos(elevations) * np.sin(azimuths),
            np.sin(elevations),
        ],
        axis=-1,
    )
    poses = np.stack([_look_at(p, LOOK_AT) for p in positions])
    # Render from the float32 poses that the dataset stores, so that the stored images and
    # depths are exact for the stored cameras.
    return poses.astype(np.float32).astype(np.float64)


def _train_poses(num_views: int) -> np.ndarray:
    azimuths = _AZIMUTH_OFFSET + 2 * np.pi * np.arange(num_views) / num_views
    elevations = np.deg2rad([_TRAIN_ELEVATIONS[i % 2] for i in range(num_views)])
    return _orbit_poses(azimuths, elevations)


def _test_poses(num_views: int) -> np.ndarray:
    # Half a step off the evenly spaced azimuths, so the test views fall between cameras.
    azimuths = _AZIMUTH_OFFSET + 2 * np.pi * (np.arange(num_views) + 0.5) / num_views
    elevations = np.deg2rad([_TEST_ELEVATIONS[i % 3] for i in range(num_views)])
    return _orbit_poses(azimuths, elevations)


def _directions(poses: np.ndarray) -> np.ndarray:
    """Unit vectors from the origin to the cameras' centres."""
    centres = poses[:, :3, 3]
    return centres / np.linalg.norm(centres, axis=-1, keepdims=True)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise angles, in degrees, between the unit vectors of `a` and of `b`."""
    return np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


def _val_poses(train_poses: np.ndarray, test_poses: np.ndarray, num_views: int) -> np.ndarray:
    # Settings are chosen on these views, so they must not be near-copies of the test views,
    # and should be as hard as the test views are. Candidates: every whole degree of azimuth
    # and of elevation in the test cameras' band, kept when their angle to the nearest
    # training camera lies within the test cameras' range of that angle. Then greedily, the
    # candidate farthest from every test camera and every validation camera already chosen
    # (first in grid order on ties).
    azimuths, elevations = np.meshgrid(
        np.arange(360.0), np.arange(_VAL_ELEVATION_BAND[0], _VAL_ELEVATION_BAND[1] + 1.0), indexing="ij"
    )
    azimuths, elevations = np.deg2rad(azimuths.ravel()), np.deg2rad(elevations.ravel())
    candidates = np.stack(
        [np.cos(elevations) * np.cos(azimuths), np.cos(elevations) * np.sin(azimuths), np.sin(elevations)],
        axis=-1,
    )
    train, test = _directions(train_poses), _directions(test_poses)
    test_to_train = _angles_deg(test, train).min(axis=1)
    to_train = _angles_deg(candidates, train).min(axis=1)
    allowed = (to_train >= test_to_train.min()) & (to_train <= test_to_train.max())
    nearest = np.where(allowed, _angles_deg(candidates, test).min(axis=1), -np.inf)
    chosen: list[int] = []
    for _ in range(num_views):
        pick = int(np.argmax(nearest))
        chosen.append(pick)
        nearest = np.minimum(nearest, _angles_deg(candidates, candidates[pick : pick + 1])[:, 0])
    return _orbit_poses(azimuths[chosen], elevations[chosen])


def builtin_views_at(
    azimuths_deg: Sequence[float] | Float[np.ndarray, " num_views"],
    elevations_deg: Sequence[float] | Float[np.ndarray, " num_views"],
    *,
    resolution: int = 64,
    first_id: int = 1000,
) -> Views:
    """The built-in scene seen from cameras on its orbit (4 units from the origin, looking at
    the scene, as every built-in camera does) at the given azimuths and elevations in degrees:
    images and true depths, numbered from `first_id`. Candidate views to capture next."""
    if len(azimuths_deg) != len(elevations_deg) or not len(azimuths_deg):
        raise ValueError("give one elevation per azimuth, at least one camera")
    _check_count(resolution, "resolution", 8, 4096)
    poses = _orbit_poses(np.deg2rad(np.asarray(azimuths_deg, np.float64)), np.deg2rad(np.asarray(elevations_deg, np.float64)))
    images, depths = _render(poses, resolution)
    return Views(
        images=images.astype(np.float32),
        camtoworlds=poses.astype(np.float32),
        focal=_focal(resolution),
        depths=depths.astype(np.float32),
        ids=tuple(range(first_id, first_id + len(poses))),
    )


def split_angles(dataset: Dataset) -> dict[str, np.ndarray]:
    """Each validation camera's angle (degrees, seen from the origin) to the nearest test camera
    and to the nearest training camera, and each test camera's to the nearest training camera."""
    if dataset.val is None:
        raise ValueError(f"{dataset.name} has no validation views")
    train, test, val = (_directions(np.asarray(v.camtoworlds, np.float64)) for v in (dataset.train, dataset.test, dataset.val))
    return {
        "val_to_test": _angles_deg(val, test).min(axis=1),
        "val_to_train": _angles_deg(val, train).min(axis=1),
        "test_to_train": _angles_deg(test, train).min(axis=1),
    }


def _focal(resolution: int) -> float:
    return float(0.5 * resolution / np.tan(0.5 * np.deg2rad(FOV_DEGREES)))


def _render(
    camtoworlds: Float[np.ndarray, "num_views 3 4"],
    resolution: int,
    specular_strength: float = SPECULAR,
) -> tuple[ImageStack, DepthStack]:
    """Renders the scene's images and z-depths (float64) from square pinhole cameras."""
    camera_dirs = pixel_directions(_focal(resolution), resolution, resolution)
    directions = np.einsum("nij,hwj->nhwi", camtoworlds[:, :, :3], camera_dirs)
    origins = np.broadcast_to(camtoworlds[:, None, None, :, 3], directions.shape)
    t, normals, shape_ids = _intersect_scene(origins, directions)

    hit = np.isfinite(t)
    points = origins + _finite(t)[..., None] * directions
    viewdirs = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    # Hard shadows: one ray per pixel towards the light, nudged off the surface so that it
    # does not hit the surface it starts from.
    shadow_origins = points + 1e-6 * _facing(normals, viewdirs)
    light_dirs = np.broadcast_to(LIGHT_DIRECTION, points.shape)
    shadow_t, _, _ = _intersect_scene(shadow_origins, light_dirs)
    visibility = np.isinf(shadow_t).astype(np.float64)

    albedo = _albedo(points, normals, shape_ids)
    rgb = shade(albedo, normals, viewdirs, visibility, specular_strength)
    images = np.where(hit[..., None], rgb, 1.0)
    return images, t


def _check_count(value: int, name: str, minimum: int, maximum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not minimum <= value <= maximum:
        raise ValueError(f"{name} must lie in [{minimum}, {maximum}], got {value}")


def make_builtin_scene(
    *, resolution: int = 64, num_train_views: int = 4, num_test_views: int = 8, num_val_views: int = 4
) -> Dataset:
    """Generates the built-in procedural scene.

    The scene is deterministic: every call with the same arguments returns bit-identical
    arrays. Training cameras are spread evenly in azimuth at elevations of 28 and 40
    degrees; test cameras lie halfway between, at elevations of 20, 34 and 46 degrees, so no
    test pose equals a training pose. Validation cameras are placed as far as possible from the
    test cameras (and from each other) while lying as far from the training cameras as the test
    cameras do: at the default counts each is 27.7 to 28.9 degrees from the nearest test camera
    and 20.0 to 21.1 degrees from the nearest training camera (test cameras: 17.4 to 27.8).
    All cameras are 4 units from the origin, look at a point slightly above the ground and have
    a 40 degree field of view. `split_angles` measures these angles.

    **Arguments:**

    - `resolution`: the width and height of the square images, in pixels.
    - `num_train_views`: the number of training views (few-shot: 3 to 9 is typical).
    - `num_test_views`: the number of held-out test views.
    - `num_val_views`: the number of validation views (0: none).

    **Returns:**

    A `Dataset` named `"builtin"` on a white background, with `near = 2` and `far = 6`,
    and true depths (`inf` on the background) in every split. Ids number the training, test
    and validation views in that order.
    """
    _check_count(resolution, "resolution", 8, 4096)
    _check_count(num_train_views, "num_train_views", 1, MAX_VIEWS)
    _check_count(num_test_views, "num_test_views", 1, MAX_VIEWS)
    _check_count(num_val_views, "num_val_views", 0, MAX_VIEWS)
    focal = _focal(resolution)

    def views(poses: np.ndarray, first_id: int) -> Views:
        images, depths = _render(poses, resolution)
        return Views(
            images=images.astype(np.float32),
            camtoworlds=poses.astype(np.float32),
            focal=focal,
            depths=depths.astype(np.float32),
            ids=tuple(range(first_id, first_id + len(poses))),
        )

    train_poses, test_poses = _train_poses(num_train_views), _test_poses(num_test_views)
    val = None
    if num_val_views:
        val = views(_val_poses(train_poses, test_poses, num_val_views), num_train_views + num_test_views)
    return Dataset(
        name="builtin",
        train=views(train_poses, 0),
        test=views(test_poses, num_train_views),
        near=NEAR,
        far=FAR,
        white_background=True,
        frustum="cone",
        val=val,
        val_source="extra cameras away from the test cameras" if num_val_views else "none asked for (data.num_val_views = 0)",
    )
