"""Writing renders as PNG files."""

from pathlib import Path

import numpy as np
from jaxtyping import Float
from PIL import Image


def to_uint8(image: Float[np.ndarray, "height width *channels"]) -> np.ndarray:
    """Clips to [0, 1] and quantises to 8 bits."""
    return np.round(np.clip(np.nan_to_num(image), 0.0, 1.0) * 255).astype(np.uint8)


def colourise_depth(
    depth: Float[np.ndarray, "height width"], near: float, far: float
) -> Float[np.ndarray, "height width channels"]:
    """Maps depth to a perceptually ordered colour ramp (near bright yellow, far dark blue).

    Non-finite depths (no surface) are shown in white.
    """
    finite = np.isfinite(depth)
    normalised = np.clip((np.where(finite, depth, far) - near) / max(far - near, 1e-12), 0.0, 1.0)
    # A short piecewise-linear ramp through the viridis anchor colours.
    anchors = np.array(
        [
            [0.993, 0.906, 0.144],
            [0.369, 0.788, 0.384],
            [0.128, 0.567, 0.551],
            [0.231, 0.322, 0.545],
            [0.267, 0.005, 0.329],
        ]
    )
    position = normalised * (len(anchors) - 1)
    lower = np.floor(position).astype(int).clip(0, len(anchors) - 2)
    fraction = (position - lower)[..., None]
    colour = anchors[lower] * (1 - fraction) + anchors[lower + 1] * fraction
    return np.where(finite[..., None], colour, 1.0)


def save_png(path: str | Path, image: Float[np.ndarray, "height width *channels"]) -> None:
    """Saves a float image in [0, 1] (greyscale or RGB) as an 8-bit PNG."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(to_uint8(image)).save(path)
