"""The training loop: a short driver around `TrainState` and the pure step.

`fit` resumes or starts a state, then repeats: draw a batch, take a step, and hand the step's
outcome to small pieces that each do one thing: `_RunLog` (the loss history and progress bar),
`_Guard` (stops a run whose steps keep failing), the occupancy-grid update, the periodic
evaluation and the checkpoints. The final evaluation writes the run's report.
"""

import contextlib
import dataclasses
import json
import os
import shutil
import statistics
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np

from .._config import Config, ConfigError, SettingWarning, config_to_dict, setting_warnings
from .._inference.evaluation import Evaluation, evaluate
from .._inference.rendering import Rendered
from .._nn.model import MixNeRF, check_model_names
from .._nn.rays import Box
from .._predictive.uncertainty import predict_views
from .._train.sharding import DataParallel, data_parallel_mesh
from .._train.state import (
    StepMetrics,
    TrainState,
    budget_bucket,
    draw_batch,
    init_train_state,
    make_live_counter,
    make_train_step,
    occupancy_key,
    scene_box,
    training_cells,
    training_rays,
    update_grid,
)
from .._util import json_io as strict_json
from .._util.images import colourise_depth
from .._util.interrupt import deferred_interrupts, raise_if_interrupted, redeliver_dropped_interrupts
from .._util.lock import LOCK_NAME, hold_folder
from .._util.progress import Progress
from .._util.tensorboard import TensorBoardLog, check_tensorboard
from ..data import Dataset, evenly_spaced, load_dataset
from .checkpoint import (
    CheckpointError,
    latest_checkpoint,
    load_checkpoint,
    load_latest_readable,
    newest_recorded_box,
    remove_stale_staging,
    save_checkpoint,
)
from .failure import FailedRunWarning, blank_image, failure, recent_train_psnr
from .run_folder import (
    DATASET_RECORD,
    check_dataset,
    check_resumable,
    continued_config,
    dataset_record,
    grid_for_rendering,
    make_skipping,
    render_summary,
    write_view_renders,
)


class TrainingDiverged(RuntimeError):
    """Too many consecutive steps had a non-finite loss or gradient."""


@dataclasses.dataclass
class TrainResult:
    """What `fit` returns: the final state, its test metrics and where the outputs are."""

    state: TrainState
    metrics: dict[str, Any]
    run_dir: Path
    history: list[dict[str, Any]]

    @property
    def model(self) -> MixNeRF:
        return self.state.model


def _due(done: int, every: int) -> bool:
    return every > 0 and done % every == 0


def _scalars(metrics: StepMetrics) -> dict[str, float]:
    terms = metrics.terms
    values = {"loss": float(terms.total), **{name: float(value) for name, value in terms.values.items()}}
    values.update(
        psnr=float(metrics.psnr), lr=float(metrics.learning_rate), lambda_colour=float(metrics.lambda_colour)
    )
    if terms.samples is not None:
        evaluations, coarse, fine, dropped, _, _ = (float(x) for x in np.asarray(terms.samples))
        values.update(field_evaluations=evaluations, live_samples=coarse + fine, dropped_samples=dropped)
    return values


class _Steps:
    """The jitted training steps: the dense step, and one skipping step per pair of buffer
    sizes (`budget_bucket`), each compiled once.

    Every `occupancy.train_budget_every` steps the live shares are counted on `PROBE_RAYS` rays
    of the batch as the next step would count them (`make_live_counter`; the same count whether
    the steps are dense or skip, so the buffers do not switch back and forth between two ways
    of counting), and the buffers follow them. A smaller buffer is taken only when it pays for
    itself: when the seconds it saves over the steps left (the median seconds per step of the
    last measurement windows, scaled by the field's share of the samples it drops) exceed the
    longest compilation measured in this run; until both are measured, no new program is
    compiled. A larger buffer (live samples beyond the current one, or samples a step dropped)
    is taken at once. Full buffers run the dense step, compiled once on a state without cells."""

    # Below this share of live coarse samples the grid is taken to be wrong (it would starve
    # the field of gradient): training falls back to dense steps for the rest of the run.
    MIN_LIVE_SHARE = 0.01
    # The share of a dense step's seconds that follows the field evaluations
    # (benchmarks/skipping_step.py: 0.8 to 0.95 on the CPU; the lower figure, so that a
    # switch is never predicted to save more than it does).
    FIELD_SHARE = 0.8
    # Rays of each measured batch whose live samples are counted.
    PROBE_RAYS = 128
    # Measurement windows whose median gives the seconds per step (a window that holds an
    # evaluation, a checkpoint or a compilation is an outlier the median ignores).
    WINDOWS = 5

    def __init__(self, config: Config, wrap: Callable[[Any], Any]):
        self.config, self.wrap = config, wrap
        self.steps: dict[Any, Any] = {}
        self.budget: tuple[float, float] | None = (1.0, 1.0)
        self.fallback: str | None = None
        self.compile_seconds: float | None = None
        self.windows: list[float] = []
        self._window: tuple[float, int] | None = None  # (clock, step) where the window began
        self._last: tuple[TrainState, Any] | None = None
        self._count = make_live_counter(config)

    @property
    def step_seconds(self) -> float | None:
        """The median seconds per step of the last `WINDOWS` measurement windows."""
        return statistics.median(self.windows) if self.windows else None

    def _program(self, key: Any) -> Any:
        if key == "dense":
            dense = dataclasses.replace(
                self.config, occupancy=dataclasses.replace(self.config.occupancy, train_skipping=False)
            )
            return self.wrap(make_train_step(dense, max_traces=1))
        return self.wrap(make_train_step(self.config, max_traces=1, budget=key))

    def __call__(self, state: TrainState, batch: Any) -> tuple[TrainState, StepMetrics]:
        # Dense steps until the grid has looked at every cell (`state.cells` set), while the
        # buffers are full, and after a fallback. The dense step always sees a state without
        # cells, so that it compiles once.
        skipping = state.cells is not None and self.budget is not None and self.budget != (1.0, 1.0)
        key = self.budget if skipping else "dense"
        step = self.steps.get(key)
        given = state if skipping else dataclasses.replace(state, cells=None)
        if step is None:
            step = self.steps[key] = self._program(key)
            started = time.perf_counter()
            new_state, metrics = step(given, batch)
            jax.block_until_ready(metrics.terms.total)
            self.compile_seconds = max(self.compile_seconds or 0.0, time.perf_counter() - started)
        else:
            new_state, metrics = step(given, batch)
        if state.cells is not None and self.budget is not None:
            # What the count needs of this step's inputs (not the optimiser's state).
            rays = jax.tree_util.tree_map(lambda x: x[: self.PROBE_RAYS], batch.rays)
            self._last = (dataclasses.replace(state, opt_state=None), rays)
        return (new_state if skipping else dataclasses.replace(new_state, cells=state.cells)), metrics

    def _time_window(self, done: int) -> None:
        """The seconds per step since the last measurement, kept for the median."""
        now = time.perf_counter()
        if self._window is not None and done > self._window[1]:
            per_step = (now - self._window[0]) / (done - self._window[1])
            self.windows = [*self.windows, per_step][-self.WINDOWS :]
        self._window = (now, done)

    def _pays(self, wanted: tuple[float, float], counts: tuple[float, float], done: int) -> bool:
        """Whether switching from the current buffers to `wanted` saves more seconds over the
        rest of the run than compiling it costs (a program already compiled always pays; none
        is compiled before a compilation and a step have been timed)."""
        if wanted in self.steps:
            return True
        if self.compile_seconds is None or self.step_seconds is None:
            return False
        assert self.budget is not None
        total = counts[0] + counts[1]

        def cost(budget: tuple[float, float]) -> float:
            shared = (budget[0] * counts[0] + budget[1] * counts[1]) / total
            return 1.0 - self.FIELD_SHARE + self.FIELD_SHARE * shared

        left = self.config.train.max_steps - done
        saved = left * self.step_seconds * (1.0 - cost(wanted) / cost(self.budget))
        return saved > self.compile_seconds

    def measure(self, done: int, metrics: StepMetrics) -> str | None:
        """Follows the live shares; returns a warning when it falls back to dense steps."""
        occupancy = self.config.occupancy
        if self.budget is None or not _due(done, occupancy.train_budget_every):
            return None
        self._time_window(done)
        if self._last is None:
            return None
        counts = np.asarray(self._count(*self._last))
        self._last = None
        coarse, fine, _, coarse_dense, fine_dense = (float(x) for x in counts)
        if coarse / coarse_dense < self.MIN_LIVE_SHARE:
            self.budget = None
            self.fallback = (
                f"step {done}: the occupancy grid marks {coarse / coarse_dense:.1%} of the coarse samples "
                f"occupied, which would starve the field: training goes on with dense steps. Check "
                "occupancy.box_radius (does the box hold the scene?) and occupancy.density_threshold."
            )
            return self.fallback
        current, headroom = self.budget, occupancy.train_headroom
        wanted = (
            budget_bucket(coarse / coarse_dense, headroom, current[0]),
            budget_bucket(fine / fine_dense, headroom, current[1]),
        )
        samples = metrics.terms.samples
        if samples is not None and float(np.asarray(samples)[3]) > 0:
            # The step itself dropped live samples: its buffers were too small; a rung up.
            wanted = (budget_bucket(current[0] * 2**0.5, 0.0), budget_bucket(current[1] * 2**0.5, 0.0))
        grows = wanted[0] > current[0] or wanted[1] > current[1]
        if wanted != current and (grows or self._pays(wanted, (coarse_dense, fine_dense), done)):
            self.budget = wanted
        return None


class _RunLog:
    """The loss history: `train_log.jsonl` in the run folder, a list, and the progress bar."""

    def __init__(self, run_dir: Path, start: int, total: int, progress: bool, tensorboard: bool = False):
        self.path = run_dir / "train_log.jsonl"
        self.tensorboard = TensorBoardLog(run_dir, start) if tensorboard else None
        # Entries past the checkpoint belong to a run that ended without saving them (a crash
        # or a kill): the resumed run redoes those steps, so the log keeps one entry per step.
        self.evaluated = _truncate_log(self.path, start)
        self.file = open(self.path, "a")  # noqa: SIM115 (closed by `close`)
        self.history: list[dict[str, Any]] = []
        self.progress = Progress(total, initial=start, unit="step", enabled=progress)
        self.timer, self.logged = time.perf_counter(), start

    def step(self, done: int, metrics: StepMetrics, skipped_total: int) -> None:
        entry = {"step": done, **_scalars(metrics), "skipped_steps": skipped_total}
        now = time.perf_counter()
        entry["steps_per_s"] = (done - self.logged) / max(now - self.timer, 1e-9)
        self.timer, self.logged = now, done
        self.history.append(entry)
        self._write(entry)
        if self.tensorboard is not None:
            self.tensorboard.step(entry)
        self.progress.update(
            done,
            loss=f"{entry['loss']:.4f}",
            psnr=f"{entry['psnr']:.2f}",
            it_s=f"{entry['steps_per_s']:.2f}",
            skipped=skipped_total,
        )

    def evaluation(
        self, done: int, means: dict[str, Any], images: dict[str, np.ndarray] | None = None
    ) -> None:
        shown = ", ".join(f"{k} {v:.4f}" for k, v in means.items() if v is not None)
        self.progress.write(f"step {done}: validation {shown}")
        self._write({"step": done, "eval": means, "split": "val"})
        if self.tensorboard is not None:
            self.tensorboard.evaluation(done, means, images or {})
        self.evaluated.add(done)

    def warning(self, done: int, message: str) -> None:
        self.progress.write(f"step {done}: warning: {message}")
        self._write({"step": done, "warning": message})

    def _write(self, entry: dict[str, Any]) -> None:
        # Flushed at once, so that `tail -f` follows the run and a crash loses no entry.
        self.file.write(strict_json.dumps(entry) + "\n")
        self.file.flush()

    def sync(self) -> None:
        """Forces the log to disk (with each checkpoint: a resumed run keeps its history)."""
        if not self.file.closed:
            os.fsync(self.file.fileno())
        if self.tensorboard is not None:
            self.tensorboard.flush()

    def close(self) -> None:
        self.progress.close()
        self.file.close()
        if self.tensorboard is not None:
            self.tensorboard.close()


def _truncate_log(log_path: Path, last_step: int) -> set[int]:
    """Drops the entries of `log_path` logged after step `last_step` (none if it is absent),
    and a last line cut short by a kill; returns the steps that the kept log holds a periodic
    evaluation of (one pass over the file)."""
    if not log_path.is_file():
        return set()
    lines = log_path.read_text().splitlines()
    kept, evaluated = [], set()
    for line in lines:
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        if entry.get("step", 0) <= last_step:
            kept.append(line)
            if "eval" in entry:
                evaluated.add(entry["step"])
    if len(kept) != len(lines):
        temporary = log_path.with_suffix(".jsonl.tmp")
        temporary.write_text("".join(line + "\n" for line in kept))
        temporary.replace(log_path)
    return evaluated


class _Guard:
    """Counts the steps whose update was not finite (and so not applied); raises
    `TrainingDiverged` after `limit` in a row.

    A step's flag is read once the next step is queued (`defer`), so the host does not wait
    for the device between steps; a step that logs, evaluates or checkpoints is read at once.
    """

    def __init__(self, limit: int, run_dir: Path):
        self.limit, self.run_dir = limit, run_dir
        self.total = self.streak = 0
        self.pending: tuple[int, Any] | None = None

    def defer(self, done: int, skipped: Any, *, read_now: bool) -> None:
        if self.pending is not None:
            self._read(*self.pending)
        self.pending = (done, skipped)
        if read_now:
            self._read(*self.pending)
            self.pending = None

    def _read(self, done: int, skipped: Any) -> None:
        if not bool(skipped):
            self.streak = 0
            return
        self.total += 1
        self.streak += 1
        if self.streak >= self.limit:
            last_good = latest_checkpoint(self.run_dir)
            raise TrainingDiverged(
                f"step {done}: {self.streak} consecutive steps had a non-finite loss or "
                f"gradient and were not applied; stopping. The last good checkpoint is "
                f"{last_good or 'none (no checkpoint was written yet)'}; lower the learning "
                "rate or check the data, then resume from it."
            )


def _prepare_run_dir(run_dir: Path) -> bool:
    """Creates the run folder, or says in one line why it cannot be used (before any loading).
    Returns whether the folder was created here."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"train.run_dir {run_dir} is a file, not a folder; choose another train.run_dir")
    existed = run_dir.is_dir()
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create train.run_dir {run_dir}: {error.strerror or error}") from None
    if not os.access(run_dir, os.W_OK | os.X_OK):
        raise ConfigError(f"train.run_dir {run_dir} is not writable; choose another train.run_dir")
    return not existed


# The held-out metrics need 32 pixels a side (LPIPS's network 31, SSIM an 11-pixel window);
# `data.resolution` is held to it by the config, scenes on disk here, before any training.
MIN_SCORED_SIZE = 32


def _check_scored_size(config: Config, dataset: Dataset) -> None:
    """Refuses a `data.image_downscale` that leaves held-out images too small to score,
    before training (scenes whose own images are that small are the caller's choice)."""
    factor = config.data.image_downscale
    height, width = dataset.test.images.shape[1:3]
    if factor == 1 or min(height, width) >= MIN_SCORED_SIZE:
        return
    raise ConfigError(
        f"data.image_downscale = {factor} leaves {width}x{height} held-out images; the held-out metrics "
        f"(LPIPS, SSIM) need {MIN_SCORED_SIZE} pixels a side or more: choose a smaller factor"
    )


def _remove_if_unused(run_dir: Path) -> None:
    """Removes a run folder that this process created and wrote nothing into but its lock."""
    if run_dir.is_dir() and {p.name for p in run_dir.iterdir()} <= {LOCK_NAME}:
        shutil.rmtree(run_dir, ignore_errors=True)


def _start_state(
    config: Config, dataset: Dataset, run_dir: Path, resume: bool
) -> tuple[Config, TrainState, Box]:
    """A new state, or the run folder's newest readable checkpoint if it has one; the config
    the run goes on with (`continued_config`: more steps keep the decay horizon); and the
    scene box its model spans (a resumed run's is the one it began with, whatever scene it is
    handed now)."""
    remove_stale_staging(run_dir)
    if latest_checkpoint(run_dir) is None:
        box = scene_box(dataset)
        return config, init_train_state(config, dataset, box=box), box
    if not resume:
        raise ConfigError(f"{run_dir} already holds checkpoints; resume, or choose another train.run_dir")
    chosen = config

    def same_run(path: Path, meta: dict[str, Any]) -> None:
        nonlocal chosen
        if meta["step"] > config.train.max_steps:
            raise ConfigError(
                f"{path} holds {meta['step']} steps, more than train.max_steps = {config.train.max_steps}"
            )
        chosen = continued_config(config, meta["config"])
        check_resumable(path, meta["config"], chosen)

    # A checkpoint written before boxes were recorded: its run's own training rays give it.
    box = newest_recorded_box(run_dir) or scene_box(dataset)
    found = load_latest_readable(run_dir, init_train_state(config, dataset, box=box), check=same_run)
    if found is None:
        raise CheckpointError(
            f"no checkpoint in {run_dir / 'checkpoints'} can be read; move the folder away to start again"
        )
    state, path = found
    if chosen is not config:
        print(
            f"continuing past the {chosen.optim.decay_steps} steps the run began with: the learning "
            f"rate stays at optim.lr_final = {chosen.optim.lr_final:g} (optim.decay_steps)"
        )
        # Read again into the state of the config the run goes on with: every schedule keeps the
        # horizon the run began with, the model's own among them (a coarse-to-fine reveal given
        # as a fraction of the run), not only the learning rate's.
        state = load_checkpoint(path, init_train_state(chosen, dataset, box=box))
    return chosen, training_cells(state, config.occupancy), box


def _evaluation_ids(config: Config, dataset: Dataset) -> list[int]:
    """The validation views of the periodic evaluation: `train.num_eval_views`, evenly spaced."""
    assert dataset.val is not None
    return evenly_spaced(dataset.val.num_views, min(config.train.num_eval_views, dataset.val.num_views))


def _warn_if_failed(log: "_RunLog", step: int, val_psnr: float | None, blank: Any) -> str | None:
    """Warns (and logs) when the figures say the run has failed (`failure.failure`)."""
    message = failure(step, val_psnr, recent_train_psnr(log.history), blank)
    if message is not None:
        log.warning(step, message)
        warnings.warn(message, FailedRunWarning, stacklevel=2)
    return message


def _periodic_evaluation(
    config: Config, dataset: Dataset, state: TrainState, *, with_images: bool = False
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Metrics of `train.num_eval_views` validation views, evenly spaced, without LPIPS: the
    test views are scored once, at the end. With `with_images`, also the first view's colour,
    depth, error and (with mixture heads) predictive colour spread, as RGB images."""
    assert dataset.val is not None
    ids = _evaluation_ids(config, dataset)
    skipping = None if state.grid is None else make_skipping(config.occupancy, state.grid)
    chunk = config.train.render_chunk if skipping is None else config.occupancy.chunk
    images: dict[str, np.ndarray] = {}

    def keep_first(index: int, metrics: dict[str, Any], rendered: Rendered) -> None:
        if with_images and index == 0:
            truth = dataset.val.images[ids[0]]
            images.update(_evaluation_images(rendered, truth, dataset.near, dataset.far))

    means = evaluate(
        state.model,
        dataset,
        chunk=chunk,
        view_ids=ids,
        with_lpips=False,
        skipping=skipping,
        split="val",
        on_view=keep_first,
    ).means
    if with_images and state.model.field.has_mixture_heads:
        view = dataset.val.select(ids[:1])
        maps = predict_views(state.model, view, dataset.near, dataset.far, config.train.render_chunk)
        images["colour_spread"] = _grey(maps["colour_std"][0].mean(axis=-1) / 0.5)
    return means, images


def _grey(values: np.ndarray) -> np.ndarray:
    return np.repeat(np.clip(values, 0.0, 1.0)[..., None], 3, axis=-1)


def _evaluation_images(
    rendered: Rendered, truth: np.ndarray, near: float, far: float
) -> dict[str, np.ndarray]:
    """One view's colour, depth (coloured from `near` to `far`) and error (white: 0.5 or more)."""
    return {
        "colour": rendered.rgb,
        "depth": colourise_depth(rendered.depth, near, far),
        "error": _grey(np.abs(rendered.rgb - truth).mean(axis=-1) / 0.5),
    }


def fit(
    config: Config,
    *,
    dataset: Dataset | None = None,
    resume: bool = True,
    progress: bool = True,
    write_renders: bool = True,
    log_every: int = 10,
    stop_after: int | None = None,
    on_step: Callable[[TrainState], None] | None = None,
) -> TrainResult:
    """Trains a model as `config` says, with checkpoints, evaluation and renders in its run dir.

    **Arguments:**

    - `config`: the run's configuration; `config.train.run_dir` receives every output.
    - `dataset`: the scene (default: loaded from `config.data`).
    - `resume`: continue from the run dir's latest checkpoint if there is one; it must have
      been written with the same settings (cosmetic ones such as `eval_every` aside).
      `False` refuses to start in a run dir that holds checkpoints.
    - `progress`: show a progress bar.
    - `write_renders`: write PNG renders of the test views at the end.
    - `log_every`: steps between entries of the loss history (and bar updates).
    - `stop_after`: stop (with a checkpoint) after this step, as if interrupted; for tests.
    - `on_step`: called with the state before the first step and after every step, between
      steps (a live viewer: `python -m mixnerf_eqx.train --viewer`); it may block (a pause),
      and a Ctrl-C while it runs stops the run at this safe point.

    **Returns:**

    A `TrainResult` with the final test metrics (also written to `metrics.json`).
    """
    check_model_names(config)  # a name the config cannot check, before anything is loaded or written
    for message in setting_warnings(config):
        warnings.warn(message, SettingWarning, stacklevel=2)
    # A Ctrl-C that lands in a garbage-collection callback stops the run all the same.
    redeliver_dropped_interrupts()
    if "tensorboard" in config.train.log_to:
        check_tensorboard()  # before anything is loaded, built or written
    run_dir = Path(config.train.run_dir)
    created = _prepare_run_dir(run_dir)
    # One writer per run folder: a second `fit` on it fails here, before touching it (and never
    # removes it: the folder may be the other writer's, just created).
    with hold_folder(run_dir):
        try:
            return _fit_holding(
                config, run_dir, dataset, resume, progress, write_renders, log_every, stop_after, on_step
            )
        except BaseException:
            if created:
                _remove_if_unused(run_dir)
            raise


def _fit_holding(
    config: Config,
    run_dir: Path,
    dataset: Dataset | None,
    resume: bool,
    progress: bool,
    write_renders: bool,
    log_every: int,
    stop_after: int | None,
    on_step: Callable[[TrainState], None] | None = None,
) -> TrainResult:
    """`fit`, once the run folder is this process's."""
    train = config.train
    if config.data.data_dir and not Path(config.data.data_dir).expanduser().is_absolute():
        # Stored absolute, so that `eval` from another folder reads the same files.
        absolute = str(Path(config.data.data_dir).expanduser().resolve())
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, data_dir=absolute))
    loaded_here = dataset is None
    dataset = load_dataset(config.data) if dataset is None else dataset
    if loaded_here:
        _check_scored_size(config, dataset)
    config, state, box = _start_state(config, dataset, run_dir, resume)
    config_dict = config_to_dict(config)
    (run_dir / "config.json").write_text(json.dumps(config_dict, indent=2))
    record = dataset_record(config, dataset)
    if int(state.step) > 0 and loaded_here:
        # A resumed run trains on the scene it began with (a scene handed to `fit` is the caller's choice).
        check_dataset(run_dir, config, dataset)
    _write_replacing(run_dir / DATASET_RECORD, json.dumps(record, indent=2))
    start = int(state.step)
    last_step = train.max_steps if stop_after is None else min(train.max_steps, stop_after)
    data = training_rays(dataset, config.loss)
    draw = eqx.filter_jit(draw_batch)
    take_step = _Steps(config, lambda step: step)
    mesh = data_parallel_mesh(train.data_parallel, train.batch_size)
    if mesh is not None:
        # The same step, its batch split over the devices; state and rays on every device.
        parallel = DataParallel(mesh)
        state, data = parallel.replicate(state), parallel.replicate(data)
        take_step, draw = _Steps(config, parallel.step), parallel.draw(draw_batch)
    eval_every = train.eval_every
    if eval_every and dataset.val is None:
        print(f"no periodic evaluation: {dataset.name} has no validation views ({dataset.val_source})")
        eval_every = 0
    images = "tensorboard" in train.log_to
    log = _RunLog(run_dir, start, train.max_steps, progress, tensorboard=images)
    guard = _Guard(train.max_nonfinite_steps, run_dir)
    blank = blank_image(dataset, _evaluation_ids(config, dataset)) if eval_every else None
    failed_at: str | None = None
    try:
        # Ctrl-C stops the loop only between steps or between chunks of a render, so the
        # state saved holds exactly the steps it is named after.
        with deferred_interrupts():
            if start and _due(start, eval_every) and start < train.max_steps and start not in log.evaluated:
                # The step resumed from is due an evaluation that the log lacks: a Ctrl-C during
                # it checkpointed the step without it (a kill leaves an older checkpoint, and the
                # loop redoes the step and its evaluation), or eval_every changed since.
                log.evaluation(start, *_periodic_evaluation(config, dataset, state, with_images=images))
                raise_if_interrupted()
            if on_step is not None:
                on_step(state)
                raise_if_interrupted()
            for done in range(start + 1, last_step + 1):
                state, metrics = take_step(state, draw(data, state, train.batch_size))
                fallback = take_step.measure(done, metrics)
                if fallback is not None:
                    log.warning(done, fallback)
                    warnings.warn(fallback, SettingWarning, stacklevel=2)
                evaluate_now = _due(done, eval_every) and done < train.max_steps
                checkpoint_now = _due(done, train.checkpoint_every)
                log_now = _due(done, log_every) or done == last_step
                guard.defer(done, metrics.skipped, read_now=log_now or evaluate_now or checkpoint_now)
                if log_now:
                    log.step(done, metrics, guard.total)
                if state.grid is not None and _due(done, config.occupancy.update_every):
                    state = update_grid(state, config.occupancy)
                if evaluate_now:
                    means, shown = _periodic_evaluation(config, dataset, state, with_images=images)
                    log.evaluation(done, means, shown)
                    if failed_at is None:
                        failed_at = _warn_if_failed(log, done, means.get("psnr"), blank)
                # No checkpoint inside a run of skipped steps: the last good one must stay the
                # newest, so that a diverging run can be resumed from before the trouble began.
                if checkpoint_now and not guard.streak:
                    save_checkpoint(run_dir, state, config=config_dict, scene_box=box)
                    log.sync()
                if on_step is not None:
                    on_step(state)
                raise_if_interrupted()
    except KeyboardInterrupt:
        log.close()
        path = save_checkpoint(run_dir, state, config=config_dict, scene_box=box)
        print(f"\ninterrupted: checkpoint of step {int(state.step)} written to {path}; run again to resume")
        raise
    finally:
        log.close()
    done = int(state.step)
    if done != start or latest_checkpoint(run_dir) is None:
        save_checkpoint(run_dir, state, config=config_dict, scene_box=box)
    metrics = {"step": done, "skipped_steps": guard.total}
    if done >= train.max_steps:
        with _rendering_after_training(done, run_dir):
            metrics = _final_report(config, dataset, state, run_dir, write_renders, metrics, progress)
        if take_step.fallback is not None:
            metrics["skipping_fallback"] = take_step.fallback
        metrics["unusable"] = _unusable(metrics, done - start)
        metrics["dataset"] = record
        metrics = _record_failure(metrics, dataset, log, done, failed_at, run_dir)
    return TrainResult(state=state, metrics=metrics, run_dir=run_dir, history=log.history)


@contextlib.contextmanager
def _rendering_after_training(step: int, run_dir: Path) -> Iterator[None]:
    """Ctrl-C while the test views render ends with a word on what is already safe."""
    try:
        with deferred_interrupts():
            yield
    except KeyboardInterrupt:
        print(
            f"\ninterrupted while rendering the test views; the checkpoint of step {step} is "
            f"saved: python -m mixnerf_eqx.eval {run_dir} renders and scores it"
        )
        raise


def _final_report(
    config: Config,
    dataset: Dataset,
    state: TrainState,
    run_dir: Path,
    write_renders: bool,
    metrics: dict[str, Any],
    progress: bool,
) -> dict[str, Any]:
    """Scores every validation view, renders and scores every test view, writes
    `metrics.json` (and the test views' PNGs)."""
    renders, staging = run_dir / "renders", run_dir / "renders.partial"
    # The PNGs go to a staging folder that replaces `renders/` only once every view is written:
    # an interrupted final evaluation leaves the run folder as it was.
    shutil.rmtree(staging, ignore_errors=True)
    bar = Progress(dataset.test.num_views, unit="view", enabled=progress)

    def write_view(index: int, entry: dict[str, Any], rendered: Rendered) -> None:
        bar.update(index + 1, psnr=f"{entry['psnr']:.2f}")
        if write_renders:
            truth = dataset.test.images[index]
            write_view_renders(staging, entry["view"], rendered, truth, near=dataset.near, far=dataset.far)

    grid = skipping = choice = None
    grid_started = time.perf_counter()
    if config.occupancy.renders_skip:
        # The run's own grid where training kept one; with `render_skipping` alone, a grid
        # built here from the trained model, as `eval` builds one.
        grid, choice = grid_for_rendering(
            config.occupancy,
            dataset,
            state.model,
            key=occupancy_key(state.key, int(state.step) + 1),
            grid=state.grid,
        )
        skipping = make_skipping(config.occupancy, grid)
    grid_seconds = time.perf_counter() - grid_started if skipping is not None else 0.0
    chunk = config.train.render_chunk if skipping is None else config.occupancy.chunk
    validation = None
    if dataset.val is not None:
        # Scored before the test views and written beside them: what later choices of
        # settings read (`benchmarks/`, sweeps), so that the test views choose nothing.
        validation = evaluate(state.model, dataset, chunk=chunk, skipping=skipping, split="val").means
    try:
        result: Evaluation = evaluate(
            state.model, dataset, chunk=chunk, on_view=write_view, skipping=skipping
        )
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        bar.close()
    metrics = {
        **metrics,
        "scene": dataset.name,
        "val": validation,
        "val_views": {
            "count": 0 if dataset.val is None else dataset.val.num_views,
            "source": dataset.val_source,
        },
        "test": result.means,
        "per_view": result.per_view,
        "render": {
            **render_summary(result.counts, result.seconds, len(result.per_view), grid, choice),
            "grid_seconds": grid_seconds,
        },
        "config": config_to_dict(config),
    }
    if write_renders:
        staging.mkdir(exist_ok=True)
        shutil.rmtree(renders, ignore_errors=True)
        staging.replace(renders)
    _write_replacing(run_dir / "metrics.json", strict_json.dumps(metrics, indent=2))
    return metrics


# A run whose steps were skipped (non-finite loss or gradients) beyond this share of the steps
# it trained is not a result, whatever its metrics say.
MAX_SKIPPED_SHARE = 0.05


def _unusable(metrics: dict[str, Any], trained: int) -> str | None:
    """Why a finished run's results cannot be used (`None`: they can): a test metric that is
    not finite, or too many skipped steps. The `train` command exits with status 1 on it."""
    bad = [name for name, value in metrics["test"].items() if value is not None and not np.isfinite(value)]
    if bad:
        return (
            f"the test {', '.join(bad)} {'is' if len(bad) == 1 else 'are'} not finite: the model diverged "
            "(check the cameras, the scene bounds and the learning rate)"
        )
    skipped = metrics.get("skipped_steps", 0)
    if trained > 0 and skipped > MAX_SKIPPED_SHARE * trained:
        return (
            f"{skipped} of the {trained} steps trained were skipped for a non-finite loss or gradient "
            f"(more than {MAX_SKIPPED_SHARE:.0%}): check the cameras, the scene bounds and the learning rate"
        )
    return None


def _record_failure(
    metrics: dict[str, Any], dataset: Dataset, log: _RunLog, step: int, during: str | None, run_dir: Path
) -> dict[str, Any]:
    """Adds `failure` to `metrics.json`: the check on every validation view at the end (or the
    warning given during training), `None` when neither found one."""
    found = during
    if dataset.val is not None and metrics.get("val"):
        blank = blank_image(dataset, list(range(dataset.val.num_views)))
        at_end = failure(step, metrics["val"].get("psnr"), recent_train_psnr(log.history), blank)
        if at_end is not None:
            if during is None:
                warnings.warn(at_end, FailedRunWarning, stacklevel=2)
            found = at_end
    metrics = {**metrics, "failure": found}
    _write_replacing(run_dir / "metrics.json", strict_json.dumps(metrics, indent=2))
    return metrics


def _write_replacing(path: Path, text: str) -> None:
    """Writes `path` under a staging name and renames it into place: a reader sees the old
    file or the new one, never half of one."""
    staging = path.with_name(path.name + ".partial")
    staging.write_text(text)
    os.replace(staging, path)
