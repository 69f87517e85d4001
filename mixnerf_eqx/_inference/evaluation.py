"""Scoring rendered views against held-out views: per-view metrics and their means, and
`evaluate`, which renders a split (`rendering.render_views`) and scores it."""

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np

from .._nn.model import MixNeRF
from ..data import Dataset
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
from .rendering import Rendered, render_views
from .skipping import RenderCounts, Skipping


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
