"""Atomic, resumable checkpoints of a `TrainState`, with the run's config."""

import dataclasses
import json
import os
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from .._nn.rays import Box
from .._train.state import TrainState

_PREFIX = "step_"


def _checkpoint_dirs(run_dir: Path) -> list[Path]:
    root = run_dir / "checkpoints"
    if not root.is_dir():
        return []
    found = []
    for path in root.iterdir():
        if path.is_dir() and path.name.startswith(_PREFIX) and path.name[len(_PREFIX) :].isdigit():
            if (path / "state.eqx").is_file() and (path / "meta.json").is_file():
                found.append(path)
    return sorted(found, key=lambda p: int(p.name[len(_PREFIX) :]))


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or written; the message names it and what to do."""


def remove_stale_staging(run_dir: str | Path) -> list[Path]:
    """Removes the staging folders a killed or failed write left behind; returns them."""
    root = Path(run_dir) / "checkpoints"
    stale = sorted(root.glob(f".{_PREFIX}*.tmp-*")) if root.is_dir() else []
    for path in stale:
        shutil.rmtree(path, ignore_errors=True)
    return stale


def checkpoints(run_dir: str | Path) -> list[Path]:
    """The complete checkpoints in `run_dir` (a state and its description; not a write cut
    short or still staging), oldest first."""
    return _checkpoint_dirs(Path(run_dir))


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint in `run_dir`, or None."""
    found = _checkpoint_dirs(Path(run_dir))
    return found[-1] if found else None


def _storable(state: TrainState) -> TrainState:
    # Typed keys are not serialisable; their raw data is. The skipping cells are derived from
    # the grid (`training_cells`), so they are not stored.
    state = dataclasses.replace(state, cells=None)
    return eqx.tree_at(lambda s: s.key, state, jax.random.key_data(state.key))


def save_checkpoint(
    run_dir: str | Path,
    state: TrainState,
    *,
    config: dict[str, Any],
    scene_box: Box | None = None,
    keep: int = 2,
) -> Path:
    """Writes `state` as the checkpoint of step `state.step` and keeps the newest `keep`.

    `scene_box` is the box the model was built with (`init_train_state`'s `box`), recorded so
    that a resumed run reads its grid through the same box whatever scene it is handed.

    The files are written into a temporary folder that is renamed into place only when
    complete, so a crash mid-write leaves the previous checkpoint intact and no partial one.
    Its name comes from the state itself, so a checkpoint always holds as many updates as
    its name says.
    """
    step = int(state.step)
    root = Path(run_dir) / "checkpoints"
    final = root / f"{_PREFIX}{step:08d}"
    staging = root / f".{final.name}.tmp-{os.getpid()}"
    try:
        root.mkdir(parents=True, exist_ok=True)
        if staging.exists():
            shutil.rmtree(staging)
        staging.mkdir()
        eqx.tree_serialise_leaves(staging / "state.eqx", _storable(state))
        meta: dict[str, Any] = {"step": step, "config": config}
        if scene_box is not None:
            meta["scene_box"] = [[float(v) for v in corner] for corner in scene_box]
        (staging / "meta.json").write_text(json.dumps(meta, indent=2))
        for path in staging.iterdir():
            with open(path, "rb") as handle:
                os.fsync(handle.fileno())
        if final.exists():
            shutil.rmtree(final)
        os.replace(staging, final)
    except OSError as error:
        shutil.rmtree(staging, ignore_errors=True)
        reason = error.strerror or str(error)
        raise CheckpointError(
            f"could not write the checkpoint of step {step} to {root}: {reason}; the previous "
            "checkpoint is intact (free space or choose a writable train.run_dir, then resume)"
        ) from error
    for old in _checkpoint_dirs(Path(run_dir))[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def read_checkpoint_meta(path: str | Path) -> dict[str, Any]:
    """The step and config stored with a checkpoint."""
    meta = Path(path) / "meta.json"
    try:
        values = json.loads(meta.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(f"{meta} cannot be read ({error})") from None
    if not isinstance(values, dict) or "config" not in values:
        raise CheckpointError(f"{meta} is not a checkpoint's description (no config)")
    return values


def recorded_box(path: str | Path) -> Box | None:
    """The scene box the model of the checkpoint at `path` was built with; `None` for one
    written before the box was recorded (its run's own training rays give it again)."""
    meta = read_checkpoint_meta(path)
    corners = meta.get("scene_box")
    if corners is None:
        return None
    try:
        low, high = ([float(v) for v in corner] for corner in corners)
        if len(low) != 3 or len(high) != 3:
            raise ValueError
    except (TypeError, ValueError):
        raise CheckpointError(
            f"{Path(path) / 'meta.json'}: its scene_box is not two corners of three numbers: {corners!r}"
        ) from None
    return (low[0], low[1], low[2]), (high[0], high[1], high[2])


def newest_recorded_box(run_dir: str | Path) -> Box | None:
    """The scene box recorded by the newest checkpoint of `run_dir` that says one (every
    checkpoint of a run records the same box); `None` if none does."""
    for path in reversed(_checkpoint_dirs(Path(run_dir))):
        try:
            return recorded_box(path)
        except CheckpointError:
            continue
    return None


def load_checkpoint(path: str | Path, like: TrainState) -> TrainState:
    """The `TrainState` stored at `path`, read into the structure of `like`.

    `like` is the state the run starts from (`init_train_state` with the run's config); its
    values are replaced, its static parts (optimiser, schedule) kept. A file that is cut
    short, empty, or written for another model raises `CheckpointError` naming it.
    """
    file = Path(path) / "state.eqx"
    try:
        stored = eqx.tree_deserialise_leaves(file, _storable(like))
    except (OSError, EOFError, ValueError, RuntimeError, TypeError) as error:
        raise CheckpointError(f"{file} {_unreadable(file, error)}") from None
    key = jax.random.wrap_key_data(np.asarray(stored.key), impl=jax.random.key_impl(like.key))
    return eqx.tree_at(lambda s: s.key, stored, key)


def _unreadable(file: Path, error: Exception) -> str:
    """Why a state file could not be read, in words."""
    if not file.is_file():
        return "is missing"
    if file.stat().st_size == 0:
        return "is empty"
    message = str(error)
    if "changed shape" in message or "dtype" in message:
        return f"was written for another model or config ({message})"
    return "is damaged: cut short, or not a checkpoint of this package"


def load_latest_readable(
    run_dir: str | Path, like: TrainState, check: Callable[[Path, dict[str, Any]], None] | None = None
) -> tuple[TrainState, Path] | None:
    """The newest checkpoint of `run_dir` that can be read, and where it is; `None` if the run
    has none. A damaged newer one is skipped with a warning that names it. `check(path, meta)`
    may refuse a readable checkpoint by raising (that error is not skipped)."""
    for path in reversed(_checkpoint_dirs(Path(run_dir))):
        try:
            meta = read_checkpoint_meta(path)
            if check is not None:
                check(path, meta)
            return load_checkpoint(path, like), path
        except CheckpointError as error:
            warnings.warn(f"skipping a damaged checkpoint: {error}", RuntimeWarning, stacklevel=2)
    return None
