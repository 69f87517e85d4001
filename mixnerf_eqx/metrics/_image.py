"""Image metrics, computed in numpy: PSNR, SSIM (an 11-pixel Gaussian window) and the mean
depth error."""

import numpy as np
from jaxtyping import Float


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB of a mean squared error on a [0, 1] signal."""
    return float(-10.0 * np.log10(max(mse, 1e-30)))


def psnr(
    prediction: Float[np.ndarray, "height width channels"], target: Float[np.ndarray, "height width channels"]
) -> float:
    """Peak signal-to-noise ratio (data range 1)."""
    difference = np.asarray(prediction, np.float64) - np.asarray(target, np.float64)
    return mse_to_psnr(float(np.mean(difference**2)))


def _gaussian_filter_valid(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    # Separable 'valid' convolution over the two spatial axes of an (H, W, C) image.
    size = kernel.shape[0]
    rows = sum(kernel[i] * image[i : image.shape[0] - size + 1 + i] for i in range(size))
    return sum(kernel[i] * rows[:, i : rows.shape[1] - size + 1 + i] for i in range(size))


def ssim(
    prediction: Float[np.ndarray, "height width channels"],
    target: Float[np.ndarray, "height width channels"],
    *,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> float:
    """Structural similarity with a `window`x`window` Gaussian window (data range 1).

    The mean over channels and over the valid (unpadded) window positions, as in mip-NeRF's
    and RegNeRF's evaluation.
    """
    x = np.asarray(prediction, np.float64)
    y = np.asarray(target, np.float64)
    if x.shape != y.shape:
        raise ValueError(f"shapes differ: {x.shape} and {y.shape}")
    if min(x.shape[:2]) < window:
        raise ValueError(f"images of size {x.shape[:2]} are smaller than the {window}-pixel window")
    offsets = np.arange(window) - (window - 1) / 2
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    kernel /= kernel.sum()
    mu_x = _gaussian_filter_valid(x, kernel)
    mu_y = _gaussian_filter_valid(y, kernel)
    var_x = np.maximum(0.0, _gaussian_filter_valid(x * x, kernel) - mu_x**2)
    var_y = np.maximum(0.0, _gaussian_filter_valid(y * y, kernel) - mu_y**2)
    cov = _gaussian_filter_valid(x * y, kernel) - mu_x * mu_y
    # Keep the correlation coefficient within [-1, 1] despite rounding.
    bound = np.sqrt(var_x * var_y)
    cov = np.clip(cov, -bound, bound)
    c1, c2 = k1**2, k2**2
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    denominator = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return float(np.mean(numerator / denominator))


def depth_error(
    prediction: Float[np.ndarray, "height width"], target: Float[np.ndarray, "height width"]
) -> float:
    """Mean absolute depth error over the pixels whose true depth is finite (foreground)."""
    mask = np.isfinite(target)
    if not mask.any():
        return float("nan")
    return float(np.mean(np.abs(np.asarray(prediction, np.float64)[mask] - target[mask])))
