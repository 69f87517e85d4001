"""A run folder: restoring a run's state, and rendering a trained model as the run says.

`restore_run` is how every client outside the training loop (the `eval` command, notebooks,
benchmarks) gets a trained model: it reads the run's config, loads its dataset, builds the
starting state with `init_train_state` and reads the checkpoint into it.
"""

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._config import Config, ConfigError, OccupancyConfig, config_from_dict, config_names, config_to_dict
from .._custom_types import PRNGKey
from .._inference.occupancy import OccupancyGrid, refresh_occupancy
from .._inference.rendering import Rendered
from .._inference.skipping import RenderCounts, Skipping
from .._inference.threshold import ThresholdChoice, choose_threshold, threshold_rays
from .._nn.model import MixNeRF
from .._train.state import TrainState, init_train_state, make_occupancy_grid
from .._util.images import colourise_depth, save_png
from ..data import Dataset, data_root, load_dataset
from .checkpoint import (
    CheckpointError,
    latest_checkpoint,
    load_checkpoint,
    load_latest_readable,
    newest_recorded_box,
    recorded_box,
)

_refresh_occupancy = jax.jit(refresh_occupancy)


def make_skipping(occupancy: OccupancyConfig, grid: OccupancyGrid | None) -> Skipping:
    """The rendering options of `occupancy` with `grid`."""
    return Skipping(
        grid=grid,
        stop_transmittance=occupancy.stop_transmittance,
        segments=occupancy.segments,
        chunk=occupancy.render_chunk_points or None,
    )


def grid_for_rendering(
    occupancy: OccupancyConfig,
    dataset: Dataset,
    model: MixNeRF,
    *,
    key: PRNGKey,
    grid: OccupancyGrid | None = None,
) -> tuple[OccupancyGrid, ThresholdChoice | None]:
    """`model`'s density evaluated in every cell of `grid` (default: a new grid for `dataset`),
    with its threshold chosen when `occupancy.choose_threshold` is on, on pixels of the views
    `occupancy.threshold_views` names (the training views where `"val"` is asked for and the
    scene has no validation views; the choice records which).

    **Returns:**

    `(grid, ThresholdChoice)`, the choice `None` when no threshold is chosen.
    """
    refresh_key, threshold_key = jax.random.split(key)
    grid = make_occupancy_grid(occupancy, dataset) if grid is None else grid
    grid = _refresh_occupancy(grid, model.field, key=refresh_key)
    if not occupancy.choose_threshold:
        return grid, None
    views = "val" if occupancy.threshold_views == "val" and dataset.val is not None else "train"
    rays, colours = threshold_rays(dataset, occupancy.threshold_rays, key=threshold_key, split=views)
    grid, choice = choose_threshold(
        model,
        grid,
        make_skipping(occupancy, grid),
        rays,
        colours,
        tolerance_db=occupancy.threshold_tolerance_db,
        doublings=occupancy.threshold_doublings,
        chunk=min(occupancy.chunk, occupancy.threshold_rays),
        # The loss measured is for held-out pixels; on training pixels, fitted far more
        # closely than any other view, only the bound says what other views may lose.
        measure=occupancy.threshold_measure if views == "val" else "bound",
    )
    return grid, dataclasses.replace(choice, views=views)


def render_summary(
    counts: RenderCounts,
    seconds: float,
    num_views: int,
    grid: OccupancyGrid | None,
    choice: ThresholdChoice | None = None,
) -> dict[str, Any]:
    """Per-frame render cost: field evaluations made and needed, and seconds (scoring included),
    with the grid's threshold and, if it was chosen, how."""
    frames = max(num_views, 1)
    return {
        "skipping": grid is not None,
        "density_threshold": None if grid is None else float(grid.threshold),
        "threshold_choice": None if choice is None else dataclasses.asdict(choice),
        "occupied_fraction": None if grid is None else float(grid.occupied_fraction()),
        "dense_evaluations_per_frame": counts.dense_evaluations / frames,
        "field_evaluations_per_frame": counts.padded_evaluations / frames,
        "needed_evaluations_per_frame": counts.field_evaluations / frames,
        "evaluation_reduction": counts.reduction,
        "seconds_per_frame": seconds / frames,
    }


def write_view_renders(
    folder: Path, view_id: int, rendered: Rendered, truth: np.ndarray, *, near: float, far: float
) -> None:
    """Writes one view's colour, depth (coloured between `near` and `far`) and true PNGs."""
    save_png(folder / f"test_{view_id:03d}_rgb.png", rendered.rgb)
    save_png(folder / f"test_{view_id:03d}_depth.png", colourise_depth(rendered.depth, near, far))
    save_png(folder / f"test_{view_id:03d}_gt.png", truth)


@dataclasses.dataclass(frozen=True)
class Run:
    """A trained run, restored: its config, scene, state and the checkpoint read."""

    config: Config
    dataset: Dataset
    state: TrainState
    checkpoint: Path

    @property
    def model(self) -> MixNeRF:
        return self.state.model

    @property
    def step(self) -> int:
        return int(self.state.step)


def read_run_config(run_dir: str | Path) -> Config:
    """The config a run was trained with (its `config.json`)."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise ConfigError(f"{run_dir} is not a training run: it has no config.json. Pass a run folder.")
    try:
        values = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ConfigError(f"{path}: not valid JSON ({error})") from None
    return config_from_dict(values, str(path), written_by_a_run=True)


def restore_run(
    run_dir: str | Path,
    *,
    checkpoint: str | Path | None = None,
    data_dir: str | None = None,
    dataset: Dataset | None = None,
) -> Run:
    """A training run's config, dataset and state from its folder.

    **Arguments:**

    - `run_dir`: the run's folder (holds `config.json` and `checkpoints/`).
    - `checkpoint`: the checkpoint folder (default: the latest).
    - `data_dir`: the dataset root, replacing the run's.
    - `dataset`: the scene, if already loaded (default: loaded as the run's config says).
    """
    run_dir = Path(run_dir)
    config = read_run_config(run_dir)
    if checkpoint is not None and not (Path(checkpoint) / "state.eqx").is_file():
        raise ConfigError(f"{checkpoint} is not a checkpoint folder (no state.eqx).")
    if checkpoint is None and latest_checkpoint(run_dir) is None:
        raise ConfigError(f"{run_dir} holds no checkpoint yet; train first (python -m mixnerf_eqx.train).")
    if data_dir is not None:
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, data_dir=data_dir))
    dataset = load_dataset(config.data) if dataset is None else dataset
    check_dataset(run_dir, config, dataset)
    # The box the run's model was built with, as its checkpoints record it.
    box = recorded_box(checkpoint) if checkpoint is not None else newest_recorded_box(run_dir)
    like = init_train_state(config, dataset, box=box)
    if checkpoint is not None:
        return Run(config, dataset, load_checkpoint(checkpoint, like), Path(checkpoint))
    found = load_latest_readable(run_dir, like)
    if found is None:
        raise CheckpointError(f"no checkpoint in {run_dir / 'checkpoints'} can be read")
    return Run(config=config, dataset=dataset, state=found[0], checkpoint=found[1])


# Settings that do not change the trajectory: a run may resume with them changed. Where the
# files are is not which files they are; the occupancy grid shapes only what is rendered.
_COSMETIC = {
    "train": (
        "eval_every",
        "num_eval_views",
        "checkpoint_every",
        "render_chunk",
        "run_dir",
        "max_nonfinite_steps",
        "log_to",
    ),
    # Validation views are only scored: they change no step.
    "data": ("data_dir", "dtu_mask_dir", "num_val_views", "max_val_views"),
    # The same values and gradients either way: a run may move between a CPU and a GPU.
    "grid": ("lookup",),
}


def _comparable(config: dict[str, Any]) -> dict[str, Any]:
    described = ("name", "reproduces", "chosen_on", "occupancy")
    kept = {key: value for key, value in config.items() if key not in described}
    for section, keys in _COSMETIC.items():
        kept[section] = {k: v for k, v in config.get(section, {}).items() if k not in keys}
    # A run may be continued to more steps: what the trajectory depends on is the horizon of
    # the learning-rate decay, not where the run stops.
    max_steps = kept["train"].pop("max_steps")
    kept["optim"] = {**kept["optim"], "decay_steps": kept["optim"]["decay_steps"] or max_steps}
    return kept


def continued_config(config: Config, stored: dict[str, Any]) -> Config:
    """`config` for continuing the run whose checkpoint holds `stored`: a run given more steps
    than it was started with keeps its learning-rate decay horizon (`optim.decay_steps`), so
    the learning rate stays at `optim.lr_final` for the added steps."""
    stored_train, stored_optim = stored.get("train", {}), stored.get("optim", {})
    horizon = stored_optim.get("decay_steps") or stored_train.get("max_steps")
    if config.optim.decay_steps or horizon is None or config.train.max_steps <= horizon:
        return config
    return dataclasses.replace(config, optim=dataclasses.replace(config.optim, decay_steps=horizon))


def _differences(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    changed = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            changed += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            changed.append(f"{prefix}{key}: {a!r} -> {b!r}")
    return changed


_SHOWN_CHANGES = 6  # differing settings named in the message; the rest are counted


def check_resumable(
    checkpoint: Path,
    stored: dict[str, Any],
    config: Config,
    remedy: str = "choose another train.run_dir to start a new run",
) -> None:
    """Raises `ConfigError` unless `config` may continue the run `stored` was written by; the
    message ends with `remedy`."""
    # Read through the schema, so that keys older versions wrote compare as they are read now.
    stored = config_to_dict(config_from_dict(stored, str(checkpoint / "meta.json"), written_by_a_run=True))
    changed = _differences(_comparable(stored), _comparable(config_to_dict(config)))
    began = stored.get("train", {}).get("max_steps")
    if (
        len(changed) == 1
        and changed[0].startswith("optim.decay_steps:")
        and not stored.get("optim", {}).get("decay_steps")
        and not config.optim.decay_steps
        and began is not None
        and config.train.max_steps < began
    ):
        # Only the horizon differs, because train.max_steps is shorter than the run's.
        raise ConfigError(
            f"{checkpoint}: the run began with train.max_steps = {began}, and its learning rate decays over "
            f"those steps; train.max_steps = {config.train.max_steps} is shorter. Give train.max_steps >= "
            f"{began}, or add optim.decay_steps={began} to stop at {config.train.max_steps} on the same "
            f"schedule, or {remedy}"
        )
    if changed:
        shown = ", ".join(changed[:_SHOWN_CHANGES])
        if len(changed) > _SHOWN_CHANGES:
            shown += f", and {len(changed) - _SHOWN_CHANGES} more"
        hint = ""
        name = stored.get("name")
        if name and name != config.name:
            # Many settings differ at once when the run is resumed without its config.
            packaged = name in config_names()
            hint = (
                f"; the run was made with the config named {name!r}"
                + (f" (--config {name})" if packaged else "")
                + f", its settings in {checkpoint.parent.parent / 'config.json'}: resume with it, or"
            )
        raise ConfigError(f"{checkpoint} was written with different settings ({shown}){hint}; {remedy}")


# --- What a run was trained against ------------------------------------------------------------

DATASET_RECORD = "dataset.json"


def dataset_fingerprint(dataset: Dataset) -> str:
    """A content hash of a loaded scene: its name, bounds and the training and test views'
    images and cameras (sha256 over the float32 bytes), so that another folder holding other
    files is told apart. The validation views are left out: how many are kept is a setting a
    run may change (`data.max_val_views`)."""
    digest = hashlib.sha256()
    digest.update(f"{dataset.name} {dataset.near!r} {dataset.far!r}".encode())
    for split in (dataset.train, dataset.test):
        if split is None:
            digest.update(b"none")
            continue
        for array in (split.images, split.camtoworlds):
            digest.update(np.ascontiguousarray(np.asarray(array, np.float32)).tobytes())
        digest.update(repr(split.ids).encode())
    return digest.hexdigest()[:16]


def dataset_record(config: Config, dataset: Dataset) -> dict:
    """What `dataset.json` holds: the absolute dataset root (`None` for the built-in scene),
    the scene and its fingerprint."""
    root = None
    if config.data.dataset != "builtin":
        try:
            root = str(data_root(config.data).resolve())
        except ValueError:  # a scene handed to `fit` directly, from no configured root
            root = None
    return {"root": root, "scene": dataset.name, "fingerprint": dataset_fingerprint(dataset)}


def check_dataset(run_dir: Path, config: Config, dataset: Dataset) -> None:
    """Raises `ConfigError` when the scene loaded for a run is not the one it trained on
    (a run folder written before the record passes)."""
    path = run_dir / DATASET_RECORD
    if not path.is_file():
        return
    recorded = json.loads(path.read_text())
    found = dataset_record(config, dataset)
    if found["fingerprint"] != recorded.get("fingerprint"):
        where = f" from {found['root']}" if found["root"] else ""
        hint = f": pass --data-dir {recorded['root']}" if recorded.get("root") else ""
        raise ConfigError(
            f"{run_dir} was trained on {recorded.get('scene')} from {recorded.get('root') or 'the built-in scene'} "
            f"(fingerprint {recorded.get('fingerprint')}), but the scene loaded now{where} holds other data "
            f"(fingerprint {found['fingerprint']}){hint}"
        )
