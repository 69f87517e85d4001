"""Camera pose utilities shared by the loaders (float64 numpy, OpenGL camera convention)."""

import math

import numpy as np
from jaxtyping import Float

from ._errors import DatasetError


def _normalise(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector)


def average_pose(camtoworlds: Float[np.ndarray, "num_views 3 4"]) -> Float[np.ndarray, "3 4"]:
    """The mean camera of the NeRF LLFF loader: the mean centre, looking along the mean
    backward axis, with the mean up axis made orthogonal to it."""
    poses = np.asarray(camtoworlds, np.float64)
    centre = poses[:, :, 3].mean(axis=0)
    backward = _normalise(poses[:, :, 2].sum(axis=0))
    up = poses[:, :, 1].sum(axis=0)
    right = _normalise(np.cross(up, backward))
    up = _normalise(np.cross(backward, right))
    return np.stack([right, up, backward, centre], axis=1)


def parse_transform_matrix(value: object, what: str) -> Float[np.ndarray, "3 4"]:
    """A JSON `transform_matrix` (4x4 or 3x4 camera-to-world) as a float64 3x4 matrix.

    Anything else is a `DatasetError` whose message starts with `what` (the file and frame).
    """
    try:
        matrix = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        matrix = np.zeros(0)
    if matrix.shape not in ((4, 4), (3, 4)):
        raise DatasetError(
            f"{what} has shape {matrix.shape}; expected a finite 4x4 camera-to-world matrix. "
            "Repair the file or export it again."
        )
    check_camera(matrix[:3, :4], what)
    return matrix[:3, :4]


# How far `R^T R` of a camera's rotation part may lie from the identity (exported files hold
# rotations to float32's precision, about 1e-7).
ROTATION_TOLERANCE = 1e-3


def check_camera(matrix: Float[np.ndarray, "3 4"], what: str) -> None:
    """A camera-to-world matrix must be finite with a rotation in its left 3x3 block: a
    `DatasetError` that starts with `what` (the file and camera) otherwise."""
    matrix = np.asarray(matrix, np.float64)
    if not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{what} holds a value that is not finite (NaN or inf). Repair the file or export it again.")
    rotation = matrix[:3, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        raise DatasetError(
            f"{what}: its 3x3 part is not a rotation (R^T R is {error:.3g} from the identity, at most "
            f"{ROTATION_TOLERANCE:g} allowed): a zero, scaled or sheared camera. Repair the file or export it again."
        )


def check_field_of_view(value: object, what: str) -> float:
    """A field of view in radians: a finite number in (0, pi); a `DatasetError` naming `what` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not 0 < value < math.pi:
        raise DatasetError(
            f"{what} is {value!r}; a field of view must be a finite angle in radians between 0 and pi "
            "(exclusive). Repair the file or export it again."
        )
    return float(value)


def _homogeneous(poses: np.ndarray) -> np.ndarray:
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), poses.shape[:-2] + (1, 4))
    return np.concatenate([poses, bottom], axis=-2)


def recenter_poses(camtoworlds: Float[np.ndarray, "num_views 3 4"]) -> Float[np.ndarray, "num_views 3 4"]:
    """Expresses the cameras in the frame of their `average_pose` (a rigid change of frame):
    the average camera then sits at the origin, looking along -z."""
    poses = np.asarray(camtoworlds, np.float64)
    world_to_average = np.linalg.inv(_homogeneous(average_pose(poses)))
    return (world_to_average @ _homogeneous(poses))[:, :3, :]


def decompose_projection(
    projection: Float[np.ndarray, "3 4"],
) -> tuple[Float[np.ndarray, "3 3"], Float[np.ndarray, "3 4"]]:
    """Splits a camera projection `P = K [R | t]` (OpenCV convention) into its parts.

    The RQ decomposition of the left 3x3 block gives an upper-triangular `K` with a positive
    diagonal and a rotation `R`; `P`'s arbitrary scale and sign are removed by fixing
    `K[2, 2] = 1`. The camera centre is the null space of `P`.

    **Arguments:**

    - `projection`: a finite-camera projection matrix (world to homogeneous pixels).

    **Returns:**

    The intrinsic matrix `K` (OpenCV pixel convention, skew kept) and the camera-to-world
    matrix in the OpenGL convention (x right, y up, looking along -z).
    """
    projection = np.asarray(projection, np.float64)
    block = projection[:, :3]
    if np.linalg.det(block) < 0:
        # P and -P project alike; with a positive determinant the rotation is proper.
        projection, block = -projection, -block
    # RQ through QR: with the row-reversing permutation J, (J M)^T = Q U gives
    # M = (J U^T J)(J Q^T), an upper-triangular factor times an orthogonal one.
    reverse = np.eye(3)[::-1]
    q, u = np.linalg.qr((reverse @ block).T)
    intrinsics = reverse @ u.T @ reverse
    rotation = reverse @ q.T
    signs = np.diag(np.sign(np.diag(intrinsics)))
    intrinsics, rotation = intrinsics @ signs, signs @ rotation
    intrinsics = intrinsics / intrinsics[2, 2]
    centre = -np.linalg.solve(block, projection[:, 3])
    opencv_to_opengl = np.diag([1.0, -1.0, -1.0])
    camtoworld = np.concatenate([rotation.T @ opencv_to_opengl, centre[:, None]], axis=1)
    return intrinsics, camtoworld
