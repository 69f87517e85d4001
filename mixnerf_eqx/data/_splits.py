"""Choosing views: evenly spaced subsets, every-n-th holdout splits and validation views."""

from pathlib import Path

import numpy as np

from ._errors import DatasetError


def evenly_spaced(count: int, num: int) -> list[int]:
    """`num` of the positions `0 .. count-1`, evenly spread: `round(linspace(0, count-1, num))`.

    Python's `round` (ties to even), as in RegNeRF's LLFF split: it matters, for example for
    the 3-view split of LLFF's horns. With `num <= count` the positions are distinct.
    """
    return [round(float(x)) for x in np.linspace(0, count - 1, num)]


def holdout_split(count: int, every: int, num_train_views: int, source: Path) -> tuple[list[int], list[int]]:
    """The LLFF protocol's split of `count` views: every `every`-th view (`i % every == 0`) is
    held out for testing, and `num_train_views` of the others, evenly spaced, train.

    **Arguments:**

    - `count`: the number of views in the scene.
    - `every`: the holdout period (8 for LLFF).
    - `num_train_views`: the number of training views.
    - `source`: the file or folder the views come from, named in errors.

    **Returns:**

    The training ids and the test ids, as indices into the scene's views.
    """
    test = [i for i in range(count) if i % every == 0]
    remaining = [i for i in range(count) if i % every != 0]
    if num_train_views > len(remaining):
        raise DatasetError(
            f"{source}: {num_train_views} training views asked for, but only {len(remaining)} of its "
            f"{count} views are left after holding out every {every}th for testing. Ask for at most "
            f"{len(remaining)} (data.num_train_views)."
        )
    return [remaining[i] for i in evenly_spaced(len(remaining), num_train_views)], test


def subsample_test_ids(ids: list[int], max_views: int) -> list[int]:
    """At most `max_views` of `ids`, evenly spaced (all of them when `max_views` is 0)."""
    if max_views <= 0 or max_views >= len(ids):
        return list(ids)
    return [ids[i] for i in evenly_spaced(len(ids), max_views)]


# A validation camera must lie at least this fraction of the test cameras' typical distance
# from the training cameras (the median over test cameras of the distance to the nearest
# training camera) away from every test camera.
MIN_TEST_GAP = 0.5


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of `a`, the distance to the nearest point of `b`."""
    return np.linalg.norm(a[:, None] - b[None], axis=-1).min(axis=1)


def test_gap_scale(train_centres: np.ndarray, test_centres: np.ndarray) -> float:
    """The test cameras' typical distance from the training cameras: the median over test
    cameras of the distance from its centre to the nearest training camera's."""
    return float(np.median(_nearest(np.asarray(test_centres, np.float64), np.asarray(train_centres, np.float64))))


def near_test(candidate_centres: np.ndarray, train_centres: np.ndarray, test_centres: np.ndarray) -> np.ndarray:
    """Which candidates are near-copies of a test view: their camera centre lies closer to some
    test camera's than `MIN_TEST_GAP` times `test_gap_scale`. Scale-free, so it serves
    forward-facing captures and orbits alike."""
    if len(candidate_centres) == 0:
        return np.zeros(0, bool)
    bound = MIN_TEST_GAP * test_gap_scale(train_centres, test_centres)
    return _nearest(np.asarray(candidate_centres, np.float64), np.asarray(test_centres, np.float64)) < bound


def validation_ids(
    candidates: list[int], excluded: list[int], max_views: int, *, centres: np.ndarray, train_ids: list[int], test_ids: list[int]
) -> tuple[list[int], int]:
    """The validation views: those of `candidates` that are neither in `excluded` (the
    protocol's training and test views) nor near-copies of a test view (`near_test`), at most
    `max_views` of them evenly spaced (0: all). Empty when nothing is left.

    `centres` holds every view's camera centre, indexed by id; `train_ids` and `test_ids` are
    the views trained on and scored. Returns the ids and how many views were left out for lying
    near a test view.

    Settings are chosen on these views, so that the test views are scored once, for the record.
    """
    used = set(excluded)
    free = [i for i in candidates if i not in used]
    centres = np.asarray(centres, np.float64)
    near = near_test(centres[free], centres[train_ids], centres[test_ids]) if free else np.zeros(0, bool)
    kept = [i for i, close in zip(free, near, strict=True) if not close]
    return subsample_test_ids(kept, max_views), len(free) - len(kept)


def describe_validation(source: str, none_left: str, val_ids: list[int], left_out: int) -> str:
    """`val_source` for a split: where its views come from (`source`), or why there are none
    (`none_left` when every view is a training or test view), and how many were left out for
    lying near a test view."""
    if not val_ids:
        return f"the {left_out} views left over all lie near a test view" if left_out else none_left
    return f"{source}; {left_out} left out for lying near a test view" if left_out else source
