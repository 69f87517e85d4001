"""Rendering images in bounded memory, and scoring them against held-out views."""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._model import MixNeRF
from ._rays import RayBundle
from ._skipping import RenderStats, Skipping, render_chunk_skipping
from .data import Dataset, Views, rays_for_views
from .metrics import (
    average_error,
    composite_outside_mask,
    depth_error,
    lpips,
    lpips_available,
    masked_psnr,
    psnr,
    ssim,
)


@eqx.filter_jit
def _render_chunk(model: MixNeRF, rays: RayBundle):
    outputs = model(rays)
    return outputs.fine.rgb, outputs.fine.depth, outputs.fine.acc


def render_rays(
    model: MixNeRF,
    rays: RayBundle,
    chunk: int = 4096,
    *,
    skipping: Skipping | None = None,
    stats: RenderStats | None = None,
):
    """Deterministically renders any number of rays, `chunk` rays at a time.

    Every call of the compiled renderer sees exactly `chunk` rays (the ray table is padded
    once to a whole number of chunks), so it compiles once, and device memory is bounded by
    the chunk, not by the image. The dense renderer queues the next chunk before it copies
    the previous one back, so the device does not wait for the host between chunks.

    **Arguments:**

    - `model`: the model.
    - `rays`: rays of any batch shape.
    - `chunk`: rays rendered at once.
    - `skipping`: skip empty space and finished rays (see `mixnerf_eqx._skipping`); `None`
      evaluates the field at every sample.
    - `stats`: a `RenderStats` that receives the ray and field-evaluation counts.

    **Returns:**

    `(rgb, depth, acc)` as numpy arrays with `rays.batch_shape` in front.
    """
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    batch_shape = rays.batch_shape
    flat = rays.reshape(-1)
    count = flat.origins.shape[0]
    num_chunks = -(-count // chunk)
    pad = num_chunks * chunk - count
    if pad:
        # Padding rays repeat the last ray; their outputs are dropped.
        flat = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), flat)
    chunks = flat.reshape(num_chunks, chunk)
    rgb = np.empty((count, 3), np.float32)
    depth = np.empty((count,), np.float32)
    acc = np.empty((count,), np.float32)

    def store(index: int, outputs) -> None:
        start, stop = index * chunk, min((index + 1) * chunk, count)
        out_rgb, out_depth, out_acc = jax.device_get(outputs)
        rgb[start:stop] = out_rgb[: stop - start]
        depth[start:stop] = out_depth[: stop - start]
        acc[start:stop] = out_acc[: stop - start]

    pending = None
    for index in range(num_chunks):
        real = min(chunk, count - index * chunk)
        piece = chunks[index]
        if skipping is None:
            outputs = _render_chunk(model, piece)
            if stats is not None:
                samples = model.coarse_sampler.num_samples + model.fine_sampler.num_samples
                stats.rays += real
                stats.dense_evaluations += real * samples
                stats.field_evaluations += real * samples
                stats.padded_evaluations += chunk * samples
        else:
            valid = jnp.arange(chunk) < real
            fine = render_chunk_skipping(
                model, piece, valid, skipping, RenderStats() if stats is None else stats
            )
            outputs = (fine.rgb, fine.depth, fine.acc)
        # JAX dispatches asynchronously: this chunk is queued before the previous one is
        # copied back, which is where the host waits.
        if pending is not None:
            store(*pending)
        pending = (index, outputs)
    if pending is not None:
        store(*pending)
    return rgb.reshape(*batch_shape, 3), depth.reshape(batch_shape), acc.reshape(batch_shape)


def render_views(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    chunk: int = 4096,
    *,
    skipping: Skipping | None = None,
    stats: RenderStats | None = None,
):
    """Renders every view of `views`; the rays of one view at a time exist on the host.

    `skipping` and `stats` are passed to `render_rays`.

    **Returns:**

    `(rgb, depth, acc)` stacked over the views, as numpy arrays.
    """
    rgb = np.empty((views.num_views, views.height, views.width, 3), np.float32)
    depth = np.empty((views.num_views, views.height, views.width), np.float32)
    acc = np.empty_like(depth)
    for index in range(views.num_views):
        rays = rays_for_views(views.select([index]), near, far)
        view_rgb, view_depth, view_acc = render_rays(model, rays, chunk, skipping=skipping, stats=stats)
        rgb[index], depth[index], acc[index] = view_rgb[0], view_depth[0], view_acc[0]
    return rgb, depth, acc


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


def evaluate(
    model: MixNeRF,
    dataset: Dataset,
    *,
    chunk: int = 4096,
    view_ids: Sequence[int] | None = None,
    with_lpips: bool = True,
    on_view: Callable[[int, dict[str, Any], tuple[np.ndarray, np.ndarray, np.ndarray]], None] | None = None,
    skipping: Skipping | None = None,
    stats: RenderStats | None = None,
):
    """Renders the test views one at a time and scores each.

    **Arguments:**

    - `model`: the trained model.
    - `dataset`: the scene; its `test` views are rendered.
    - `chunk`: rays rendered at once.
    - `view_ids`: positions of the test views to use (default: all).
    - `with_lpips`: compute LPIPS where its weights are installed.
    - `on_view`: called as `on_view(position, metrics, (rgb, depth, acc))` after each view,
      e.g. to write its PNGs, so that nothing but the metrics has to be kept.
    - `skipping`, `stats`: passed to `render_rays`.

    **Returns:**

    `(mean metrics, per-view metrics)`.
    """
    views = dataset.test if view_ids is None else dataset.test.select(view_ids)
    per_view = []
    for index in range(views.num_views):
        one = views.select([index])
        rgb, depth, acc = render_views(
            model, one, dataset.near, dataset.far, chunk, skipping=skipping, stats=stats
        )
        mask = None if one.masks is None else one.masks[0]
        entry: dict[str, Any] = {"view": int(one.ids[0])}
        entry.update(image_metrics(rgb[0], one.images[0], mask=mask, with_lpips=with_lpips))
        if one.depths is not None:
            entry["depth_mae"] = depth_error(depth[0], one.depths[0])
        per_view.append(entry)
        if on_view is not None:
            on_view(index, entry, (rgb[0], depth[0], acc[0]))
    return mean_metrics(per_view), per_view
