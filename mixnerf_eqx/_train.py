"""Training: the optimiser, the jitted step, image rendering and the training loop."""

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import optax
from jaxtyping import Array, Bool, Float, Int
from tqdm.auto import tqdm

from ._calibrate import ThresholdChoice, calibrate_threshold, calibration_rays
from ._checkpoint import latest_checkpoint, load_checkpoint, read_checkpoint_meta, save_checkpoint
from ._config import Config, ConfigError, build_model, config_to_dict, init_key
from ._custom_types import PRNGKey
from ._evaluate import evaluate, render_rays, render_views  # noqa: F401 (render_* re-exported)
from ._images import colourise_depth, save_png
from ._loss import LossTerms, loss_fn
from ._model import MixNeRF
from ._occupancy import OccupancyGrid, empty_grid, frustum_box, refresh_occupancy, update_occupancy
from ._rays import RayBundle
from ._schedule import anneal_sample_space, learning_rate_schedule, linear_ramp
from ._skipping import RenderStats, Skipping
from .data import Dataset, load_dataset, rays_for_views


def make_optimizer(config: Config) -> optax.GradientTransformation:
    """Element-wise clip, global-norm clip, then Adam on the log-linear warm-up schedule.

    Steps count from 1, as in the released code: Adam's `count` is the number of updates
    already applied, so update `count` uses the learning rate of step `count + 1`.
    """
    optim = config.optim
    by_step = learning_rate_schedule(
        optim.lr_init, optim.lr_final, config.train.max_steps, optim.warmup_steps
    )

    def schedule(count: Int[Array, ""]) -> Float[Array, ""]:
        return by_step(count + 1)

    parts = []
    if optim.grad_max_value > 0:
        parts.append(optax.clip(optim.grad_max_value))
    if optim.grad_max_norm > 0:
        parts.append(optax.clip_by_global_norm(optim.grad_max_norm))
    parts.append(optax.adam(schedule))
    return optax.chain(*parts)


class TrainingRays(eqx.Module):
    """Every training pixel's ray and colour, on the device, grouped by image."""

    rays: RayBundle
    rgb: Float[Array, "num_images num_pixels 3"]


def training_rays(dataset: Dataset) -> TrainingRays:
    """Builds the device-resident ray table of the training views."""
    views = dataset.train
    rays = rays_for_views(views, dataset.near, dataset.far)
    num_pixels = views.height * views.width
    return TrainingRays(
        rays=rays.reshape(views.num_views, num_pixels),
        rgb=jnp.asarray(views.images.reshape(views.num_views, num_pixels, 3), jnp.float32),
    )


class StepMetrics(eqx.Module):
    """What one training step reports."""

    terms: LossTerms
    psnr: Float[Array, ""]
    learning_rate: Float[Array, ""]
    lambda_colour: Float[Array, ""]
    skipped: Bool[Array, ""]


class TrainingDiverged(RuntimeError):
    """Too many consecutive steps had a non-finite loss or gradient."""


def _all_finite(tree) -> Bool[Array, ""]:
    leaves = [
        jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    ]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


def draw_batch(
    data: TrainingRays, batch_size: int, *, key: PRNGKey
) -> tuple[RayBundle, Float[Array, "batch 3"]]:
    """`batch_size` random pixels (with replacement) of one random training image."""
    image_key, pixel_key = jax.random.split(key)
    num_images, num_pixels = data.rgb.shape[:2]
    image = jax.random.randint(image_key, (), 0, num_images)
    pixels = jax.random.randint(pixel_key, (batch_size,), 0, num_pixels)
    rays = jax.tree_util.tree_map(lambda x: x[image][pixels], data.rays)
    return rays, data.rgb[image][pixels]


def make_train_step(
    config: Config, optimizer: optax.GradientTransformation, *, max_traces: int | None = None
) -> Callable:
    """The jitted training step `(model, opt_state, data, step, key) -> (model, opt_state, metrics)`.

    Everything static (the config, the optimiser) is closed over, so the step traces once;
    `step` is a traced integer, the number of updates already applied (the schedules are
    evaluated at `step + 1`, as steps count from 1), and `key` the run's root key, folded with
    `step`. With
    `max_traces`, tracing more often than that raises (a guard against recompiles).
    """
    weights = config.loss.weights()
    loss_cfg, train_cfg, optim_cfg = config.loss, config.train, config.optim
    schedule = learning_rate_schedule(
        optim_cfg.lr_init, optim_cfg.lr_final, train_cfg.max_steps, optim_cfg.warmup_steps
    )

    def train_step(
        model: MixNeRF, opt_state: Any, data: TrainingRays, step: Int[Array, ""], key: PRNGKey
    ) -> tuple[MixNeRF, Any, StepMetrics]:
        batch_key, render_key = jax.random.split(jax.random.fold_in(key, step))
        rays, target = draw_batch(data, train_cfg.batch_size, key=batch_key)
        # Schedules count steps from 1 (the released code): `step` updates are done, this is
        # update `step + 1`.
        step_number = step + 1
        rays = anneal_sample_space(
            rays, step_number, train_cfg.anneal_steps, train_cfg.anneal_start, train_cfg.anneal_mid
        )
        lambda_colour = linear_ramp(
            step_number,
            loss_cfg.lambda_colour_start,
            loss_cfg.lambda_colour_end,
            loss_cfg.lambda_colour_steps,
        )
        (_, terms), grads = eqx.filter_value_and_grad(loss_fn, has_aux=True)(
            model, rays, target, lambda_colour, weights, key=render_key
        )
        updates, new_opt_state = optimizer.update(grads, opt_state, eqx.filter(model, eqx.is_array))
        new_model = eqx.apply_updates(model, updates)
        # A step whose loss or gradients are not finite is not applied: the model and the
        # optimiser state (moments and step count) stay exactly as they were.
        finite = jnp.isfinite(terms.total) & _all_finite(grads)
        model, opt_state = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finite, new, old) if eqx.is_array(new) else new,
            (new_model, new_opt_state),
            (model, opt_state),
        )
        metrics = StepMetrics(
            terms=terms,
            psnr=-10.0 * jnp.log10(terms.mse_fine),
            learning_rate=schedule(step_number),
            lambda_colour=lambda_colour,
            skipped=~finite,
        )
        return model, opt_state, metrics

    if max_traces is not None:
        train_step = eqx.debug.assert_max_traces(train_step, max_traces=max_traces)
    return eqx.filter_jit(train_step)


def make_occupancy_grid(config: Config, dataset: Dataset) -> OccupancyGrid:
    """An unevaluated grid for `dataset` as `config.occupancy` says.

    With `occupancy.box_radius > 0` the grid spans `[-r, r]^3` and the scene is taken to lie
    inside it; otherwise it spans the box of the training rays between near and far (in NDC
    for LLFF scenes) and points outside it count as occupied.
    """
    occupancy = config.occupancy
    if occupancy.box_radius > 0:
        radius = occupancy.box_radius
        box_min, box_max, outside_occupied = (-radius,) * 3, (radius,) * 3, False
    else:
        box_min, box_max = frustum_box(rays_for_views(dataset.train, dataset.near, dataset.far))
        outside_occupied = True
    return empty_grid(
        box_min,
        box_max,
        resolution=occupancy.resolution,
        threshold=occupancy.density_threshold,
        dilation=occupancy.dilation,
        outside_occupied=outside_occupied,
    )


def make_skipping(config: Config, grid: OccupancyGrid | None) -> Skipping:
    """The rendering options of `config.occupancy` with `grid`."""
    occupancy = config.occupancy
    return Skipping(grid=grid, stop_transmittance=occupancy.stop_transmittance, segments=occupancy.segments)


_update_occupancy = eqx.filter_jit(update_occupancy)
_refresh_occupancy = eqx.filter_jit(refresh_occupancy)


def calibrate_grid(
    config: Config, dataset: Dataset, model: MixNeRF, grid: OccupancyGrid, *, key: PRNGKey
) -> tuple[OccupancyGrid, ThresholdChoice | None]:
    """`grid` with the threshold `calibrate_threshold` chooses on `config.occupancy.calibrate_rays`
    training pixels, or unchanged (and `None`) when `config.occupancy.calibrate` is off."""
    occupancy = config.occupancy
    if not occupancy.calibrate:
        return grid, None
    rays, colours = calibration_rays(dataset, occupancy.calibrate_rays, key=key)
    return calibrate_threshold(
        model,
        grid,
        make_skipping(config, grid),
        rays,
        colours,
        tolerance_db=occupancy.calibrate_tolerance_db,
        doublings=occupancy.calibrate_doublings,
        chunk=min(occupancy.chunk, occupancy.calibrate_rays),
    )


def occupancy_for_model(
    config: Config, dataset: Dataset, model: MixNeRF, *, key: PRNGKey, with_choice: bool = False
) -> OccupancyGrid | tuple[OccupancyGrid, ThresholdChoice | None]:
    """A grid of `model`'s density evaluated in every cell (for rendering a trained model),
    with its threshold calibrated when `config.occupancy.calibrate` is on. `with_choice`
    returns `(grid, ThresholdChoice or None)` instead, for reports."""
    refresh_key, calibrate_key = jax.random.split(key)
    grid = _refresh_occupancy(make_occupancy_grid(config, dataset), model.field, key=refresh_key)
    grid, choice = calibrate_grid(config, dataset, model, grid, key=calibrate_key)
    return (grid, choice) if with_choice else grid


# Train-section keys that do not change the trajectory: a run may resume with them changed.
_COSMETIC_TRAIN_KEYS = (
    "eval_every",
    "num_eval_views",
    "checkpoint_every",
    "render_chunk",
    "run_dir",
    "typecheck",
    "max_nonfinite_steps",
)
# Data keys that say where the files are, not which: a run may resume from another checkout.
_COSMETIC_DATA_KEYS = ("data_dir", "dtu_mask_dir")
# Occupancy-grid settings shape only what is rendered, never the trained parameters.
_COSMETIC_SECTIONS = ("occupancy",)


def _comparable(config_dict: dict[str, Any]) -> dict[str, Any]:
    train = {k: v for k, v in config_dict["train"].items() if k not in _COSMETIC_TRAIN_KEYS}
    data = {k: v for k, v in config_dict["data"].items() if k not in _COSMETIC_DATA_KEYS}
    kept = {k: v for k, v in config_dict.items() if k not in _COSMETIC_SECTIONS}
    return {**kept, "train": train, "data": data, "name": None, "reproduces": None}


def _truncate_log(log_path: Path, last_step: int) -> None:
    """Drops the entries of `log_path` logged after step `last_step` (none if it is absent),
    and a last line cut short by a kill."""
    if not log_path.is_file():
        return

    def keep(line: str) -> bool:
        try:
            return json.loads(line).get("step", 0) <= last_step
        except json.JSONDecodeError:
            return False

    lines = log_path.read_text().splitlines()
    kept = [line for line in lines if keep(line)]
    if len(kept) != len(lines):
        temporary = log_path.with_suffix(".jsonl.tmp")
        temporary.write_text("".join(line + "\n" for line in kept))
        temporary.replace(log_path)


@dataclasses.dataclass
class TrainResult:
    """What `fit` returns: the trained model, its test metrics and where the outputs are."""

    model: MixNeRF
    metrics: dict[str, Any]
    run_dir: Path
    history: list[dict[str, Any]]


def _scalars(metrics: StepMetrics) -> dict[str, float]:
    terms = metrics.terms
    return {
        "loss": float(terms.total),
        "mse_fine": float(terms.mse_fine),
        "mse_coarse": float(terms.mse_coarse),
        "nll_colour": float(terms.nll_colour),
        "nll_depth": float(terms.nll_depth),
        "nll_regen": float(terms.nll_regen),
        "psnr": float(metrics.psnr),
        "lr": float(metrics.learning_rate),
        "lambda_colour": float(metrics.lambda_colour),
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

    **Returns:**

    A `TrainResult` with the final test metrics (also written to `metrics.json`).
    """
    run_dir = Path(config.train.run_dir)
    config_dict = config_to_dict(config)
    dataset = load_dataset(config.data) if dataset is None else dataset
    model_key, train_key = jax.random.split(init_key(config))
    model = build_model(
        config, key=model_key, frustum=dataset.frustum, white_background=dataset.white_background
    )
    optimizer = make_optimizer(config)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_array))
    start = 0
    checkpoint = latest_checkpoint(run_dir)
    if checkpoint is not None:
        stored = read_checkpoint_meta(checkpoint)["config"]
        if not resume:
            raise ConfigError(f"{run_dir} already holds checkpoints; resume, or choose another train.run_dir")
        if _comparable(stored) != _comparable(config_dict):
            changed = _differences(_comparable(stored), _comparable(config_dict))
            raise ConfigError(
                f"{checkpoint} was written with different settings ({', '.join(changed)}); "
                "choose another train.run_dir to start a new run"
            )
        model, opt_state, start, train_key = load_checkpoint(
            checkpoint, model=model, opt_state=opt_state, key=train_key
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(config_dict, indent=2))

    data = training_rays(dataset)
    train_step = make_train_step(config, optimizer, max_traces=1)
    occupancy = config.occupancy
    # The grid is rebuilt (from unevaluated, so all-occupied, cells) when a run resumes: it
    # only shapes what is rendered, never the training trajectory.
    grid = make_occupancy_grid(config, dataset) if occupancy.enabled else None
    grid_key = jax.random.fold_in(train_key, 0x0CC)
    history: list[dict[str, Any]] = []
    log_path = run_dir / "train_log.jsonl"
    # Entries past the checkpoint belong to a run that ended without saving them (a crash or
    # a kill): the resumed run redoes those steps, so the log keeps one entry per step.
    _truncate_log(log_path, start)
    max_steps = config.train.max_steps
    last_step = max_steps if stop_after is None else min(max_steps, stop_after)

    def checkpoint_now(step: int) -> Path:
        return save_checkpoint(
            run_dir, model=model, opt_state=opt_state, step=step, key=train_key, config=config_dict
        )

    previous_disable = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", not config.train.typecheck)
    bar = tqdm(total=max_steps, initial=start, disable=not progress, unit="step", dynamic_ncols=True)
    step = logged_step = start
    skipped_total = skipped_streak = 0
    pending = None

    def check_skipped(done: int, skipped) -> None:
        nonlocal skipped_total, skipped_streak
        if bool(skipped):
            skipped_total += 1
            skipped_streak += 1
            if skipped_streak >= config.train.max_nonfinite_steps:
                last_good = latest_checkpoint(run_dir)
                raise TrainingDiverged(
                    f"step {done}: {skipped_streak} consecutive steps had a non-finite loss or "
                    f"gradient and were not applied; stopping. The last good checkpoint is "
                    f"{last_good or 'none (no checkpoint was written yet)'}; lower the learning "
                    "rate or check the data, then resume from it."
                )
        else:
            skipped_streak = 0

    timer = time.perf_counter()
    try:
        with open(log_path, "a") as log_file:
            for step in range(start, last_step):
                model, opt_state, metrics = train_step(
                    model, opt_state, data, jnp.asarray(step, jnp.int32), train_key
                )
                done = step + 1
                # A step's skip flag is read once the next step is queued, so the host does not
                # wait for the device between steps; a step that logs, evaluates or checkpoints
                # is read at once, as those need its outcome.
                if pending is not None:
                    check_skipped(*pending)
                pending = (done, metrics.skipped)
                if (
                    done % log_every == 0
                    or done == last_step
                    or (config.train.eval_every and done % config.train.eval_every == 0)
                    or (config.train.checkpoint_every and done % config.train.checkpoint_every == 0)
                ):
                    check_skipped(*pending)
                    pending = None
                if done % log_every == 0 or done == last_step:
                    scalars = {"step": done, **_scalars(metrics), "skipped_steps": skipped_total}
                    elapsed = time.perf_counter() - timer
                    scalars["steps_per_s"] = (done - logged_step) / max(elapsed, 1e-9)
                    timer, logged_step = time.perf_counter(), done
                    history.append(scalars)
                    log_file.write(json.dumps(scalars) + "\n")
                    bar.set_postfix(
                        loss=f"{scalars['loss']:.4f}",
                        psnr=f"{scalars['psnr']:.2f}",
                        it_s=f"{scalars['steps_per_s']:.2f}",
                        skipped=skipped_total,
                    )
                    bar.update(done - bar.n)
                if grid is not None and done % occupancy.update_every == 0:
                    grid = _update_occupancy(
                        grid,
                        model.field,
                        key=jax.random.fold_in(grid_key, done),
                        decay=occupancy.decay,
                        fraction=occupancy.update_fraction,
                        offset=jnp.asarray(done // occupancy.update_every, jnp.int32),
                    )
                if config.train.eval_every and done % config.train.eval_every == 0 and done < max_steps:
                    ids = list(range(min(config.train.num_eval_views, dataset.test.num_views)))
                    means, _ = evaluate(
                        model,
                        dataset,
                        chunk=occupancy.chunk if grid is not None else config.train.render_chunk,
                        view_ids=ids,
                        with_lpips=False,
                        skipping=None if grid is None else make_skipping(config, grid),
                    )
                    shown = ", ".join(f"{k} {v:.4f}" for k, v in means.items() if v is not None)
                    bar.write(f"step {done}: held-out {shown}")
                    log_file.write(json.dumps({"step": done, "eval": means}) + "\n")
                # No checkpoint inside a run of skipped steps: the last good one must stay the
                # newest, so that a diverging run can be resumed from before the trouble began.
                if (
                    config.train.checkpoint_every
                    and done % config.train.checkpoint_every == 0
                    and not skipped_streak
                ):
                    checkpoint_now(done)
            step = last_step
    except KeyboardInterrupt:
        bar.close()
        path = checkpoint_now(step)
        print(f"\ninterrupted: checkpoint of step {step} written to {path}; run again to resume")
        raise
    finally:
        bar.close()
        jaxtyping.config.update("jaxtyping_disable", previous_disable)
    if step != start or latest_checkpoint(run_dir) is None:
        checkpoint_now(step)
    if step < max_steps:
        return TrainResult(
            model=model,
            metrics={"step": step, "skipped_steps": skipped_total},
            run_dir=run_dir,
            history=history,
        )

    renders = run_dir / "renders"

    def write_view(index: int, entry: dict[str, Any], outputs) -> None:
        if write_renders:
            write_view_renders(renders, dataset, index, entry["view"], outputs)

    skipping = choice = None
    if grid is not None:
        grid = _refresh_occupancy(grid, model.field, key=jax.random.fold_in(grid_key, step + 1))
        grid, choice = calibrate_grid(
            config, dataset, model, grid, key=jax.random.fold_in(grid_key, step + 2)
        )
        skipping = make_skipping(config, grid)
    stats = RenderStats()
    render_timer = time.perf_counter()
    means, per_view = evaluate(
        model,
        dataset,
        chunk=config.train.render_chunk if grid is None else occupancy.chunk,
        on_view=write_view,
        skipping=skipping,
        stats=stats,
    )
    metrics = {
        "step": step,
        "skipped_steps": skipped_total,
        "scene": dataset.name,
        "test": means,
        "per_view": per_view,
        "render": render_summary(stats, time.perf_counter() - render_timer, len(per_view), grid, choice),
        "config": config_dict,
    }
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return TrainResult(model=model, metrics=metrics, run_dir=run_dir, history=history)


def render_summary(
    stats: RenderStats,
    seconds: float,
    num_views: int,
    grid: OccupancyGrid | None,
    choice: ThresholdChoice | None = None,
) -> dict[str, Any]:
    """Per-frame render cost: field evaluations made and needed, and seconds (scoring included),
    with the grid's threshold and, if it was calibrated, how."""
    frames = max(num_views, 1)
    return {
        "skipping": grid is not None,
        "density_threshold": None if grid is None else grid.threshold,
        "calibration": None if choice is None else dataclasses.asdict(choice),
        "occupied_fraction": None if grid is None else float(grid.occupied_fraction()),
        "dense_evaluations_per_frame": stats.dense_evaluations / frames,
        "field_evaluations_per_frame": stats.padded_evaluations / frames,
        "needed_evaluations_per_frame": stats.field_evaluations / frames,
        "evaluation_reduction": stats.reduction,
        "seconds_per_frame": seconds / frames,
    }


def write_view_renders(folder: Path, dataset: Dataset, index: int, view_id: int, outputs) -> None:
    """Writes one test view's colour, depth and ground-truth PNGs into `folder`."""
    rgb, depth, _ = outputs
    save_png(folder / f"test_{view_id:03d}_rgb.png", rgb)
    save_png(folder / f"test_{view_id:03d}_depth.png", colourise_depth(depth, dataset.near, dataset.far))
    save_png(folder / f"test_{view_id:03d}_gt.png", dataset.test.images[index])


def _differences(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    changed = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            changed += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            changed.append(f"{prefix}{key}: {a!r} -> {b!r}")
    return changed
