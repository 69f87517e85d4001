"""The view to capture next: candidate cameras ranked by how uncertain the model is there.

A trained MixNeRF predicts, for every pixel of a camera it never saw, a colour mixture and a
distribution of where the ray terminates. Where those are wide the model has not pinned the
scene down, and an image taken there is expected to teach it the most. `next_view` renders
each candidate at a small width (`width` pixels across) and scores it by the spread over its
pixels, averaged with each pixel's opacity as its weight (a nearly transparent ray's
distributions are renormalised over almost nothing, and say nothing about the scene):

- `"depth"`: the termination distance's standard deviation, in units of the sampling
  interval `far - near` (geometry the views leave ambiguous);
- `"colour"`: the colour mixture's standard deviation, averaged over the channels.

`farthest_first` is the geometric baseline: the candidate whose camera centre lies farthest
from every training camera's. Candidate poses are checked first: finite camera-to-world
matrices whose rotation part is a rotation, and cameras that face the scene (for NDC scenes
every ray must point along -z, the direction NDC is defined for; for bounded scenes the model
must see something there: a mean opacity of at least `MIN_OPACITY`).
"""

import dataclasses

import numpy as np
from jaxtyping import Float

import equinox as eqx
import jax.numpy as jnp

from .._nn.chunks import join_chunks, map_ray_chunks
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from ..data import Views, rays_at_poses
from .distribution import predictive

SCORES = ("depth", "colour")
# A bounded scene's candidate whose render is this transparent on average sees nothing of it.
MIN_OPACITY = 0.02
_ROTATION_TOLERANCE = 1e-3


@dataclasses.dataclass(frozen=True)
class ViewRanking:
    """Candidates ranked for capture.

    **Fields:**

    - `order`: candidate indices, the best first.
    - `scores`: each candidate's score, in the candidates' order (larger: more to learn).
    - `score`: which spread (`"depth"` or `"colour"`).
    - `opacity`: each candidate's mean rendered opacity.
    """

    order: np.ndarray
    scores: np.ndarray
    score: str
    opacity: np.ndarray


def check_candidate_poses(camtoworlds) -> Float[np.ndarray, "num_views 3 4"]:
    """`camtoworlds` as a float64 `(n, 3, 4)` array (a `(n, 4, 4)` one loses its last row), or a
    `ValueError` that names the first bad pose: not finite, or a rotation part that is not a
    rotation (orthonormal with determinant +1, to 1e-3)."""
    given = np.asarray(camtoworlds)
    if given.dtype.kind not in "fiu":
        raise ValueError(f"candidate poses must be real numbers, got an array of {given.dtype}")
    poses = given.astype(np.float64)
    if poses.ndim == 3 and poses.shape[1:] == (4, 4):
        bottom = poses[:, 3]
        bad = np.flatnonzero(np.abs(bottom - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > _ROTATION_TOLERANCE)
        if bad.size:
            raise ValueError(f"candidate pose {bad[0]} is a 4 x 4 matrix whose last row is not [0, 0, 0, 1]")
        poses = poses[:, :3]
    if poses.ndim != 3 or poses.shape[1:] != (3, 4) or poses.shape[0] == 0:
        raise ValueError(
            f"candidate poses must be camera-to-world matrices of shape (n, 3, 4) or (n, 4, 4), n >= 1; "
            f"got shape {poses.shape}"
        )
    for index, pose in enumerate(poses):
        with np.errstate(over="ignore"):
            finite = np.all(np.isfinite(pose.astype(np.float32)))
        if not finite:
            raise ValueError(f"candidate pose {index} is not finite (in float32, which the rays are made in)")
        rotation = pose[:, :3]
        if (
            np.abs(rotation.T @ rotation - np.eye(3)).max() > _ROTATION_TOLERANCE
            or abs(np.linalg.det(rotation) - 1.0) > _ROTATION_TOLERANCE
        ):
            raise ValueError(
                f"candidate pose {index}'s rotation part is not a rotation (orthonormal columns, determinant "
                f"+1): give camera-to-world matrices in the scene's convention (OpenGL axes)"
            )
    return poses


@eqx.filter_jit
def _spreads(model: MixNeRF, rays: RayBundle) -> dict:
    """Per ray: the termination distance's and the colour's standard deviation, and the opacity."""
    prediction = predictive(model, rays)
    return {
        "depth": prediction.depth.std(),
        "colour": jnp.mean(prediction.colour.std(), axis=-1),
        "acc": prediction.acc,
    }


def _small(like: Views, width: int) -> Views:
    """`like`'s camera shrunk to `width` pixels across (intrinsics scaled alike): one blank view
    that only lends `rays_at_poses` its image size, intrinsics and ray space."""
    factor = min(1.0, width / like.width)
    small_width = max(2, round(like.width * factor))
    small_height = max(2, round(like.height * factor))
    intrinsics = None
    if like.intrinsics is not None:
        intrinsics = like.intrinsics[:1].copy()
        intrinsics[:, :2] *= np.array([small_width / like.width, small_height / like.height])[None, :, None]
    return dataclasses.replace(
        like.select([0]),
        images=np.zeros((1, small_height, small_width, 3), np.float32),
        depths=None,
        masks=None,
        focal=like.focal * small_width / like.width,
        intrinsics=intrinsics,
    )


def next_view(
    model: MixNeRF,
    like: Views,
    camtoworlds,
    near: float,
    far: float,
    *,
    score: str = "depth",
    width: int = 48,
    chunk: int = 4096,
) -> ViewRanking:
    """Ranks candidate cameras (`camtoworlds`, in the scene's convention) by the model's mean
    predictive spread there; `like` lends them its intrinsics and ray space (a split of the
    scene). A candidate facing away from the scene is a `ValueError` that names it."""
    if score not in SCORES:
        raise ValueError(f"score must be one of {', '.join(SCORES)}, got {score!r}")
    if width < 2:
        raise ValueError(f"width must be at least 2 pixels, got {width}")
    poses = check_candidate_poses(camtoworlds)
    small = _small(like, width)
    scores, opacity = [], []
    for index, pose in enumerate(poses):
        if like.ndc:
            # NDC is defined for rays that look along -z in the world: check them before the map.
            world = rays_at_poses(dataclasses.replace(small, ndc=False), pose[None].astype(np.float32), 0.0, 1.0)
            if not np.all(np.asarray(world.directions)[..., 2] < 0):
                raise ValueError(
                    f"candidate pose {index} faces away from the scene: an NDC scene is seen along -z"
                )
        rays = rays_at_poses(small, pose[None].astype(np.float32), near, far)
        flat = rays.reshape(-1)
        parts, count = map_ray_chunks(lambda piece, real, _: _spreads(model, piece), flat, chunk)
        spreads = {name: join_chunks([part[name] for part in parts], count).astype(np.float64) for name in parts[0]}
        seen = float(np.mean(spreads["acc"]))
        if not like.ndc and seen < MIN_OPACITY:
            raise ValueError(
                f"candidate pose {index} sees nothing of the scene (mean opacity {seen:.3f} < {MIN_OPACITY}): "
                "it faces away from it or lies outside its bounds"
            )
        weights = np.clip(spreads["acc"], 0.0, 1.0)
        value = float(np.sum(weights * spreads[score]) / max(np.sum(weights), 1e-12))
        scores.append(value / (far - near) if score == "depth" else value)
        opacity.append(seen)
    scores = np.asarray(scores)
    return ViewRanking(order=np.argsort(-scores, kind="stable"), scores=scores, score=score, opacity=np.asarray(opacity))


def farthest_first(camtoworlds, train_camtoworlds) -> np.ndarray:
    """Candidate indices ordered by the distance of their camera centre to the nearest
    training camera's, farthest first (the geometric baseline)."""
    centres = check_candidate_poses(camtoworlds)[:, :, 3]
    train = np.asarray(train_camtoworlds, np.float64)[:, :3, 3]
    nearest = np.linalg.norm(centres[:, None] - train[None], axis=-1).min(axis=1)
    return np.argsort(-nearest, kind="stable")
