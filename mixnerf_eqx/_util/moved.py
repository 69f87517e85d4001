"""Names that left the top level of `mixnerf_eqx`.

Until this release the package re-exported about 130 names flat; they now live in namespaces
(`mx.nn`, `mx.training`, ...) and the top level keeps a few (`__init__.pyi`). An old flat name
still works for this release, with a `DeprecationWarning` that names its new place. Names that
left the top level in an earlier release are errors that name their new place.
"""

import importlib
from typing import Any

# Every public name of these namespaces was at the top level in the previous release; of
# `mx.runs`, two were.
NAMESPACES = ("nn", "training", "inference", "uncertainty", "config", "runtime")
FROM_RUNS = ("CheckpointError", "FolderBusyError")
# Left the top level earlier: an error naming the new place.
GONE = {
    **{
        name: f"mixnerf_eqx.runs.{name}"
        for name in (
            "Run",
            "restore_run",
            "grid_for_rendering",
            "make_skipping",
            "render_summary",
            "write_view_renders",
            "hold_folder",
            "save_checkpoint",
            "load_checkpoint",
            "latest_checkpoint",
            "read_checkpoint_meta",
        )
    },
    "calibrate_threshold": "mixnerf_eqx.inference.choose_threshold",
    "calibration_rays": "mixnerf_eqx.inference.threshold_rays",
}


def new_place(name: str) -> str | None:
    """`mixnerf_eqx.<namespace>.<name>` for a name of the previous release's top level."""
    if name in FROM_RUNS:
        return f"mixnerf_eqx.runs.{name}"
    if name.startswith("_"):
        return None
    for namespace in NAMESPACES:
        if name in vars(importlib.import_module(f"mixnerf_eqx.{namespace}")):
            return f"mixnerf_eqx.{namespace}.{name}"
    return None


def moved_name(name: str) -> tuple[str, Any]:
    """The new place of an old top-level `name` and the object it stands for (the package's
    `__getattr__` warns); `AttributeError` for a name that left earlier or is not the package's."""
    if name in GONE:
        raise AttributeError(f"mixnerf_eqx.{name} has moved: use {GONE[name]}")
    place = new_place(name)
    if place is None:
        raise AttributeError(f"module 'mixnerf_eqx' has no attribute {name!r}")
    namespace, _, attribute = place.rpartition(".")
    return place, getattr(importlib.import_module(namespace), attribute)
