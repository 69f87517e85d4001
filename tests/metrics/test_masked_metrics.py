import math

import numpy as np
import pytest
from jaxtyping import TypeCheckError

from mixnerf_eqx.metrics import average_error, composite_outside_mask, masked_psnr, psnr


@pytest.mark.parametrize(
    "psnr_db,ssim_value,lpips_value,expected",
    [
        # MSE 0.01, sqrt(1 - 0.75) = 0.5, LPIPS 0.2: cube root of 0.001.
        (20.0, 0.75, 0.2, 0.1),
        # MSE 0.001, sqrt(1 - 0.96) = 0.2, LPIPS 0.005: cube root of 1e-6.
        (30.0, 0.96, 0.005, 0.01),
        # MSE 1, sqrt(1 - 0) = 1, LPIPS 0.512: cube root 0.8.
        (0.0, 0.0, 0.512, 0.8),
    ],
)
def test_average_error_closed_form(psnr_db, ssim_value, lpips_value, expected):
    assert average_error(psnr_db, ssim_value, lpips_value) == pytest.approx(expected, rel=1e-12)


def _random_case(seed: int):
    rng = np.random.default_rng(seed)
    prediction = rng.uniform(size=(13, 17, 3)).astype(np.float32)
    target = rng.uniform(size=(13, 17, 3)).astype(np.float32)
    mask = rng.uniform(size=(13, 17)) < 0.4
    return prediction, target, mask


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_masked_psnr_matches_a_float64_reference(seed):
    prediction, target, mask = _random_case(seed)
    weights = mask.astype(np.float64)[..., None]
    squared = (prediction.astype(np.float64) - target.astype(np.float64)) ** 2
    mse = np.sum(weights * squared) / (3.0 * np.sum(weights))
    expected = -10.0 * math.log10(mse)
    assert masked_psnr(prediction, target, mask) == pytest.approx(expected, rel=1e-12)
    # The pixels outside the mask must not count: a different PSNR unless by coincidence.
    assert abs(masked_psnr(prediction, target, mask) - psnr(prediction, target)) > 1e-3


def test_masked_psnr_ignores_pixels_outside_the_mask():
    prediction, target, mask = _random_case(3)
    changed = prediction.copy()
    changed[~mask] = 1.0 - changed[~mask]
    assert masked_psnr(changed, target, mask) == masked_psnr(prediction, target, mask)
    with pytest.raises(ValueError, match="no pixel"):
        masked_psnr(prediction, target, np.zeros_like(mask))


def test_masked_psnr_of_a_full_mask_is_psnr():
    prediction, target, _ = _random_case(4)
    full = np.ones(prediction.shape[:2], bool)
    assert masked_psnr(prediction, target, full) == pytest.approx(psnr(prediction, target), rel=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_composite_outside_mask_is_white(dtype):
    prediction, _, mask = _random_case(5)
    image = prediction.astype(dtype)
    weights = mask.astype(np.float64)[..., None]
    expected = weights * image.astype(np.float64) + (1.0 - weights) * 1.0
    composited = composite_outside_mask(image, mask)
    assert composited.dtype == dtype and composited.shape == image.shape
    np.testing.assert_array_equal(composited.astype(np.float64), expected)
    assert np.all(composited[~mask] == 1.0)
    # The input is left as it was.
    np.testing.assert_array_equal(image, prediction.astype(dtype))


def test_composite_rejects_a_mask_of_another_size():
    prediction, _, mask = _random_case(6)
    # Under the jaxtyping hook the annotations reject the mask first, naming it.
    with pytest.raises((ValueError, TypeCheckError), match="mask"):
        composite_outside_mask(prediction, mask[:-1])
