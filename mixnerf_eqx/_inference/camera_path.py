"""Camera paths for videos: a spiral in front of a forward-facing scene, an orbit around a
360-degree one, both built from the poses of the scene's cameras (float64 numpy, OpenGL
cameras as in `mixnerf_eqx._nn.rays`).

The spiral is the path of the NeRF literature's LLFF videos: cameras circle the average
camera in its image plane (and move along its axis at half the rate, twice per loop), all
looking at one point on its axis. The orbit circles the point that the cameras' optical axes
pass closest to, at their mean distance and elevation, about their mean up direction.
"""

import warnings
from typing import Literal

import numpy as np
from jaxtyping import Float

from .._config import SettingWarning
from .._custom_types import PoseStack
from ..data import Dataset
from ..data._poses import average_pose

# The scene's cameras; a path has as many cameras as it has frames, a count of its own.
SceneCameras = Float[np.ndarray, "_num_views 3 4"]

# The spiral looks at the depth NeRF's LLFF videos focus at, 1 / ((1 - 0.75) / close + 0.75 / far),
# for a scene scaled (as the LLFF loader does) so that its nearest content lies at 4/3, with
# close = 0.9 of that and the far content far away.
SPIRAL_FOCUS_DEPTH = 0.9 * (4.0 / 3.0) / (1.0 - 0.75)


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector, axis=-1, keepdims=True)


def look_at(
    positions: Float[np.ndarray, "num_views 3"],
    targets: Float[np.ndarray, "num_views 3"],
    up: Float[np.ndarray, "3"],
) -> PoseStack:
    """Cameras at `positions` looking at `targets` (each camera's -z axis points at its
    target), with their y axis in the plane of `up` and the viewing direction."""
    backward = _unit(positions - targets)
    right = _unit(np.cross(up, backward))
    camera_up = np.cross(backward, right)
    return np.stack([right, camera_up, backward, positions], axis=-1)


def spiral_path(
    camtoworlds: SceneCameras,
    num_frames: int,
    *,
    focus_depth: float = SPIRAL_FOCUS_DEPTH,
    rotations: int = 2,
    percentile: float = 90.0,
) -> PoseStack:
    """A spiral of `num_frames` cameras in front of a forward-facing scene.

    **Arguments:**

    - `camtoworlds`: the scene's cameras.
    - `num_frames`: cameras on the path.
    - `focus_depth`: distance along the average camera's axis of the point every camera
      looks at.
    - `rotations`: loops around the average camera.
    - `percentile`: the spiral's radius along each axis of the average camera is this
      percentile of the cameras' offsets from it along that axis.

    **Returns:**

    The path's camera-to-world matrices; the first frame's camera lies on the average
    camera's x axis.
    """
    poses = np.asarray(camtoworlds, np.float64)
    average = average_pose(poses)
    rotation, centre = average[:, :3], average[:, 3]
    offsets = (poses[:, :, 3] - centre) @ rotation  # in the average camera's frame
    radii = np.percentile(np.abs(offsets), percentile, axis=0)
    angles = np.linspace(0.0, 2.0 * np.pi * rotations, num_frames, endpoint=False)
    local = np.stack([np.cos(angles), -np.sin(angles), -np.sin(0.5 * angles)], axis=-1) * radii
    positions = centre + local @ rotation.T
    focus = centre - focus_depth * rotation[:, 2]
    return look_at(positions, np.broadcast_to(focus, positions.shape), rotation[:, 1])


def orbit_centre(camtoworlds: SceneCameras) -> Float[np.ndarray, "3"]:
    """The point closest (in the least-squares sense) to every camera's optical axis."""
    poses = np.asarray(camtoworlds, np.float64)
    axes = _unit(-poses[:, :, 2])
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto each axis's normal plane
    matrix = projectors.sum(axis=0)
    vector = np.einsum("nij,nj->i", projectors, poses[:, :, 3])
    return np.linalg.lstsq(matrix, vector, rcond=None)[0]


def up_direction(camtoworlds: SceneCameras) -> Float[np.ndarray, "3"]:
    """The world's up direction as the cameras show it: the direction most nearly
    perpendicular to every camera's x axis (exactly so for cameras without roll, whatever
    their elevations), signed to agree with their y axes."""
    poses = np.asarray(camtoworlds, np.float64)
    rights = poses[:, :, 0]
    _, vectors = np.linalg.eigh(rights.T @ rights)
    up = vectors[:, 0]
    return up if up @ poses[:, :, 1].sum(axis=0) >= 0 else -up


def orbit_path(camtoworlds: SceneCameras, num_frames: int) -> PoseStack:
    """An orbit of `num_frames` cameras around a 360-degree scene.

    The cameras circle `orbit_centre` about the cameras' mean up direction, at their mean
    distance from the centre and their mean elevation above the plane through it, all looking
    at the centre; the first frame sits at the azimuth of the first camera.
    """
    poses = np.asarray(camtoworlds, np.float64)
    centre = orbit_centre(poses)
    up = up_direction(poses)
    offsets = poses[:, :, 3] - centre
    distances = np.linalg.norm(offsets, axis=-1)
    elevation = np.arcsin(np.clip(offsets @ up / distances, -1.0, 1.0)).mean()
    radius = distances.mean()
    first = _unit(offsets[0] - (offsets[0] @ up) * up)
    second = np.cross(up, first)
    angles = np.linspace(0.0, 2.0 * np.pi, num_frames, endpoint=False)
    around = np.cos(angles)[:, None] * first + np.sin(angles)[:, None] * second
    positions = centre + radius * (np.sin(elevation) * up + np.cos(elevation) * around)
    return look_at(positions, np.broadcast_to(centre, positions.shape), up)


PathKind = Literal["auto", "spiral", "orbit"]


def camera_path(dataset: Dataset, kind: PathKind = "auto", num_frames: int = 120) -> PoseStack:
    """The video path through `dataset`: a spiral for forward-facing (NDC) scenes and an
    orbit for the others with `kind="auto"`; built from the poses of both splits (poses
    only: no held-out image is looked at)."""
    if num_frames < 1:
        raise ValueError(f"a camera path needs at least one frame, got {num_frames}")
    poses = np.concatenate([dataset.train.camtoworlds, dataset.test.camtoworlds]).astype(np.float64)
    natural = "spiral" if dataset.train.ndc else "orbit"
    if kind in ("spiral", "orbit") and kind != natural:
        scene = "a forward-facing" if dataset.train.ndc else "a 360-degree"
        warnings.warn(
            f"a{'n' if kind == 'orbit' else ''} {kind} through {scene} scene leaves the views it was "
            f"trained on (the {natural} is its path; --path auto chooses it)",
            SettingWarning,
            stacklevel=2,
        )
    if kind == "auto":
        kind = natural
    if kind == "spiral":
        return spiral_path(poses, num_frames)
    if kind == "orbit":
        return orbit_path(poses, num_frames)
    raise ValueError(f"unknown camera path {kind!r}; choose auto, spiral or orbit")
