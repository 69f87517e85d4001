"""A user's own scene in the `transforms.json` convention of nerfstudio and instant-ngp.

`<scene>/transforms.json` lists `frames`, each with a `file_path` (relative to the JSON's
folder) and a `transform_matrix` (a camera-to-world matrix in the OpenGL convention, which
both tools use). The pinhole intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` may sit at the
top level or in each frame (a frame's own values win); instant-ngp's `camera_angle_x` and
`camera_angle_y` stand in for absent focal lengths, and the principal point defaults to the
image centre. Lens distortion (`k1` to `k4`, `p1`, `p2`) is ignored, with a warning; fisheye
and equirectangular cameras are refused.

A `downscale` factor (`data.image_downscale`) area-averages the stored images (straight RGBA
before compositing) and scales the intrinsics to match; a side that it does not divide loses
its remainder, half from each end, and the principal point moves with the crop (see
`mixnerf_eqx.data._downscale`).

Frames are ordered by file name (numbers by value). As in LLFF, every 8th frame is held out
for testing and `n` of the others, evenly spaced, train. RGBA images are composited on white
(and rendered on white); RGB images have no background colour.

The file holds no sampling bounds. Unless the config gives them (`data.near`, `data.far`),
the scene is taken to be centred on the origin, as object captures in these tools usually
are: near is half the smallest camera distance from the origin and far 1.5 times the
largest (2.0 and 6.0 for the Blender scenes, whose cameras are 4.03 from the origin).
"""

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .._config import DataConfig
from .._nn.rays import intrinsic_matrix
from ._dataset import Dataset, Views
from ._downscale import check_factor, downscale_image, downscale_intrinsics
from ._errors import DatasetError
from ._files import (
    check_same_size,
    composite_on_white,
    natural_key,
    read_images,
    read_json,
)
from ._format import DatasetFormat
from ._poses import check_field_of_view, parse_transform_matrix
from ._splits import describe_validation, holdout_split, subsample_test_ids, validation_ids

__all__ = ["default_bounds", "load_transforms"]

HOLDOUT_EVERY = 8
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
UNSUPPORTED_MODELS = ("OPENCV_FISHEYE", "FISHEYE", "EQUIRECTANGULAR", "FISHEYE624")
_ADVICE = "Write the scene's transforms.json as nerfstudio or instant-ngp do."


def default_bounds(camtoworlds: np.ndarray) -> tuple[float, float]:
    """Sampling bounds for a scene centred on the origin, from the camera distances."""
    distances = np.linalg.norm(np.asarray(camtoworlds, np.float64)[:, :, 3], axis=-1)
    return float(0.5 * distances.min()), float(1.5 * distances.max())


def _number(frame: dict, meta: dict, key: str, path: Path) -> float | None:
    value = frame.get(key, meta.get(key))
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(f"{path}: {key!r} must be a number, got {value!r}.")
    return float(value)


def _frame_intrinsics(
    frame: dict, meta: dict, width: int, height: int, path: Path, image: Path
) -> np.ndarray:
    stated = (_number(frame, meta, "w", path), _number(frame, meta, "h", path))
    if None not in stated and (round(stated[0]), round(stated[1])) != (width, height):
        raise DatasetError(
            f"{image}: the image is {width}x{height} but {path.name} says w={stated[0]:.0f}, "
            f"h={stated[1]:.0f}. Point file_path at the full-size images, or fix w and h."
        )
    focal_x = _number(frame, meta, "fl_x", path)
    focal_y = _number(frame, meta, "fl_y", path)
    if focal_x is None:
        angle_x = _number(frame, meta, "camera_angle_x", path)
        if angle_x is None:
            raise DatasetError(f"{path}: no focal length for {image.name}: give fl_x (or camera_angle_x).")
        focal_x = 0.5 * width / math.tan(0.5 * check_field_of_view(angle_x, f"{path}: camera_angle_x of {image.name}"))
    if focal_y is None:
        angle_y = _number(frame, meta, "camera_angle_y", path)
        if angle_y is not None:
            check_field_of_view(angle_y, f"{path}: camera_angle_y of {image.name}")
        focal_y = focal_x if angle_y is None else 0.5 * height / math.tan(0.5 * angle_y)
    for name, focal in (("fl_x", focal_x), ("fl_y", focal_y)):
        if not math.isfinite(focal) or focal <= 0:
            raise DatasetError(f"{path}: {name} of {image.name} is {focal!r}; a focal length must be finite and positive.")
    cx = _number(frame, meta, "cx", path)
    cy = _number(frame, meta, "cy", path)
    return intrinsic_matrix(
        focal_x, focal_y, 0.5 * width if cx is None else cx, 0.5 * height if cy is None else cy
    )


def _frames(meta: Any, path: Path) -> list[dict]:
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DatasetError(f"{path}: expected an object with a non-empty 'frames' list. {_ADVICE}")
    model = meta.get("camera_model", "")
    if isinstance(model, str) and model.upper() in UNSUPPORTED_MODELS:
        raise DatasetError(
            f"{path}: camera_model {model!r} is not a pinhole camera; only pinhole cameras (PINHOLE, "
            "OPENCV with its distortion ignored) are supported. Undistort the images first."
        )
    frames = []
    for index, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DatasetError(f"{path}: frame {index} has no 'file_path'.")
        if "transform_matrix" not in frame:
            raise DatasetError(f"{path}: frame {index} ({frame['file_path']}) has no 'transform_matrix'.")
        frames.append(frame)
    distorted = [
        key
        for key in DISTORTION_KEYS
        if any(_number(frame, meta, key, path) not in (None, 0.0) for frame in frames)
    ]
    if distorted:
        warnings.warn(
            f"{path}: lens distortion ({', '.join(distorted)}) is ignored; the images are treated as "
            "undistorted pinhole images. Undistort them for accurate cameras.",
            UserWarning,
            stacklevel=4,
        )
    return sorted(frames, key=lambda frame: natural_key(frame["file_path"]))


def _image_path(scene_dir: Path, file_path: str) -> Path:
    path = scene_dir / file_path
    if path.suffix or path.is_file():
        return path
    # Blender-style paths leave out the extension.
    return path.with_name(path.name + ".png")


def _poses(frames: list[dict], path: Path) -> np.ndarray:
    """The frames' camera-to-world matrices, stacked."""
    return np.stack(
        [
            parse_transform_matrix(f["transform_matrix"], f"{path}: the transform_matrix of {f['file_path']}")
            for f in frames
        ]
    )


def _read_frame_images(
    scene_dir: Path, frames: list[dict], ids: list[int]
) -> dict[int, tuple[Path, np.ndarray]]:
    """The path and decoded image of each frame in `ids`; all images must have one size."""
    paths = {i: _image_path(scene_dir, frames[i]["file_path"]) for i in ids}
    decoded = read_images([paths[i] for i in ids])
    check_same_size(decoded, [paths[i] for i in ids])
    return {i: (paths[i], image) for i, image in zip(ids, decoded, strict=True)}


def _load_views(
    ids: list[int],
    frames: list[dict],
    meta: dict,
    path: Path,
    raw_images: dict[int, tuple[Path, np.ndarray]],
    poses: np.ndarray,
    *,
    has_alpha: bool,
    downscale: int,
) -> Views:
    """The views `ids`, composited on white when any image of the scene has alpha."""
    images, intrinsics = [], []
    for i in ids:
        image_path, image = raw_images[i]
        height, width = image.shape[:2]
        check_factor(downscale, height, width, image_path)
        k = _frame_intrinsics(frames[i], meta, width, height, path, image_path)
        if downscale > 1:
            k = downscale_intrinsics(k, height, width, downscale)
        pixels = downscale_image(image, downscale)
        images.append(composite_on_white(pixels) if has_alpha else pixels[..., :3])
        intrinsics.append(k)
    intrinsics = np.stack(intrinsics)
    return Views(
        images=np.stack(images),
        camtoworlds=poses[ids].astype(np.float32),
        focal=float(np.mean(intrinsics[:, 0, 0])),
        ids=tuple(ids),
        intrinsics=intrinsics.astype(np.float32),
    )


def load_transforms(
    scene_dir: Path,
    *,
    num_train_views: int,
    max_test_views: int = 0,
    max_val_views: int = 0,
    downscale: int = 1,
    bounds: tuple[float, float] | None = None,
) -> Dataset:
    """Loads a `transforms.json` scene, holding out every 8th frame for testing.

    **Arguments:**

    - `scene_dir`: the folder holding `transforms.json`.
    - `num_train_views`: the number of training views, picked evenly from the frames that
      are not held out.
    - `max_test_views`: keep only this many of the held-out views, evenly spaced (0: all).
    - `max_val_views`: keep only this many validation views (the frames that are neither
      training nor test views), evenly spaced (0: all).
    - `downscale`: area-average `downscale x downscale` blocks of the images and scale the
      intrinsics to match (see the module docstring); 1 keeps the stored images.
    - `bounds`: `(near, far)`; `None` derives them from the cameras (`default_bounds`).

    **Returns:**

    A `Dataset` with per-view intrinsics and cone frustums.
    """
    path = scene_dir / "transforms.json"
    meta = read_json(path, "transforms.json", _ADVICE)
    frames = _frames(meta, path)
    poses = _poses(frames, path)
    train_ids, test_ids = holdout_split(len(frames), HOLDOUT_EVERY, num_train_views, path)
    test_ids = subsample_test_ids(test_ids, max_test_views)
    val_ids, left_out = validation_ids(
        list(range(len(frames))),
        train_ids + test_ids,
        max_val_views,
        centres=poses[:, :3, 3],
        train_ids=train_ids,
        test_ids=test_ids,
    )
    near, far = default_bounds(poses) if bounds is None else bounds
    if not 0 <= near < far:
        raise DatasetError(
            f"{path}: sampling bounds near={near:g}, far={far:g} are unusable (cameras at the origin?); "
            "set data.near and data.far."
        )
    raw_images = _read_frame_images(scene_dir, frames, train_ids + test_ids + val_ids)
    has_alpha = any(image.shape[-1] == 4 for _, image in raw_images.values())

    def views(ids: list[int]) -> Views:
        return _load_views(
            ids, frames, meta, path, raw_images, poses, has_alpha=has_alpha, downscale=downscale
        )

    return Dataset(
        name=scene_dir.name,
        train=views(train_ids),
        test=views(test_ids),
        near=float(near),
        far=float(far),
        white_background=has_alpha,
        frustum="cone",
        val=views(val_ids) if val_ids else None,
        val_source=describe_validation(
            "frames neither trained on nor held out for testing",
            "every frame is a training or test view",
            val_ids,
            left_out,
        ),
    )


def _load_from_config(scene_dir: Path, config: DataConfig) -> Dataset:
    return load_transforms(
        scene_dir,
        num_train_views=config.num_train_views,
        max_test_views=config.max_test_views,
        max_val_views=config.max_val_views,
        downscale=config.image_downscale,
        bounds=(config.near, config.far) if config.far > 0 else None,
    )


FORMAT = DatasetFormat(
    name="transforms",
    layouts=(),
    scenes=(),
    release="the scene's folder with its transforms.json",
    load=_load_from_config,
)
