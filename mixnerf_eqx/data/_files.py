"""Reading dataset files: images, JSON and numpy arrays, with errors that name the file.

Images are decoded once, on a few threads (Pillow releases the GIL while it decodes), and
turned into float32 arrays; area downsampling by an integer factor is an exact box average
of the 8-bit values, computed in integers and divided once.
"""

import json
import os
import re
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float, UInt8
from PIL import Image

from ._errors import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_MAX_DECODE_THREADS = 8


def require_dir(path: Path, what: str, advice: str) -> Path:
    """Returns `path` if it is a folder, else raises a `DatasetError` naming it."""
    if not path.is_dir():
        raise DatasetError(f"{what} not found: {path} is not a folder. {advice}")
    return path


def require_file(path: Path, what: str, advice: str) -> Path:
    """Returns `path` if it is a file, else raises a `DatasetError` naming it."""
    if not path.is_file():
        raise DatasetError(f"{what} not found: {path} does not exist. {advice}")
    return path


def read_json(path: Path, what: str, advice: str) -> Any:
    """Parses a JSON file; a missing or malformed file is a `DatasetError` naming it as `what`."""
    require_file(path, what, advice)
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: cannot read the file ({error}). {advice}") from None
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"{path}: not valid JSON (line {error.lineno}, column {error.colno}: {error.msg}). "
            "Repair the file or download it again."
        ) from None


def read_npy(path: Path, what: str, advice: str) -> np.ndarray:
    """Loads a `.npy` array; a missing or unreadable file is a `DatasetError` naming it as `what`."""
    require_file(path, what, advice)
    with open(path, "rb") as file:
        magic = file.read(6)
    if magic != b"\x93NUMPY":
        # numpy reads anything else as a pickle, and its refusal speaks of pickles.
        raise DatasetError(f"{path}: not a .npy array file (it does not start with numpy's header). {advice}")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise DatasetError(f"{path}: not a readable .npy array ({error}). {advice}") from None


def natural_key(name: str) -> tuple:
    """A sort key that orders embedded numbers by value (`r_2` before `r_10`)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name))


def list_images(folder: Path) -> list[Path]:
    """The image files of a folder, in name order (numbers by value)."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_image(path: Path) -> UInt8[np.ndarray, "height width channels"]:
    """Decodes one 8-bit image file into RGB (3 channels) or RGBA (4 channels).

    Greyscale and palette images are expanded to RGB (RGBA when they carry transparency).
    A missing, unreadable, truncated or 16-bit file is a `DatasetError` that names it.
    """
    if not path.is_file():
        raise DatasetError(f"image not found: {path} does not exist. Restore the file, or fix its name.")
    try:
        with Image.open(path) as image:
            image.load()
            mode = image.mode
            if mode in ("RGB", "RGBA"):
                converted = image
            elif mode in ("L", "1"):
                converted = image.convert("RGB")
            elif mode in ("LA", "PA") or (mode == "P" and "transparency" in image.info):
                converted = image.convert("RGBA")
            elif mode == "P":
                converted = image.convert("RGB")
            else:
                raise DatasetError(
                    f"{path}: unsupported pixel format {mode!r}; save the image as 8-bit RGB or RGBA."
                )
            return np.asarray(converted)
    except DatasetError:
        raise
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        raise DatasetError(
            f"{path}: cannot decode the image ({error}). The file is damaged or truncated: "
            "download or export it again."
        ) from None


def read_images(paths: Sequence[Path]) -> list[UInt8[np.ndarray, "height width channels"]]:
    """Decodes several image files in parallel (see `read_image`), in order."""
    if len(paths) <= 1:
        return [read_image(p) for p in paths]
    workers = min(_MAX_DECODE_THREADS, os.cpu_count() or 1, len(paths))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(read_image, paths))


def check_same_size(images: Sequence[np.ndarray], paths: Sequence[Path]) -> tuple[int, int]:
    """Returns the common `(height, width)`; images of mixed sizes are a `DatasetError`."""
    height, width = images[0].shape[:2]
    for image, path in zip(images, paths, strict=True):
        if image.shape[:2] != (height, width):
            raise DatasetError(
                f"{path}: the image is {image.shape[1]}x{image.shape[0]} but {paths[0].name} is "
                f"{width}x{height}; every image of a scene must have the same size. Replace the file "
                "with one of the right size."
            )
    return height, width


def to_float(image: UInt8[np.ndarray, "height width channels"]) -> Float[np.ndarray, "height width channels"]:
    """8-bit values to float32 in [0, 1]."""
    return image.astype(np.float32) / np.float32(255)


def area_downsample(
    image: UInt8[np.ndarray, "height width channels"], factor: int
) -> Float[np.ndarray, "out_height out_width channels"]:
    """The exact box average over `factor x factor` pixel blocks, as float32 in [0, 1].

    This is what an area resize by an integer factor computes (OpenCV's `INTER_AREA`,
    Pillow's `reduce`); the sum runs in integers, so the only rounding is the final division.
    The image's size must be a multiple of `factor`.
    """
    height, width, channels = image.shape
    if height % factor or width % factor:
        raise ValueError(f"a {width}x{height} image cannot be downsampled by {factor}")
    if factor == 1:
        return to_float(image)
    blocks = image.reshape(height // factor, factor, width // factor, factor, channels)
    sums = blocks.sum(axis=(1, 3), dtype=np.uint32)
    return sums.astype(np.float32) / np.float32(255 * factor * factor)


def composite_on_white(
    image: Float[np.ndarray, "height width _channels"],
) -> Float[np.ndarray, "height width channels"]:
    """RGB of a straight-alpha RGBA image composited on white (RGB images pass through)."""
    if image.shape[-1] == 3:
        return image
    rgb, alpha = image[..., :3], image[..., 3:]
    return rgb * alpha + (1.0 - alpha)
