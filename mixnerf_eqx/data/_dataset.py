"""The typed dataset that every loader produces."""

import dataclasses
from typing import Literal

import numpy as np
from jaxtyping import Float

from .._custom_types import DepthStack, ImageStack, PoseStack


@dataclasses.dataclass(frozen=True)
class Views:
    """A set of posed pinhole images of one scene (host memory, float32).

    **Fields:**

    - `images`: linear RGB in [0, 1], already composited on the background.
    - `camtoworlds`: camera-to-world matrices (OpenGL convention, see `mixnerf_eqx._rays`).
    - `focal`: focal length in pixels.
    - `depths`: true depth along the unnormalised ray direction (camera z-depth), `inf`
      where the ray hits nothing; `None` when the scene has no true depth.
    - `ids`: the views' indices in the source dataset, for reporting.
    """

    images: ImageStack
    camtoworlds: PoseStack
    focal: float
    depths: DepthStack | None = None
    ids: tuple[int, ...] = ()

    def __post_init__(self):
        num_views = self.images.shape[0]
        if self.camtoworlds.shape != (num_views, 3, 4):
            raise ValueError(f"camtoworlds has shape {self.camtoworlds.shape}, expected ({num_views}, 3, 4)")
        if self.depths is not None and self.depths.shape != self.images.shape[:3]:
            raise ValueError(f"depths has shape {self.depths.shape}, expected {self.images.shape[:3]}")
        if not self.ids:
            object.__setattr__(self, "ids", tuple(range(num_views)))

    @property
    def num_views(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]


@dataclasses.dataclass(frozen=True)
class Dataset:
    """A scene split into training and held-out test views.

    **Fields:**

    - `name`: a human-readable scene name.
    - `train`, `test`: the two splits.
    - `near`, `far`: sampling bounds along the unnormalised ray directions.
    - `white_background`: composite renders on white (Blender-style scenes).
    - `frustum`: `"cone"` for bounded scenes, `"cylinder"` for NDC (LLFF) scenes.
    """

    name: str
    train: Views
    test: Views
    near: float
    far: float
    white_background: bool = True
    frustum: Literal["cone", "cylinder"] = "cone"

    def __post_init__(self):
        if not 0 <= self.near < self.far:
            raise ValueError(f"need 0 <= near < far, got near={self.near}, far={self.far}")


def check_images(images: Float[np.ndarray, "..."], name: str) -> None:
    """Raises a clear error when an image stack is not finite float data in [0, 1]."""
    if not np.all(np.isfinite(images)):
        raise ValueError(f"{name}: images contain non-finite values")
    if images.min() < 0 or images.max() > 1:
        raise ValueError(f"{name}: image values must lie in [0, 1]")
