"""The training state and the pure training step.

`init_train_state` builds everything a run starts from (model, optimiser state, step, key,
occupancy grid) as one `TrainState` Module; `make_train_step` returns the jitted function
`(state, batch) -> (state, metrics)`. The training loop (`fit`), the evaluation command, the
notebook and the benchmarks all start from these two, as MultiNeRF's train, eval and render
scripts share one `setup_model`.
"""

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float, Int, PyTree

from .._config import Config, LossConfig, OccupancyConfig, OptimConfig, TrainConfig, schedule_steps
from .._custom_types import PoseStack, PRNGKey
from .._inference.camera_path import orbit_path, spiral_path
from .._inference.occupancy import OccupancyGrid, OccupiedCells, empty_grid, frustum_box, update_occupancy
from .._nn.budget import SampleBudget
from .._nn.field import AbstractField
from .._nn.model import MixNeRF, build_model
from .._nn.rays import Box, RayBundle, radius_box
from ..data import Dataset, rays_at_poses, rays_for_views
from .loss import LossTerms, LossWeights, loss_fn, needs_patches
from .schedule import anneal_sample_space, learning_rate_schedule, linear_ramp


def make_optimizer(optim: OptimConfig, learning_rate: optax.Schedule) -> optax.GradientTransformation:
    """Element-wise clip, global-norm clip, then Adam on `learning_rate`.

    `learning_rate` is indexed by step number, counting from 1 as the released code does;
    Adam's `count` is the number of updates already applied, so update `count` uses the
    learning rate of step `count + 1`.
    """

    def by_update(count: Int[Array, ""]) -> Float[Array, ""]:
        return learning_rate(count + 1)

    parts = []
    if optim.grad_max_value > 0:
        parts.append(optax.clip(optim.grad_max_value))
    if optim.grad_max_norm > 0:
        parts.append(optax.clip_by_global_norm(optim.grad_max_norm))
    parts.append(optax.adam(by_update))
    return optax.chain(*parts)


def scene_box(dataset: Dataset) -> Box:
    """The box of the training rays between near and far (in NDC for LLFF scenes), grown by
    1% on every side: every sample a training ray can place lies inside."""
    low, high = frustum_box(rays_for_views(dataset.train, dataset.near, dataset.far))
    return tuple(float(v) for v in low), tuple(float(v) for v in high)


def make_occupancy_grid(occupancy: OccupancyConfig, dataset: Dataset) -> OccupancyGrid:
    """An unevaluated grid for `dataset` as `occupancy` says.

    With `occupancy.box_radius > 0` the grid spans `[-r, r]^3` and the scene is taken to lie
    inside it; otherwise it spans the box of the training rays between near and far (in NDC
    for LLFF scenes) and points outside it count as occupied.
    """
    box = radius_box(occupancy.box_radius)
    outside_occupied = box is None
    box_min, box_max = scene_box(dataset) if box is None else box
    return empty_grid(
        box_min,
        box_max,
        resolution=occupancy.resolution,
        threshold=occupancy.density_threshold,
        dilation=occupancy.dilation,
        outside_occupied=outside_occupied,
    )


class TrainState(eqx.Module):
    """Everything a training run carries from one step to the next.

    **Fields:**

    - `model`: the model being trained.
    - `opt_state`: the optimiser's state.
    - `step`: steps taken so far (a step whose update was not finite counts, unapplied).
    - `key`: the run's training key; step `s` draws its randomness from `fold_in(key, s)`.
    - `grid`: the occupancy grid kept during training, or `None`.
    - `optimizer` (static): the gradient transformation.
    - `learning_rate` (static): the learning rate by step number (from 1).
    - `cells`: with `occupancy.train_skipping`, the grid's occupied cells as the steps skip
      them (its dilated mask, computed at each grid update rather than in every step), once
      the grid has looked at every cell; `None` before (the steps are dense) and without
      skipping. Not stored in checkpoints: `training_cells` recomputes it from the grid.
    """

    model: MixNeRF
    opt_state: PyTree
    step: Int[Array, ""]
    key: PRNGKey
    grid: OccupancyGrid | None
    optimizer: optax.GradientTransformation = eqx.field(static=True)
    learning_rate: optax.Schedule = eqx.field(static=True)
    cells: OccupiedCells | None = None


def init_key(config: Config) -> PRNGKey:
    """The root random key of a run (`train.seed`)."""
    return jax.random.key(config.train.seed)


# One compiled program draws every initial parameter (the config, frustum and box are static,
# so a process compiles it once per setting): run op by op, each initialiser of another shape
# compiled on its own, about 4 s of a CPU run's start, none of it in the persistent cache.
_build_model_compiled = eqx.filter_jit(build_model)


def init_train_state(
    config: Config, dataset: Dataset, *, key: PRNGKey | None = None, box: Box | None = None
) -> TrainState:
    """The state a run starts from.

    **Arguments:**

    - `config`: the run's configuration.
    - `dataset`: the scene (its frustum shape, background and, for the occupancy grid, the
      training rays' box).
    - `key`: the root key; default `init_key(config)`. It is split into the model's
      initialisation key and the run's training key.
    - `box`: the box a grid field spans when `grid.box_radius = 0`; default the training
      rays' (`scene_box(dataset)`). A resumed run passes the one it began with (its
      checkpoints record it), since another scene's training rays may span another.

    **Returns:**

    A `TrainState` at step 0.
    """
    model_key, train_key = jax.random.split(init_key(config) if key is None else key)
    model = _build_model_compiled(
        config,
        key=model_key,
        frustum=dataset.frustum,
        white_background=dataset.white_background,
        scene_box=scene_box(dataset) if box is None else box,
    )
    optim = config.optim
    horizon = optim.decay_steps or config.train.max_steps
    learning_rate = learning_rate_schedule(
        optim.lr_init, optim.lr_final, horizon, schedule_steps(config).warmup
    )
    optimizer = make_optimizer(optim, learning_rate)
    grid = make_occupancy_grid(config.occupancy, dataset) if config.occupancy.enabled else None
    return TrainState(
        model=model,
        opt_state=optimizer.init(eqx.filter(model, eqx.is_array)),
        step=jnp.asarray(0, jnp.int32),
        key=train_key,
        grid=grid,
        optimizer=optimizer,
        learning_rate=learning_rate,
    )


class TrainingRays(eqx.Module):
    """Every training pixel's ray and colour, on the device, grouped by image, and the pool of
    unseen-view patches that the depth-smoothness prior draws from (`None` without it)."""

    rays: RayBundle
    rgb: Float[Array, "num_views num_pixels channels"]
    patches: RayBundle | None = None
    patches_per_step: int = eqx.field(static=True, default=0)


def unseen_cameras(dataset: Dataset, num_views: int) -> PoseStack:
    """Cameras no training image was taken from, for the priors on unseen views: a spiral
    around the training cameras for forward-facing (NDC) scenes, otherwise an orbit at their
    mean distance and elevation (`mixnerf_eqx._inference.camera_path`). Built from the training poses
    alone."""
    poses = np.asarray(dataset.train.camtoworlds, np.float64)
    path = spiral_path(poses, num_views) if dataset.train.ndc else orbit_path(poses, num_views)
    return path.astype(np.float32)


def unseen_patches(
    dataset: Dataset, num_views: int, patch_size: int, patches_per_view: int = 16, seed: int = 0
) -> RayBundle:
    """A pool of square patches of rays from `unseen_cameras`, `patches_per_view` at random
    places in each, with the training views' image size, intrinsics and ray space.

    **Returns:**

    A `RayBundle` of batch shape `(num_views * patches_per_view, patch_size, patch_size)`.
    """
    train = dataset.train
    if patch_size > min(train.height, train.width):
        raise ValueError(
            f"loss.smoothness_patch_size {patch_size} exceeds the training images "
            f"({train.height}x{train.width})"
        )
    rng = np.random.default_rng(seed)
    offsets = np.arange(patch_size)
    pool = []
    for pose in unseen_cameras(dataset, num_views):
        rays = rays_at_poses(train, pose[None], dataset.near, dataset.far)
        rows = rng.integers(0, train.height - patch_size + 1, patches_per_view)
        cols = rng.integers(0, train.width - patch_size + 1, patches_per_view)
        index = (
            0,
            (rows[:, None, None] + offsets[None, :, None]),
            (cols[:, None, None] + offsets[None, None, :]),
        )
        pool.append(jax.tree_util.tree_map(lambda leaf, index=index: leaf[index], rays))
    return jax.tree_util.tree_map(lambda *leaves: jnp.concatenate(leaves), *pool)


def training_rays(dataset: Dataset, loss: LossConfig | None = None) -> TrainingRays:
    """Builds the device-resident ray table of the training views (and, when `loss` turns
    the depth-smoothness prior on, its pool of unseen-view patches)."""
    views = dataset.train
    rays = rays_for_views(views, dataset.near, dataset.far)
    num_pixels = views.height * views.width
    patches, per_step = None, 0
    if loss is not None and needs_patches(loss):
        patches = unseen_patches(dataset, loss.smoothness_views, loss.smoothness_patch_size)
        per_step = loss.smoothness_patches
    return TrainingRays(
        rays=rays.reshape(views.num_views, num_pixels),
        rgb=jnp.asarray(views.images.reshape(views.num_views, num_pixels, 3), jnp.float32),
        patches=patches,
        patches_per_step=per_step,
    )


class Batch(eqx.Module):
    """The rays of one training step and their true colours, and the unseen-view patches of
    the depth-smoothness prior (flattened, `None` without it)."""

    rays: RayBundle
    rgb: Float[Array, "batch channels"]
    patches: RayBundle | None = None


def _step_keys(state: TrainState) -> tuple[PRNGKey, PRNGKey]:
    """The batch key and the render key of the step `state` is about to take."""
    batch_key, render_key = jax.random.split(jax.random.fold_in(state.key, state.step))
    return batch_key, render_key


def _annealed(
    rays: RayBundle, step_number: Int[Array, ""] | int, anneal_steps: int, train: TrainConfig
) -> RayBundle:
    """`rays` with the sample space of step `step_number` (`anneal_sample_space`)."""
    return anneal_sample_space(rays, step_number, anneal_steps, train.anneal_start, train.anneal_mid)


def _at_step(model: MixNeRF, step_number: Int[Array, ""] | int) -> MixNeRF:
    """`model` with the field as step `step_number` sees it (a grid's coarse-to-fine levels)."""
    return eqx.tree_at(lambda m: m.field, model, model.field.at_step(step_number))


def draw_batch(data: TrainingRays, state: TrainState, batch_size: int) -> Batch:
    """`batch_size` random pixels (with replacement) of one random training image, drawn
    with the randomness of the step `state` is about to take, and `data.patches_per_step`
    random patches of the unseen-view pool."""
    batch_key = _step_keys(state)[0]
    image_key, pixel_key = jax.random.split(batch_key)
    num_images, num_pixels = data.rgb.shape[:2]
    image = jax.random.randint(image_key, (), 0, num_images)
    pixels = jax.random.randint(pixel_key, (batch_size,), 0, num_pixels)
    rays = jax.tree_util.tree_map(lambda x: x[image][pixels], data.rays)
    patches = None
    if data.patches is not None:
        # A key of its own, so that a run without patches draws exactly the pixels it always did.
        patch_key = jax.random.fold_in(batch_key, 1)
        chosen = jax.random.randint(patch_key, (data.patches_per_step,), 0, data.patches.batch_shape[0])
        patches = jax.tree_util.tree_map(lambda x: x[chosen], data.patches)
        patches = patches.reshape(-1)
    return Batch(rays=rays, rgb=data.rgb[image][pixels], patches=patches)


class StepMetrics(eqx.Module):
    """What one training step reports."""

    terms: LossTerms
    psnr: Float[Array, ""]
    learning_rate: Float[Array, ""]
    lambda_colour: Float[Array, ""]
    skipped: Bool[Array, ""]


def _all_finite(tree: Any) -> Bool[Array, ""]:
    leaves = [
        jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    ]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


# Buffer shares are rungs of a ladder, each 1/sqrt(2) of the one above (1, 0.71, 0.5, 0.35,
# 0.25, ...): a step compiles once per rung pair (seconds on a CPU), so the rungs are few and
# far apart; a share between two rungs costs at most sqrt(2) times its evaluations.
BUDGET_RUNGS = tuple(2.0 ** (-k / 2) for k in range(15))


def budget_bucket(live_share: float, headroom: float, current: float | None = None) -> float:
    """The buffer share for a level whose live share was `live_share`: the smallest rung of
    `BUDGET_RUNGS` that holds `live_share + headroom`. With the `current` share, a larger rung
    is taken only when the current one leaves less than half the headroom, so that a share
    near a rung does not switch (and compile) back and forth."""
    wanted = min(rung for rung in BUDGET_RUNGS if rung >= min(1.0, live_share + headroom) - 1e-9)
    if current is not None and wanted > current and live_share + headroom / 2 <= current:
        return current
    return wanted


def make_train_step(
    config: Config, *, max_traces: int | None = None, budget: tuple[float, float] = (1.0, 1.0)
) -> Callable[[TrainState, Batch], tuple[TrainState, StepMetrics]]:
    """The jitted training step `(state, batch) -> (state, metrics)`.

    The step is pure: the schedules are evaluated at step number `state.step + 1` (steps
    count from 1), its randomness comes from `fold_in(state.key, state.step)`, and a step
    whose loss or gradients are not finite leaves the model and the optimiser state exactly
    as they were (only `step` advances, so the next step draws another batch). With
    `max_traces`, tracing more often than that raises (a guard against recompiles).

    With `occupancy.train_skipping`, the step evaluates the field within buffers of `budget`
    = (coarse, fine) shares of the samples (`budget_bucket`) where `state.cells` is set (the
    occupancy grid has looked at every cell: `training_cells`), and densely where it is
    `None`; the two compile apart (the state's structure differs).
    """
    weights = LossWeights.from_config(config.loss, config.method)
    loss_cfg, train_cfg, occupancy = config.loss, config.train, config.occupancy
    lengths = schedule_steps(config)
    skips = occupancy.enabled and occupancy.train_skipping

    def train_step(state: TrainState, batch: Batch) -> tuple[TrainState, StepMetrics]:
        step_number = state.step + 1
        rays = _annealed(batch.rays, step_number, lengths.anneal, train_cfg)
        lambda_colour = linear_ramp(
            step_number,
            loss_cfg.lambda_colour_start,
            loss_cfg.lambda_colour_end,
            lengths.lambda_colour,
        )

        def scheduled_loss(model: MixNeRF, *args, **kwargs):
            # The stored model keeps the whole field.
            return loss_fn(_at_step(model, step_number), *args, **kwargs)

        patches = batch.patches
        if patches is not None:
            patches = _annealed(patches, step_number, lengths.anneal, train_cfg)
        sample_budget = None
        if skips and state.cells is not None:
            # The grid only skips space it has looked at: `cells` is None (dense steps) until
            # every cell is evaluated (`training_cells`).
            sample_budget = SampleBudget(
                occupancy=state.cells,
                coarse_fraction=budget[0],
                fine_fraction=budget[1],
                stop_transmittance=occupancy.train_stop_transmittance,
            )
        (_, terms), grads = eqx.filter_value_and_grad(scheduled_loss, has_aux=True)(
            state.model,
            rays,
            batch.rgb,
            lambda_colour,
            weights,
            key=_step_keys(state)[1],
            patches=patches,
            budget=sample_budget,
        )
        params = eqx.filter(state.model, eqx.is_array)
        updates, new_opt_state = state.optimizer.update(grads, state.opt_state, params)
        new_model = eqx.apply_updates(state.model, updates)
        finite = jnp.isfinite(terms.total) & _all_finite(grads)
        model, opt_state = jax.tree_util.tree_map(
            lambda new, old: jnp.where(finite, new, old) if eqx.is_array(new) else new,
            (new_model, new_opt_state),
            (state.model, state.opt_state),
        )
        metrics = StepMetrics(
            terms=terms,
            psnr=-10.0 * jnp.log10(terms["mse_fine"]),
            learning_rate=state.learning_rate(step_number),
            lambda_colour=lambda_colour,
            skipped=~finite,
        )
        state = eqx.tree_at(lambda s: (s.model, s.opt_state, s.step), state, (model, opt_state, step_number))
        return state, metrics

    if max_traces is not None:
        train_step = eqx.debug.assert_max_traces(train_step, max_traces=max_traces)
    return eqx.filter_jit(train_step)


def make_live_counter(config: Config) -> Callable[[TrainState, RayBundle], Float[Array, "5"]]:
    """`count(state, rays)`: the live samples of `rays` as the next skipping step would count
    them (its annealed sample space, its field's levels, its randomness, `state.cells`), as
    `[coarse, fine, 0, coarse total, fine total]`; forward only. Training counts a few rays of
    each measured batch with it to size the skipping buffers, also while the steps are dense."""
    lengths, train_cfg, occupancy = schedule_steps(config), config.train, config.occupancy

    @eqx.filter_jit
    def count(state: TrainState, rays: RayBundle) -> Float[Array, "5"]:
        step_number = state.step + 1  # as `make_train_step`'s step sees its rays and field
        rays = _annealed(rays, step_number, lengths.anneal, train_cfg)
        model = _at_step(state.model, step_number)
        budget = SampleBudget(occupancy=state.cells, stop_transmittance=occupancy.train_stop_transmittance)
        _, report = model.render_within(rays, budget, key=_step_keys(state)[1])
        num_rays = rays.batch_shape[0]
        totals = [float(num_rays * model.coarse_sampler.num_samples), float(num_rays * model.fine_sampler.num_samples)]
        return jnp.stack(
            [
                report.coarse_live.astype(float),
                report.fine_live.astype(float),
                jnp.zeros(()),
                jnp.asarray(totals[0]),
                jnp.asarray(totals[1]),
            ]
        )

    return count


def occupancy_key(key: PRNGKey, step: Int[Array, ""] | int) -> PRNGKey:
    """The randomness of the occupancy grid's work at `step` (its updates, and the final
    render's threshold calibration at `step + 1`): a stream apart from the steps' own."""
    return jax.random.fold_in(jax.random.fold_in(key, 0x0CC), step)


def update_grid(state: TrainState, occupancy: OccupancyConfig) -> TrainState:
    """`state` with `occupancy.update_fraction` of its grid's cells re-evaluated (and, with
    `occupancy.train_skipping`, its `cells` recomputed: `training_cells`).

    Meant for every `occupancy.update_every`-th step; the cells visited rotate with the
    step, so every cell is visited once in `1 / update_fraction` updates.
    """
    if state.grid is None:
        return state
    grid = _updated_grid(state.grid, state.model.field, state.key, state.step, occupancy)
    return training_cells(eqx.tree_at(lambda s: s.grid, state, grid), occupancy)


@eqx.filter_jit
def _updated_grid(
    grid: OccupancyGrid, field: AbstractField, key: PRNGKey, step: Int[Array, ""], occupancy: OccupancyConfig
) -> OccupancyGrid:
    return update_occupancy(
        grid,
        field,
        key=occupancy_key(key, step),
        decay=occupancy.decay,
        fraction=occupancy.update_fraction,
        offset=step // occupancy.update_every,
    )


@eqx.filter_jit
def _cells_if_complete(grid: OccupancyGrid) -> tuple[OccupiedCells, Bool[Array, ""]]:
    return grid.cells(), grid.fully_evaluated()


def training_cells(state: TrainState, occupancy: OccupancyConfig) -> TrainState:
    """`state` with `cells` set from its grid (with `occupancy.train_skipping`, once the grid
    has looked at every cell; `None` otherwise). Called after every grid update and on resume;
    the steps read the dilated mask from here instead of computing it each step."""
    cells = None
    if occupancy.enabled and occupancy.train_skipping and state.grid is not None:
        found, complete = _cells_if_complete(state.grid)
        cells = found if bool(complete) else None
    return dataclasses.replace(state, cells=cells)
