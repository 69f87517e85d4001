"""The typed dataset that every loader produces."""

import dataclasses
from collections.abc import Sequence
from typing import Literal

import numpy as np
from jaxtyping import Bool, Float

from .._custom_types import DepthStack, ImageStack, PoseStack
from .._nn.rays import RayBundle, camera_rays


@dataclasses.dataclass(frozen=True)
class Views:
    """A set of posed pinhole images of one scene (host memory, float32).

    **Fields:**

    - `images`: linear RGB in [0, 1], already composited on the background.
    - `camtoworlds`: camera-to-world matrices (OpenGL convention, see `mixnerf_eqx._nn.rays`).
    - `focal`: focal length in pixels.
    - `depths`: true depth along the unnormalised ray direction (camera z-depth), `inf`
      where the ray hits nothing; `None` when the scene has no true depth.
    - `ids`: the views' indices in the source dataset, for reporting.
    - `intrinsics`: per-view pinhole matrices `K` in the OpenCV pixel convention (see
      `mixnerf_eqx._nn.rays`), for cameras whose principal point is off-centre, whose two focal
      lengths differ, or whose intrinsics differ from view to view (DTU); `None`: `focal` on
      both axes and the principal point at the image centre.
    - `masks`: object masks, true on the object (DTU's evaluation masks); `None` when the
      metrics use every pixel.
    - `ndc`: the rays live in normalised device coordinates (forward-facing LLFF scenes).
    - `origin_plane_z`: ray origins move along their rays onto the world plane
      `z = origin_plane_z` (RegNeRF's DTU rays); `None` keeps them at the camera centres.
    """

    images: ImageStack
    camtoworlds: PoseStack
    focal: float
    depths: DepthStack | None = None
    ids: tuple[int, ...] = ()
    intrinsics: Float[np.ndarray, "num_views 3 3"] | None = None
    masks: Bool[np.ndarray, "num_views height width"] | None = None
    ndc: bool = False
    origin_plane_z: float | None = None

    def __post_init__(self):
        num_views = self.images.shape[0]
        if self.camtoworlds.shape != (num_views, 3, 4):
            raise ValueError(f"camtoworlds has shape {self.camtoworlds.shape}, expected ({num_views}, 3, 4)")
        if self.depths is not None and self.depths.shape != self.images.shape[:3]:
            raise ValueError(f"depths has shape {self.depths.shape}, expected {self.images.shape[:3]}")
        if self.intrinsics is not None and self.intrinsics.shape != (num_views, 3, 3):
            raise ValueError(f"intrinsics has shape {self.intrinsics.shape}, expected ({num_views}, 3, 3)")
        if self.masks is not None and self.masks.shape != self.images.shape[:3]:
            raise ValueError(f"masks has shape {self.masks.shape}, expected {self.images.shape[:3]}")
        if self.ndc and self.origin_plane_z is not None:
            raise ValueError("NDC rays start on the near plane: origin_plane_z must be None")
        if not self.ids:
            object.__setattr__(self, "ids", tuple(range(num_views)))
        if len(self.ids) != num_views:
            raise ValueError(f"{len(self.ids)} ids for {num_views} views")

    @property
    def num_views(self) -> int:
        return self.images.shape[0]

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]

    def select(self, indices: Sequence[int]) -> "Views":
        """The views at positions `indices` (not source ids), with all their per-view data."""
        indices = [int(i) for i in indices]

        def pick(array):
            return None if array is None else array[indices]

        return dataclasses.replace(
            self,
            images=self.images[indices],
            camtoworlds=self.camtoworlds[indices],
            depths=pick(self.depths),
            ids=tuple(self.ids[i] for i in indices),
            intrinsics=pick(self.intrinsics),
            masks=pick(self.masks),
        )


@dataclasses.dataclass(frozen=True)
class Dataset:
    """A scene split into training, validation and held-out test views.

    **Fields:**

    - `name`: a human-readable scene name.
    - `train`, `test`: the protocol's training and test views.
    - `val`: validation views, disjoint from both: the views that settings are chosen on and
      that the periodic evaluation of training renders, so that the test views are scored
      once, at the end. `None` when the scene has no view left over (see `val_source`).
    - `val_source`: where the validation views come from, for reports.
    - `near`, `far`: sampling bounds along the unnormalised ray directions.
    - `white_background`: composite renders on white (Blender-style scenes).
    - `frustum`: `"cone"` for bounded scenes, `"cylinder"` for NDC (LLFF) scenes.

    Build the rays of any split with `rays_for_views`; `split(name)` picks one by name.
    """

    name: str
    train: Views
    test: Views
    near: float
    far: float
    white_background: bool = True
    frustum: Literal["cone", "cylinder"] = "cone"
    val: Views | None = None
    val_source: str = "none"

    def __post_init__(self):
        if not 0 <= self.near < self.far:
            raise ValueError(f"need 0 <= near < far, got near={self.near}, far={self.far}")

    def split(self, name: str) -> Views:
        """The views of split `name` (`"train"`, `"val"` or `"test"`); a clear error when the
        scene has no validation views. (`str`, not a `Literal`: a wrong name gets this
        method's message, not a type-check error.)"""
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r}; choose one of {', '.join(SPLITS)}")
        views = getattr(self, name)
        if views is None:
            raise ValueError(
                f"{self.name} has no validation views ({self.val_source}); score on another split, "
                "or train on fewer views so that some are left over"
            )
        return views


SPLITS = ("train", "val", "test")


def rays_for_views(views: Views, near: float, far: float) -> RayBundle:
    """The rays through every pixel of `views`, in the ray space the views ask for.

    This is `mixnerf_eqx._nn.rays.camera_rays` with the views' own intrinsics, NDC flag and
    origin plane, so that training and evaluation build rays the same way for every dataset.

    **Arguments:**

    - `views`: the posed images.
    - `near`, `far`: sampling bounds along the unnormalised directions (a `Dataset`'s).

    **Returns:**

    A float32 `RayBundle` with batch shape `(num_views, height, width)`.
    """
    return camera_rays(
        views.camtoworlds,
        views.focal,
        views.height,
        views.width,
        near,
        far,
        intrinsics=views.intrinsics,
        ndc=views.ndc,
        origin_plane_z=views.origin_plane_z,
    )


def rays_at_poses(like: Views, camtoworlds: PoseStack, near: float, far: float) -> RayBundle:
    """The rays of cameras at `camtoworlds` with `like`'s image size, intrinsics (its first
    view's) and ray space: views that no image was taken from (videos, priors on unseen views).

    **Returns:**

    A float32 `RayBundle` with batch shape `(num_poses, height, width)`.
    """
    intrinsics = None if like.intrinsics is None else np.repeat(like.intrinsics[:1], len(camtoworlds), axis=0)
    return camera_rays(
        camtoworlds,
        like.focal,
        like.height,
        like.width,
        near,
        far,
        intrinsics=intrinsics,
        ndc=like.ndc,
        origin_plane_z=like.origin_plane_z,
    )
