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


def validation_ids(candidates: list[int], excluded: list[int], max_views: int) -> list[int]:
    """The validation views: those of `candidates` not in `excluded` (the protocol's training
    and test views), at most `max_views` of them evenly spaced (0: all). Empty when nothing is left.

    Settings are chosen on these views, so that the test views are scored once, for the record.
    """
    used = set(excluded)
    return subsample_test_ids([i for i in candidates if i not in used], max_views)
