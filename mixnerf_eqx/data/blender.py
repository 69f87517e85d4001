"""The NeRF synthetic ("Blender") scenes: `nerf_synthetic/<scene>/transforms_{train,test}.json`.

Images are the 800x800 RGBA renders, area-downsampled by 2 to 400x400 as straight RGBA and
then composited on white (RegNeRF's and MixNeRF's `factor = 2` with a white background).
A split's images may instead come from a `<split>_400/` folder beside `<split>/` holding the
same views already downsampled (such as the `test_400/` folder of the project's shared data):
the loader reads `<split>/` when it holds every image it needs, else `<split>_400/`.

A `downscale` factor (`data.image_downscale`) then area-averages the composited 400x400
images further, so that each output pixel is the mean of the protocol's pixels as they are
scored; both splits alike, whether read from `<split>/` or `<split>_400/`. A side that the
factor does not divide loses its remainder, half from each end, and an odd remainder gives
the views explicit intrinsics that keep the principal point where it was (see
`mixnerf_eqx.data._downscale`).

Cameras are the JSON's OpenGL camera-to-world matrices; the focal length follows from
`camera_angle_x` and the 400-pixel width, divided by `downscale` (so by `2 * downscale`
from the 800x800 renders' camera). Sampling bounds are near 2 and far 6.

Two protocols choose the views:

- `"mixnerf"` (MixNeRF, following InfoNeRF): the first `n` frames of `transforms_train.json`
  for training and all 200 test frames.
- `"dietnerf"` (DietNeRF): the training frames `[26, 86, 2, 55, 75, 93, 16, 73]` (the first
  `n` of them) and every 8th test frame (25 views).

Numbers from the two protocols are not comparable.

Validation views come from `transforms_val.json` when its images are there, otherwise from
the frames of `transforms_train.json` that the protocol does not train on; evenly spaced
either way, after leaving out the cameras that lie near a test camera (`_splits.near_test`).
Neither set meets the test views.
"""

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .._config import DataConfig
from ._dataset import Dataset, Views
from ._downscale import check_factor, downscale_centred_camera, downscale_image
from ._errors import DatasetError
from ._files import (
    area_downsample,
    check_same_size,
    composite_on_white,
    read_images,
    read_json,
    to_float,
)
from ._format import DatasetFormat
from ._poses import check_field_of_view, parse_transform_matrix
from ._splits import describe_validation, near_test, subsample_test_ids, validation_ids

__all__ = ["SCENES", "load_blender", "split_ids"]

SCENES = ("chair", "drums", "ficus", "hotdog", "lego", "materials", "mic", "ship")
NEAR = 2.0
FAR = 6.0
DOWNSAMPLE = 2
DIETNERF_TRAIN_IDS = (26, 86, 2, 55, 75, 93, 16, 73)
DIETNERF_TEST_EVERY = 8
_ADVICE = "Point --data-dir (or MIXNERF_DATA_DIR) at the folder that holds nerf_synthetic/."


def split_ids(
    protocol: Literal["mixnerf", "dietnerf"],
    num_train_frames: int,
    num_test_frames: int,
    num_train_views: int,
    train_file: Path,
) -> tuple[list[int], list[int]]:
    """The frame ids of the training and test views that `protocol` uses.

    **Arguments:**

    - `protocol`: `"mixnerf"` or `"dietnerf"` (see the module docstring).
    - `num_train_frames`, `num_test_frames`: the numbers of frames in the two JSON files.
    - `num_train_views`: how many training views to use.
    - `train_file`: the training JSON, named in errors.

    **Returns:**

    The training frame ids and the test frame ids.
    """
    if protocol == "mixnerf":
        if num_train_views > num_train_frames:
            raise DatasetError(
                f"{train_file}: {num_train_views} training views asked for, but the file lists only "
                f"{num_train_frames} frames. Ask for at most {num_train_frames} (data.num_train_views)."
            )
        return list(range(num_train_views)), list(range(num_test_frames))
    if protocol == "dietnerf":
        if num_train_views > len(DIETNERF_TRAIN_IDS):
            raise DatasetError(
                f"{num_train_views} training views asked for, but the DietNeRF protocol defines "
                f"{len(DIETNERF_TRAIN_IDS)} ({list(DIETNERF_TRAIN_IDS)}). Ask for at most "
                f'{len(DIETNERF_TRAIN_IDS)} (data.num_train_views), or use data.protocol = "mixnerf".'
            )
        train = list(DIETNERF_TRAIN_IDS[:num_train_views])
        if max(train) >= num_train_frames:
            raise DatasetError(
                f"{train_file}: the DietNeRF protocol uses frame {max(train)}, but the file lists only "
                f"{num_train_frames} frames. Use the original transforms_train.json (100 frames)."
            )
        return train, list(range(0, num_test_frames, DIETNERF_TEST_EVERY))
    raise DatasetError(
        f'unknown Blender protocol {protocol!r}; choose "mixnerf" or "dietnerf" (data.protocol)'
    )


def _frames(meta: Any, path: Path) -> list[dict]:
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DatasetError(f"{path}: expected an object with a non-empty 'frames' list. {_ADVICE}")
    if not isinstance(meta.get("camera_angle_x"), (int, float)):
        raise DatasetError(
            f"{path}: 'camera_angle_x' (the horizontal field of view) is missing or not a number."
        )
    check_field_of_view(meta["camera_angle_x"], f"{path}: 'camera_angle_x'")
    for index, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DatasetError(f"{path}: frame {index} has no 'file_path'.")
        if "transform_matrix" not in frame:
            raise DatasetError(f"{path}: frame {index} has no 'transform_matrix'.")
    return meta["frames"]


def _image_path(scene_dir: Path, file_path: str) -> Path:
    path = scene_dir / file_path
    return path if path.suffix.lower() == ".png" else path.with_name(path.name + ".png")


def _downsampled_path(path: Path) -> Path:
    # ./test/r_0.png -> ./test_400/r_0.png
    return path.parent.with_name(f"{path.parent.name}_400") / path.name


def _read_split_images(paths: list[Path]) -> tuple[np.ndarray, list[Path]]:
    """Reads and downsamples the full-size images, or reads the `_400` copies when some
    full-size image is missing and every copy exists."""
    small = [_downsampled_path(p) for p in paths]
    if all(p.is_file() for p in paths) or not all(p.is_file() for p in small):
        # The full-size images; a missing one raises its own error from here.
        images = read_images(paths)
        check_same_size(images, paths)
        for image, path in zip(images, paths, strict=True):
            if image.shape[0] % DOWNSAMPLE or image.shape[1] % DOWNSAMPLE:
                raise DatasetError(
                    f"{path}: a {image.shape[1]}x{image.shape[0]} image cannot be halved exactly; the "
                    "Blender protocol downsamples the 800x800 renders by 2."
                )
        floats = [composite_on_white(area_downsample(image, DOWNSAMPLE)) for image in images]
        return np.stack(floats), paths
    images = read_images(small)
    check_same_size(images, small)
    return np.stack([composite_on_white(to_float(image)) for image in images]), small


def _load_views(scene_dir: Path, ids: list[int], meta: Any, path: Path, downscale: int) -> Views:
    frames = _frames(meta, path)
    paths = [_image_path(scene_dir, frames[i]["file_path"]) for i in ids]
    poses = np.stack(
        [
            parse_transform_matrix(
                frames[i]["transform_matrix"], f"{path}: the transform_matrix of frame {i}"
            )
            for i in ids
        ]
    )
    images, sources = _read_split_images(paths)
    height, width = images.shape[1:3]
    check_factor(downscale, height, width, sources[0])
    focal, intrinsics = downscale_centred_camera(
        0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"])), height, width, downscale, len(ids)
    )
    if downscale > 1:
        images = np.stack([downscale_image(image, downscale) for image in images])
    return Views(
        images=np.ascontiguousarray(images, np.float32),
        camtoworlds=poses.astype(np.float32),
        focal=float(focal),
        ids=tuple(ids),
        intrinsics=intrinsics,
    )


def _centres(meta: Any, path: Path) -> np.ndarray:
    """Every frame's camera centre."""
    return np.stack(
        [
            parse_transform_matrix(frame["transform_matrix"], f"{path}: the transform_matrix of frame {i}")[:3, 3]
            for i, frame in enumerate(_frames(meta, path))
        ]
    )


def _validation(
    scene_dir: Path, train_meta: Any, train_path: Path, train_ids: list[int], test: Views, max_views: int, downscale: int
) -> tuple[Views | None, str]:
    """The validation views and where they come from (see the module docstring)."""
    train_centres = _centres(train_meta, train_path)
    test_centres = np.asarray(test.camtoworlds, np.float64)[:, :3, 3]
    val_path = scene_dir / "transforms_val.json"
    if val_path.is_file():
        val_meta = read_json(val_path, "Blender camera file", _ADVICE)
        frames = _frames(val_meta, val_path)
        near = near_test(_centres(val_meta, val_path), train_centres[train_ids], test_centres)
        kept = [i for i in range(len(frames)) if not near[i]]
        ids = subsample_test_ids(kept, max_views)
        paths = [_image_path(scene_dir, frames[i]["file_path"]) for i in ids]
        if ids and all(p.is_file() or _downsampled_path(p).is_file() for p in paths):
            source = describe_validation("transforms_val.json", "", ids, len(frames) - len(kept))
            return _load_views(scene_dir, ids, val_meta, val_path, downscale), source
    # The unused training frames; the test cameras join the frames' own, for `near_test`.
    count = len(train_centres)
    ids, left_out = validation_ids(
        list(range(count)),
        train_ids,
        max_views,
        centres=np.concatenate([train_centres, test_centres]),
        train_ids=train_ids,
        test_ids=list(range(count, count + len(test_centres))),
    )
    source = describe_validation(
        "training frames not trained on (transforms_val.json's images are missing)",
        "no val images and no unused training frame",
        ids,
        left_out,
    )
    if not ids:
        return None, source
    return _load_views(scene_dir, ids, train_meta, train_path, downscale), source


def load_blender(
    scene_dir: Path,
    *,
    num_train_views: int,
    protocol: Literal["mixnerf", "dietnerf"] = "mixnerf",
    max_test_views: int = 0,
    max_val_views: int = 0,
    downscale: int = 1,
) -> Dataset:
    """Loads one NeRF synthetic scene under the chosen protocol.

    **Arguments:**

    - `scene_dir`: the scene's folder (holding `transforms_train.json`, `transforms_test.json`).
    - `num_train_views`: the number of training views.
    - `protocol`: `"mixnerf"` or `"dietnerf"` (see the module docstring).
    - `max_test_views`: keep only this many of the protocol's test views, evenly spaced
      (0 keeps them all).
    - `max_val_views`: the number of validation views, evenly spaced (0: every one there is;
      the val split has 100).
    - `downscale`: area-average `downscale x downscale` blocks of the composited 400x400
      images and divide the focal length by it (see the module docstring); 1 keeps 400x400.

    **Returns:**

    A `Dataset` at 400x400 (over `downscale`) on a white background, with near 2 and far 6.
    """
    train_path = scene_dir / "transforms_train.json"
    test_path = scene_dir / "transforms_test.json"
    train_meta = read_json(train_path, "Blender camera file", _ADVICE)
    test_meta = read_json(test_path, "Blender camera file", _ADVICE)
    train_ids, test_ids = split_ids(
        protocol,
        len(_frames(train_meta, train_path)),
        len(_frames(test_meta, test_path)),
        num_train_views,
        train_path,
    )
    test_ids = subsample_test_ids(test_ids, max_test_views)
    train = _load_views(scene_dir, train_ids, train_meta, train_path, downscale)
    test = _load_views(scene_dir, test_ids, test_meta, test_path, downscale)
    val, val_source = _validation(scene_dir, train_meta, train_path, train_ids, test, max_val_views, downscale)
    return Dataset(
        name=scene_dir.name,
        train=train,
        test=test,
        near=NEAR,
        far=FAR,
        white_background=True,
        frustum="cone",
        val=val,
        val_source=val_source,
    )


def _load_from_config(scene_dir: Path, config: DataConfig) -> Dataset:
    return load_blender(
        scene_dir,
        num_train_views=config.num_train_views,
        protocol=config.protocol,
        max_test_views=config.max_test_views,
        max_val_views=config.max_val_views,
        downscale=config.image_downscale,
    )


FORMAT = DatasetFormat(
    name="blender",
    layouts=("nerf_synthetic",),
    scenes=SCENES,
    release="the NeRF synthetic release (nerf_synthetic/)",
    load=_load_from_config,
)
