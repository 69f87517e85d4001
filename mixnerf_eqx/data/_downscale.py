"""Area downscaling of a dataset's images by `data.image_downscale`, with the cameras to match.

The factor applies on top of each format's own resolution (LLFF's 504x378 `images_8/`,
Blender's 400x400, DTU's 400x300, a `transforms.json` capture's stored size): every output
pixel is the exact box average of a `factor x factor` block of those pixels.

A side that the factor does not divide first loses its remainder, half from each end (the
odd row or column, if any, from the bottom or the right), so that as little as possible of
the picture is lost and the blocks stay centred. The cameras follow: pixel centres sit at
`col + 0.5` (see `mixnerf_eqx._nn.rays`), so cropping `left` columns moves the principal point
by `-left` and box averaging divides every intrinsic by the factor; the ray through the
centre of an output pixel is then exactly the ray through the centre of its block. A
principal point at the image centre (LLFF, Blender) stays at the centre unless a remainder
is odd; then the views carry explicit intrinsics that hold the shifted principal point.
"""

from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float, UInt8

from .._nn.rays import intrinsic_matrix
from ._errors import DatasetError
from ._files import area_downsample

__all__ = [
    "check_factor",
    "crop_offsets",
    "downscale_centred_camera",
    "downscale_image",
    "downscale_intrinsics",
    "downscale_mask",
]


def check_factor(factor: int, height: int, width: int, source: Path) -> None:
    """Raises a `DatasetError` unless `factor` leaves at least one pixel of a `width x height`
    image (read from `source`, named in the message)."""
    if factor < 1:
        raise DatasetError(f"data.image_downscale must be at least 1, got {factor}.")
    if factor > min(height, width):
        raise DatasetError(
            f"{source}: data.image_downscale = {factor} is larger than the {width}x{height} images it "
            f"applies to (the dataset's own resolution); choose a factor from 1 to {min(height, width)}."
        )


def crop_offsets(height: int, width: int, factor: int) -> tuple[int, int]:
    """The rows cut from the top and the columns cut from the left before downscaling by
    `factor`: half of each side's remainder, rounded down (the rest comes off the bottom and
    the right)."""
    return (height % factor) // 2, (width % factor) // 2


def _crop(array: np.ndarray, factor: int) -> np.ndarray:
    height, width = array.shape[:2]
    top, left = crop_offsets(height, width, factor)
    return array[top : top + height - height % factor, left : left + width - width % factor]


def _block_mean(array: np.ndarray, factor: int) -> Float[np.ndarray, "..."]:
    """The float64 mean over `factor x factor` blocks of an array whose sides it divides."""
    height, width = array.shape[:2]
    blocks = array.reshape(height // factor, factor, width // factor, factor, *array.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64)


def downscale_image(
    image: UInt8[np.ndarray, "height width channels"] | Float[np.ndarray, "height width channels"],
    factor: int,
) -> Float[np.ndarray, "out_height out_width channels"]:
    """Crops the remainder (see `crop_offsets`) and box-averages `factor x factor` blocks.

    **Arguments:**

    - `image`: 8-bit values (averaged exactly in integers, see `area_downsample`) or floats
      in [0, 1] (averaged in float64).
    - `factor`: the downscaling factor; 1 returns the image as float32 values, unchanged.

    **Returns:**

    Float32 values in [0, 1].
    """
    if image.dtype == np.uint8:
        return area_downsample(_crop(image, factor), factor)
    if factor == 1:
        return image
    return _block_mean(_crop(image, factor), factor).astype(np.float32)


def downscale_mask(
    mask: Bool[np.ndarray, "height width"], factor: int
) -> Bool[np.ndarray, "out_height out_width"]:
    """An object mask for the image that `downscale_image` makes: an output pixel is on the
    object where more than half of its block is (a tie counts as off the object)."""
    if factor == 1:
        return mask
    return _block_mean(_crop(mask, factor), factor) > 0.5


def downscale_intrinsics(
    intrinsics: Float[np.ndarray, "*batch 3 3"], height: int, width: int, factor: int
) -> Float[np.ndarray, "*batch 3 3"]:
    """The pinhole matrices `K` (OpenCV pixel convention) of `height x width` images after
    `downscale_image`: the principal point moves with the crop, then rows 0 and 1 are
    divided by `factor`. Returned in float64."""
    top, left = crop_offsets(height, width, factor)
    result = np.array(intrinsics, np.float64, copy=True)
    result[..., 0, :] -= left * result[..., 2, :]
    result[..., 1, :] -= top * result[..., 2, :]
    result[..., :2, :] /= factor
    return result


def downscale_centred_camera(
    focal: float, height: int, width: int, factor: int, num_views: int
) -> tuple[float, Float[np.ndarray, "num_views 3 3"] | None]:
    """The camera of `height x width` images with focal length `focal` and the principal
    point at their centre, after `downscale_image`.

    **Arguments:**

    - `focal`: the focal length in pixels of the images before downscaling.
    - `height`, `width`: their size.
    - `factor`: the downscaling factor.
    - `num_views`: the number of views that share the camera.

    **Returns:**

    The focal length divided by `factor`, and `None` when the principal point is still at
    the centre of the downscaled images (always when `factor` divides both sides), else the
    per-view float32 intrinsics that hold it (see the module docstring).
    """
    if factor == 1:
        return focal, None
    if (height % factor) % 2 == 0 and (width % factor) % 2 == 0:
        return focal / factor, None
    k = downscale_intrinsics(intrinsic_matrix(focal, focal, width / 2, height / 2), height, width, factor)
    return focal / factor, np.repeat(k[None], num_views, axis=0).astype(np.float32)
