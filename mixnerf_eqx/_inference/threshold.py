"""Choosing an occupancy grid's density threshold from the trained model itself.

A fixed density threshold means different things in different scenes: after a short run a
model may hold its whole image in a low-density haze (then even a threshold of 1 removes
content), while a converged model's empty space is far below it. `choose_threshold` picks,
per model, the largest threshold whose skipping render of a set of threshold rays (pixels
of the validation views, or of the training views) stays within a tolerance of the dense
render. Two measures of "within":

- `"bound"`: a bound on the PSNR it can lose,

      RMS(skipped - target) <= RMS(dense - target) + RMS(skipped - dense)

  (the triangle inequality for the root-mean-square norm), so the skipping render's PSNR
  against `target` is at most `20 log10(1 + RMS(skipped - dense) / RMS(dense - target))` dB
  lower than the dense one's: the worst case, where every change points along the error.
- `"psnr"`: the PSNR it does lose, `psnr(dense, target) - psnr(skipped, target)` (a gain
  counts as no loss): what the tolerance is about, measured where it matters when the rays
  are held-out pixels. Removing a faint haze changes an image in directions that have
  little to do with its error, so the bound can refuse what costs a few hundredths of a dB.

On the threshold rays either holds exactly; on other views it is an estimate.
"""

import dataclasses
import math

import jax
import numpy as np
from jaxtyping import Array, Float

from .._custom_types import PRNGKey
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from ..data import Dataset, rays_for_views
from .occupancy import OccupancyGrid
from .rendering import render_rays
from .skipping import Skipping


@dataclasses.dataclass(frozen=True)
class ThresholdTrial:
    """One tried threshold: its PSNR-drop bound on the threshold rays and its savings."""

    threshold: float
    bound_db: float
    reduction: float
    psnr_drop_db: float = math.nan  # psnr(dense) - psnr(skipped) on the threshold rays


@dataclasses.dataclass(frozen=True)
class ThresholdChoice:
    """What `choose_threshold` chose and why.

    **Fields:**

    - `threshold`: the chosen density threshold.
    - `bound_db`: its bound on the PSNR lost on the threshold rays.
    - `reduction`: dense field evaluations per evaluation made, on the threshold rays.
    - `within_tolerance`: whether its measure is within `tolerance_db`; `False` only when not
      even the threshold 0 (which skips only cells of exactly zero density) met it.
    - `tolerance_db`: the tolerance asked for.
    - `measure`: `"bound"` or `"psnr"` (module docstring).
    - `psnr_drop_db`: the PSNR it lost on the threshold rays (negative: a gain).
    - `trials`: every threshold rendered, in the order tried.
    - `views`: the views the threshold rays were drawn from (`"val"`, `"train"`), or
      `"given"` when the caller passed its own rays.
    """

    threshold: float
    bound_db: float
    reduction: float
    within_tolerance: bool
    tolerance_db: float
    trials: tuple[ThresholdTrial, ...]
    views: str = "given"
    measure: str = "bound"
    psnr_drop_db: float = math.nan


def psnr_drop_bound(
    dense: np.ndarray | Float[Array, "..."],
    skipped: np.ndarray | Float[Array, "..."],
    target: np.ndarray | Float[Array, "..."],
) -> float:
    """Upper bound in dB on `psnr(dense, target) - psnr(skipped, target)` (module docstring).

    0 when `skipped` equals `dense`; `inf` when they differ and `dense` equals `target`.
    """
    dense, skipped, target = (np.asarray(x, np.float64) for x in (dense, skipped, target))
    difference = math.sqrt(np.mean((skipped - dense) ** 2))
    error = math.sqrt(np.mean((dense - target) ** 2))
    if difference == 0:
        return 0.0
    if error == 0:
        return math.inf
    return 20 * math.log10(1 + difference / error)


def psnr_drop(
    dense: np.ndarray | Float[Array, "..."],
    skipped: np.ndarray | Float[Array, "..."],
    target: np.ndarray | Float[Array, "..."],
) -> float:
    """`psnr(dense, target) - psnr(skipped, target)` in dB, in float64 (negative: `skipped`
    is the closer); 0 when they are equal, `inf` when only `dense` equals `target`."""
    dense, skipped, target = (np.asarray(x, np.float64) for x in (dense, skipped, target))
    before, after = np.mean((dense - target) ** 2), np.mean((skipped - target) ** 2)
    if before == after:
        return 0.0
    if before == 0:
        return math.inf
    if after == 0:
        return -math.inf
    return 10 * math.log10(after / before)


def threshold_rays(
    dataset: Dataset, num_rays: int, *, key: PRNGKey, split: str = "train"
) -> tuple[RayBundle, np.ndarray]:
    """`num_rays` distinct random pixels of the views of `split` (`"train"` or `"val"`; never
    the test views): their rays and colours.

    The bound of `choose_threshold` divides by the dense render's error on these pixels. A
    few-shot model fits its training pixels far more closely than any other view (often 30 dB
    and more against about 20 on held-out views), so on training pixels a change that costs
    held-out views a few hundredths of a dB can bound above the tolerance: held-out validation
    pixels measure the error the skipping render adds where the model is actually used.
    """
    if split not in ("train", "val"):
        raise ValueError(f'threshold rays come from the "train" or "val" views, got {split!r}')
    views = dataset.split(split)
    count = views.num_views * views.height * views.width
    if num_rays < 1:
        raise ValueError(f"num_rays must be at least 1, got {num_rays}")
    seed = int(jax.random.randint(key, (), 0, 2**31 - 1))
    chosen = np.random.default_rng(seed).choice(count, size=min(num_rays, count), replace=False)
    rays = rays_for_views(views, dataset.near, dataset.far).reshape(-1)[chosen]
    colours = np.asarray(views.images, np.float32).reshape(-1, 3)[chosen]
    return rays, colours


def choose_threshold(
    model: MixNeRF,
    grid: OccupancyGrid,
    skipping: Skipping,
    rays: RayBundle,
    target: np.ndarray | Float[Array, "batch channels"],
    *,
    tolerance_db: float = 0.1,
    doublings: int = 14,
    chunk: int = 4096,
    measure: str = "bound",
) -> tuple[OccupancyGrid, ThresholdChoice]:
    """The largest threshold of `grid.threshold * 2^k`, `k = 0..doublings`, within tolerance.

    **Arguments:**

    - `model`: the trained model.
    - `grid`: its evaluated occupancy grid; `grid.threshold` (> 0) is the smallest candidate.
      Only the threshold changes between candidates (an array leaf), so every candidate
      reuses the compiled render.
    - `skipping`: the other rendering options (early termination); its grid is replaced.
    - `rays`, `target`: the threshold rays and their colours (`threshold_rays`): pixels of
      the validation or the training views, never of the test views.
    - `tolerance_db`: the largest PSNR loss accepted, as `measure` counts it.
    - `doublings`: how many times the smallest candidate is doubled at most.
    - `chunk`: rays rendered at once.
    - `measure`: `"bound"` (the worst case) or `"psnr"` (the loss measured on the rays;
      for held-out rays), as the module docstring says.

    The candidates are searched by bisection, which assumes that the measure never falls as
    the threshold grows (more cells are skipped); `log2(doublings + 1) + 1` renders. The
    bound nearly always grows; the measured loss need not (a haze removed can gain), so with
    `"psnr"` the choice is the largest candidate accepted on the bisection's path, not
    necessarily the largest acceptable one. If
    not even the smallest candidate is within tolerance, the threshold 0 is rendered and
    returned.

    **Returns:**

    `(grid with the chosen threshold, ThresholdChoice)`.
    """
    smallest = float(grid.threshold)
    if smallest <= 0:
        raise ValueError(f"the grid's threshold is the smallest candidate and must be > 0, got {smallest}")
    if tolerance_db < 0 or doublings < 0:
        raise ValueError("tolerance_db and doublings must be >= 0")
    if measure not in ("bound", "psnr"):
        raise ValueError(f'measure is "bound" or "psnr", got {measure!r}')
    target = np.asarray(target, np.float32).reshape(-1, 3)
    dense = render_rays(model, rays, chunk).rgb.reshape(-1, 3)
    trials: list[ThresholdTrial] = []

    def trial(threshold: float) -> ThresholdTrial:
        candidate = dataclasses.replace(skipping, grid=grid.with_threshold(threshold))
        rendered = render_rays(model, rays, chunk, skipping=candidate)
        rgb = rendered.rgb.reshape(-1, 3)
        result = ThresholdTrial(
            threshold,
            psnr_drop_bound(dense, rgb, target),
            rendered.counts.reduction,
            psnr_drop(dense, rgb, target),
        )
        trials.append(result)
        return result

    def within(result: ThresholdTrial) -> bool:
        return (result.bound_db if measure == "bound" else result.psnr_drop_db) <= tolerance_db

    candidates = [smallest * 2.0**k for k in range(doublings + 1)]
    low, high, best = 0, len(candidates) - 1, None
    while low <= high:
        middle = (low + high) // 2
        result = trial(candidates[middle])
        if within(result):
            best, low = result, middle + 1
        else:
            high = middle - 1
    if best is None:
        best = trial(0.0)
    choice = ThresholdChoice(
        threshold=best.threshold,
        bound_db=best.bound_db,
        reduction=best.reduction,
        within_tolerance=within(best),
        tolerance_db=tolerance_db,
        trials=tuple(trials),
        measure=measure,
        psnr_drop_db=best.psnr_drop_db,
    )
    return grid.with_threshold(best.threshold), choice
