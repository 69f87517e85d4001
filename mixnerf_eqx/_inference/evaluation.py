"""Rendering images in bounded memory, and scoring them against held-out views."""

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._nn.chunks import join_chunks, map_ray_chunks
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from .._nn.renderer import LevelOutputs
from ..data import Dataset, Views, rays_for_views
from ..metrics import (
    average_error,
    composite_outside_mask,
    depth_error,
    lpips,
    lpips_available,
    masked_psnr,
    psnr,
    ssim,
)
from .skipping import RenderCounts, Skipping, render_skipping


@eqx.filter_jit
def _render_dense(model: MixNeRF, rays: RayBundle) -> LevelOutputs:
    return model(rays).fine


@dataclasses.dataclass(frozen=True)
class Rendered:
    """Rendered rays on the host, with what rendering them cost.

    **Fields:**

    - `rgb`, `depth`, `acc`: colour, expected depth and opacity, with the rays' batch shape
      in front.
    - `counts`: rays and field evaluations.
    """

    rgb: np.ndarray
    depth: np.ndarray
    acc: np.ndarray
    counts: RenderCounts

    def select(self, index: int) -> "Rendered":
        """The rays of position `index` along the first batch dimension (e.g. one view)."""
        return dataclasses.replace(self, rgb=self.rgb[index], depth=self.depth[index], acc=self.acc[index])


def _render_chunk(
    model: MixNeRF, piece: RayBundle, real: int, skipping: Skipping | None
) -> tuple[LevelOutputs, RenderCounts]:
    """One chunk of rays, of which the first `real` are real, dense or with skipping."""
    if skipping is not None:
        return render_skipping(model, piece, jnp.arange(piece.batch_shape[0]) < real, skipping)
    per_ray = model.samples_per_ray
    counts = RenderCounts(
        rays=real,
        dense_evaluations=real * per_ray,
        field_evaluations=real * per_ray,
        padded_evaluations=piece.batch_shape[0] * per_ray,
    )
    return _render_dense(model, piece), counts


def render_rays(
    model: MixNeRF, rays: RayBundle, chunk: int = 4096, *, skipping: Skipping | None = None
) -> Rendered:
    """Deterministically renders any number of rays, `chunk` rays at a time
    (`map_ray_chunks`: one compiled renderer, memory bounded by the chunk).

    **Arguments:**

    - `model`: the model.
    - `rays`: rays of any batch shape.
    - `chunk`: rays rendered at once.
    - `skipping`: skip empty space and finished rays (`mixnerf_eqx.inference.Skipping`); `None`
      evaluates the field at every sample.

    **Returns:**

    A `Rendered` with `rays.batch_shape` in front.
    """
    batch_shape = rays.batch_shape

    def render(piece: RayBundle, real: int, _) -> tuple[tuple[Array, Array, Array], RenderCounts]:
        level, counts = _render_chunk(model, piece, real, skipping)
        return (level.rgb, level.depth, level.acc), counts

    parts, count = map_ray_chunks(render, rays, chunk)
    if not parts:
        empty = np.empty((0,), np.float32)
        return Rendered(
            rgb=np.empty((*batch_shape, 3), np.float32),
            depth=empty.reshape(batch_shape),
            acc=empty.reshape(batch_shape),
            counts=RenderCounts(),
        )
    rgb, depth, acc = (join_chunks([outputs[i] for outputs, _ in parts], count) for i in range(3))
    counts = sum((chunk_counts for _, chunk_counts in parts), RenderCounts())
    return Rendered(
        rgb=rgb.astype(np.float32, copy=False).reshape(*batch_shape, 3),
        depth=depth.astype(np.float32, copy=False).reshape(batch_shape),
        acc=acc.astype(np.float32, copy=False).reshape(batch_shape),
        counts=counts,
    )


def render_views(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    chunk: int = 4096,
    *,
    skipping: Skipping | None = None,
) -> Rendered:
    """Renders every view of `views`; the rays of one view at a time exist on the host.

    **Returns:**

    A `Rendered` stacked over the views (`skipping` as in `render_rays`).
    """
    rgb = np.empty((views.num_views, views.height, views.width, 3), np.float32)
    depth = np.empty((views.num_views, views.height, views.width), np.float32)
    acc = np.empty_like(depth)
    counts = RenderCounts()
    for index in range(views.num_views):
        rays = rays_for_views(views.select([index]), near, far)
        view = render_rays(model, rays, chunk, skipping=skipping)
        rgb[index], depth[index], acc[index] = view.rgb[0], view.depth[0], view.acc[0]
        counts = counts + view.counts
    return Rendered(rgb=rgb, depth=depth, acc=acc, counts=counts)


def image_metrics(
    prediction: np.ndarray,
    target: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    with_lpips: bool = True,
) -> dict[str, float | None]:
    """PSNR, SSIM, LPIPS and the "average" error of one rendered image.

    With an object `mask` (DTU), PSNR uses the masked pixels only and SSIM and LPIPS see both
    images composited on white outside the mask, as in RegNeRF's and MixNeRF's evaluation.
    LPIPS (and so the average) is `None` when its weights are not installed or when
    `with_lpips` is false: it is reported as unavailable, never as a stand-in number.
    """
    if mask is None:
        scores = {"psnr": psnr(prediction, target)}
        structural_pred, structural_target = prediction, target
    else:
        scores = {"psnr": masked_psnr(prediction, target, mask)}
        structural_pred = composite_outside_mask(prediction, mask)
        structural_target = composite_outside_mask(target, mask)
    scores["ssim"] = ssim(structural_pred, structural_target)
    if with_lpips and lpips_available():
        scores["lpips"] = lpips(structural_pred, structural_target)
        scores["average"] = average_error(scores["psnr"], scores["ssim"], scores["lpips"])
    else:
        scores["lpips"] = None
        scores["average"] = None
    return scores


def mean_metrics(per_view: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """The mean of every metric over the views (`None` where a metric is unavailable)."""
    names = [name for name in per_view[0] if name != "view"]
    means: dict[str, float | None] = {}
    for name in names:
        values = [view[name] for view in per_view]
        means[name] = None if any(v is None for v in values) else float(np.mean(values))
    return means


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Scores of rendered held-out views.

    **Fields:**

    - `means`: each metric's mean over the views (`None` where it is unavailable).
    - `per_view`: each view's id and metrics.
    - `counts`: rays and field evaluations of the renders.
    - `seconds`: wall-clock time of rendering and scoring.
    """

    means: dict[str, float | None]
    per_view: list[dict[str, Any]]
    counts: RenderCounts
    seconds: float


def evaluate(
    model: MixNeRF,
    dataset: Dataset,
    *,
    chunk: int = 4096,
    view_ids: Sequence[int] | None = None,
    with_lpips: bool = True,
    on_view: Callable[[int, dict[str, Any], Rendered], None] | None = None,
    skipping: Skipping | None = None,
    split: Literal["test", "val", "train"] = "test",
) -> Evaluation:
    """Renders the views of one split one at a time and scores each.

    **Arguments:**

    - `model`: the trained model.
    - `dataset`: the scene; the views of its split `split` are rendered.
    - `chunk`: rays rendered at once.
    - `view_ids`: positions of the split's views to use (default: all).
    - `with_lpips`: compute LPIPS where its weights are installed.
    - `on_view`: called as `on_view(position, metrics, rendered view)` after each view,
      e.g. to write its PNGs, so that nothing but the metrics has to be kept.
    - `skipping`: passed to `render_rays`.
    - `split`: `"test"` (the protocol's test views, to score once for the record), `"val"`
      (the validation views, to choose settings on) or `"train"`.

    **Returns:**

    An `Evaluation`.
    """
    started = time.perf_counter()
    views = dataset.split(split)
    views = views if view_ids is None else views.select(view_ids)
    per_view = []
    counts = RenderCounts()
    for index in range(views.num_views):
        one = views.select([index])
        rendered = render_views(model, one, dataset.near, dataset.far, chunk, skipping=skipping).select(0)
        counts = counts + rendered.counts
        mask = None if one.masks is None else one.masks[0]
        entry: dict[str, Any] = {"view": int(one.ids[0])}
        entry.update(image_metrics(rendered.rgb, one.images[0], mask=mask, with_lpips=with_lpips))
        if one.depths is not None:
            entry["depth_mae"] = depth_error(rendered.depth, one.depths[0])
        per_view.append(entry)
        if on_view is not None:
            on_view(index, entry, rendered)
    return Evaluation(mean_metrics(per_view), per_view, counts, time.perf_counter() - started)
