"""Telling a failed run from a slow one, from the validation views while it trains.

A few-shot run can fail outright: it fits its training views (training PSNR in the 30s) with
geometry that no other view sees, such as floaters that fill the space in front of a white
background, and scores its held-out views no better than a blank image would. Such a run does
not recover (`benchmarks/README.md`, "The verdict per scene"). The check compares each
evaluation's validation PSNR with the best blank image's on the same views (the background
colour on white-background scenes, or the mean colour of the training pixels) and with the
training PSNR of the steps before it:

- failed: validation PSNR less than `MARGIN_DB` above the blank image's, while the training
  PSNR is at least `FIT_GAP_DB` above the validation PSNR (so a run that has not yet fitted
  anything, early in training, is not called failed).

The check names the step and both figures; `fit` warns with it and records it in
`train_log.jsonl` and `metrics.json`.
"""

from dataclasses import dataclass

import numpy as np

from ..data import Dataset

__all__ = ["FIT_GAP_DB", "MARGIN_DB", "Blank", "FailedRunWarning", "blank_image", "failure", "recent_train_psnr"]

MARGIN_DB = 1.0
FIT_GAP_DB = 6.0


class FailedRunWarning(UserWarning):
    """A run whose validation views score no better than a blank image while it fits its
    training views (see `failure`)."""


def recent_train_psnr(history: list[dict], count: int = 5) -> float | None:
    """The mean training-batch PSNR of the last `count` logged steps (`None` before any)."""
    values = [entry["psnr"] for entry in history[-count:] if "psnr" in entry]
    return float(np.mean(values)) if values else None


@dataclass(frozen=True)
class Blank:
    """The blank image that scores best on some validation views."""

    psnr: float  # mean over the views of each view's PSNR
    what: str  # "the white background" or "the mean training colour"


def _mean_view_psnr(images: np.ndarray, colour: np.ndarray) -> float:
    errors = np.mean((np.asarray(images, np.float64) - colour) ** 2, axis=(1, 2, 3))
    return float(np.mean(-10.0 * np.log10(np.maximum(errors, 1e-10))))


def blank_image(dataset: Dataset, view_ids: list[int]) -> Blank:
    """The best of the blank images on the validation views `view_ids`, scored as `evaluate`
    scores them (the mean of the views' PSNRs)."""
    if dataset.val is None:
        raise ValueError(f"{dataset.name} has no validation views")
    images = np.asarray(dataset.val.images)[view_ids]
    mean = np.asarray(dataset.train.images, np.float64).reshape(-1, 3).mean(axis=0)
    candidates = [Blank(_mean_view_psnr(images, mean), "the mean training colour")]
    if dataset.white_background:
        candidates.append(Blank(_mean_view_psnr(images, np.ones(3)), "the white background"))
    return max(candidates, key=lambda blank: blank.psnr)


def failure(step: int, val_psnr: float | None, train_psnr: float | None, blank: Blank) -> str | None:
    """A one-line description of the failure that these figures show, or `None`."""
    if val_psnr is None or train_psnr is None or not np.isfinite(val_psnr) or not np.isfinite(train_psnr):
        return None
    if val_psnr >= blank.psnr + MARGIN_DB or train_psnr < val_psnr + FIT_GAP_DB:
        return None
    return (
        f"the run looks failed at step {step}: validation PSNR {val_psnr:.2f} dB is within "
        f"{MARGIN_DB:g} dB of a blank image's ({blank.what}: {blank.psnr:.2f} dB) while the "
        f"training views are fitted to {train_psnr:.2f} dB, so the geometry fits only the "
        "training views (floaters in front of the background, typically). Such runs do not "
        "recover: try another train.seed, or see benchmarks/README.md, 'The verdict per scene'."
    )
