"""Metrics of the DTU protocol: PSNR within object masks, the background composited outside
them, and the average error of RegNeRF's tables."""

import math

import numpy as np
from jaxtyping import Bool, Float

from ._image import mse_to_psnr


def average_error(psnr: float, ssim: float, lpips: float) -> float:
    """The "average" error of RegNeRF and MixNeRF: the geometric mean of
    MSE = 10^(-PSNR/10), sqrt(1 - SSIM) and LPIPS. Lower is better.
    """
    mse = 10.0 ** (-psnr / 10.0)
    # SSIM can exceed 1 by rounding only; clamp so that the square root stays real.
    structural = math.sqrt(max(0.0, 1.0 - ssim))
    return float((mse * structural * lpips) ** (1.0 / 3.0))


def _check_mask(image: np.ndarray, mask: np.ndarray) -> None:
    if image.shape[:2] != mask.shape:
        raise ValueError(f"the mask of shape {mask.shape} does not cover an image of shape {image.shape}")


def masked_psnr(
    prediction: Float[np.ndarray, "height width channels"],
    target: Float[np.ndarray, "height width channels"],
    mask: Bool[np.ndarray, "height width"],
) -> float:
    """PSNR (data range 1) from the mean squared error over the channel values of the pixels
    inside the object `mask` only (DTU's protocol in RegNeRF and MixNeRF).

    **Raises:**

    - `ValueError` when the mask selects no pixel.
    """
    _check_mask(prediction, mask)
    if not mask.any():
        raise ValueError("the object mask selects no pixel")
    difference = np.asarray(prediction, np.float64)[mask] - np.asarray(target, np.float64)[mask]
    return mse_to_psnr(float(np.mean(difference**2)))


def composite_outside_mask(
    image: Float[np.ndarray, "height width channels"], mask: Bool[np.ndarray, "height width"]
) -> Float[np.ndarray, "height width channels"]:
    """The image with every pixel outside the object `mask` set to white (1.0), as SSIM and
    LPIPS see DTU's images. Returns a new array of the image's dtype.
    """
    _check_mask(image, mask)
    return np.where(mask[..., None], image, np.ones((), image.dtype))
