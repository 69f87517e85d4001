import numpy as np
import pytest

from mixnerf_eqx.metrics import ssim


def _reference_ssim(x: np.ndarray, y: np.ndarray) -> float:
    # Direct float64 loop over every valid 11x11 window and channel, with weighted moments
    # computed about the window means (not E[x^2] - E[x]^2 as the implementation does).
    size, sigma, c1, c2 = 11, 1.5, 0.01**2, 0.03**2
    offsets = np.arange(size) - (size - 1) / 2
    profile = np.exp(-(offsets**2) / (2 * sigma**2))
    window = np.outer(profile, profile)
    window /= window.sum()
    height, width, channels = x.shape
    values = []
    for row in range(height - size + 1):
        for col in range(width - size + 1):
            for channel in range(channels):
                patch_x = x[row : row + size, col : col + size, channel]
                patch_y = y[row : row + size, col : col + size, channel]
                mean_x = np.sum(window * patch_x)
                mean_y = np.sum(window * patch_y)
                var_x = np.sum(window * (patch_x - mean_x) ** 2)
                var_y = np.sum(window * (patch_y - mean_y) ** 2)
                cov = np.sum(window * (patch_x - mean_x) * (patch_y - mean_y))
                numerator = (2 * mean_x * mean_y + c1) * (2 * cov + c2)
                denominator = (mean_x**2 + mean_y**2 + c1) * (var_x + var_y + c2)
                values.append(numerator / denominator)
    return float(np.mean(values))


def _pair(kind: str):
    rng = np.random.default_rng(11)
    shape = (17, 15, 3)
    x = rng.uniform(size=shape)
    if kind == "independent":
        y = rng.uniform(size=shape)
    elif kind == "noisy":
        y = np.clip(x + rng.normal(scale=0.05, size=shape), 0, 1)
    else:  # "anticorrelated"
        y = 1.0 - 0.5 * x
    return x, y


@pytest.mark.parametrize("kind", ["independent", "noisy", "anticorrelated"])
def test_ssim_matches_a_per_window_loop(kind):
    x, y = _pair(kind)
    expected = _reference_ssim(x, y)
    assert ssim(x, y) == pytest.approx(expected, abs=1e-10)
    assert ssim(y, x) == pytest.approx(expected, abs=1e-10)


def test_ssim_of_identical_images_is_one():
    x, _ = _pair("independent")
    assert ssim(x, x.copy()) == pytest.approx(1.0, abs=1e-12)


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="smaller than"):
        ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))
