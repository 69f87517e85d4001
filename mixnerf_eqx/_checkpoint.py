"""Atomic, resumable checkpoints: model, optimiser state, step, config and RNG key."""

import json
import os
import shutil
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

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


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint in `run_dir`, or None."""
    found = _checkpoint_dirs(Path(run_dir))
    return found[-1] if found else None


def save_checkpoint(
    run_dir: str | Path,
    *,
    model: eqx.Module,
    opt_state: Any,
    step: int,
    key: jax.Array,
    config: dict[str, Any],
    keep: int = 2,
) -> Path:
    """Writes a checkpoint atomically and keeps the newest `keep` of them.

    The files are written into a temporary folder that is renamed into place only when
    complete, so a crash mid-write leaves the previous checkpoint intact and no partial one.
    """
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"{_PREFIX}{step:08d}"
    staging = root / f".{final.name}.tmp-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    state = (
        model,
        opt_state,
        jnp.asarray(step, jnp.int64 if jax.config.jax_enable_x64 else jnp.int32),
        jax.random.key_data(key),
    )
    eqx.tree_serialise_leaves(staging / "state.eqx", state)
    meta = {"step": int(step), "config": config}
    (staging / "meta.json").write_text(json.dumps(meta, indent=2))
    for path in staging.iterdir():
        with open(path, "rb") as handle:
            os.fsync(handle.fileno())
    if final.exists():
        shutil.rmtree(final)
    os.replace(staging, final)
    for old in _checkpoint_dirs(Path(run_dir))[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def read_checkpoint_meta(path: str | Path) -> dict[str, Any]:
    """The step and config stored with a checkpoint."""
    return json.loads((Path(path) / "meta.json").read_text())


def load_checkpoint(path: str | Path, *, model: eqx.Module, opt_state: Any, key: jax.Array):
    """Restores `(model, opt_state, step, key)` from `path` into the given skeletons."""
    like = (
        model,
        opt_state,
        jnp.asarray(0, jnp.int64 if jax.config.jax_enable_x64 else jnp.int32),
        jax.random.key_data(key),
    )
    model, opt_state, step, key_data = eqx.tree_deserialise_leaves(Path(path) / "state.eqx", like)
    key = jax.random.wrap_key_data(np.asarray(key_data), impl=jax.random.key_impl(key))
    return model, opt_state, int(step), key
