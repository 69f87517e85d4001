"""The MixNeRF model: a field, two samplers, a renderer and a mixture in one pytree.

Rendering a level is three steps, each a method of the model: `sample_*` places the samples
(the samplers), `query_field` calls the field at them, `composite` turns the field's outputs into
pixels (the renderer). The dense render (`__call__`) and the render that skips empty space
(`mixnerf_eqx._inference.skipping`) run the same three steps; the second only evaluates fewer samples.
"""

import dataclasses
import inspect
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._config import Config, ConfigError, GridConfig, did_you_mean, schedule_steps
from .._custom_types import FourKeysPerRay, PRNGKey, RayKeys
from .budget import SampleBudget, budget_capacity, evaluate_live, transmittance_before
from .field import (
    AbstractField,
    AbstractGridEncoding,
    FieldOutputs,
    GridField,
    HashEncoding,
    MipNeRFField,
    TriPlaneEncoding,
)
from .field.grid import level_resolutions
from .mixture import AbstractMixture, LaplaceMixture
from .rays import Box, RayBundle, RaySamples, radius_box
from .renderer import AbstractRenderer, LevelOutputs, VolumeRenderer
from .sampler import AbstractSampler, HierarchicalSampler, StratifiedSampler


class RenderOutputs(eqx.Module):
    """Both levels of a batch of rays; the fine level is the model's prediction."""

    coarse: LevelOutputs
    fine: LevelOutputs


def _vmap_sampler(sampler: AbstractSampler, *args, keys: RayKeys | None) -> RaySamples:
    if keys is None:
        return jax.vmap(lambda *a: sampler(*a))(*args)
    return jax.vmap(lambda k, *a: sampler(*a, key=k))(keys, *args)


class BudgetReport(eqx.Module):
    """What a budgeted training render evaluated (`MixNeRF.render_within`).

    **Fields:**

    - `evaluations` (static): field evaluations made, both levels (the buffers' sizes).
    - `dense` (static): the dense render's, both levels.
    - `coarse_live`, `fine_live`: samples the budget found live on each level.
    - `dropped`: live samples that did not fit their level's buffer.
    """

    evaluations: int = eqx.field(static=True)
    dense: int = eqx.field(static=True)
    coarse_live: Array
    fine_live: Array
    dropped: Array


class MixNeRF(eqx.Module):
    """mip-NeRF's two-level cone tracer with MixNeRF's mixture density (paper Sec. 3).

    The same `field` serves the coarse level (samples from `coarse_sampler`) and the fine
    level (samples from `fine_sampler`, drawn from the coarse weights). `mixture` holds the
    mixture density used by the losses; the mip-NeRF baseline is the same model whose field
    has no mixture heads and whose `mixture` is `None`. With `remat`, the field's activations
    are recomputed in the backward pass instead of stored, which bounds training memory at the
    paper's batch on small machines for about a third more compute.

    Any part can be replaced by another implementation of its abstract class, e.g.
    `eqx.tree_at(lambda m: m.fine_sampler, model, OtherSampler(...))`; the dense and the
    skipping render both follow the replacement.
    """

    field: AbstractField
    coarse_sampler: AbstractSampler
    fine_sampler: AbstractSampler
    renderer: AbstractRenderer
    mixture: AbstractMixture | None
    remat: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.mixture is not None and not self.field.has_mixture_heads:
            raise ValueError("a mixture needs a field with mixture heads (beta and ray depth)")

    @property
    def samples_per_ray(self) -> int:
        """Field evaluations the dense render makes per ray (both levels)."""
        return self.coarse_sampler.num_samples + self.fine_sampler.num_samples

    def sample_coarse(self, rays: RayBundle, keys: RayKeys | None = None) -> RaySamples:
        """The coarse samples of a flat batch of rays (`keys`: one per ray, or `None`)."""
        return _vmap_sampler(self.coarse_sampler, rays, keys=keys)

    def sample_fine(self, rays: RayBundle, coarse: LevelOutputs, keys: RayKeys | None = None) -> RaySamples:
        """The fine samples of a flat batch of rays, drawn from the coarse level's weights."""
        return _vmap_sampler(self.fine_sampler, rays, coarse.t_edges, coarse.weights, keys=keys)

    def query_points(
        self,
        means: Float[Array, "batch 3"],
        covs: Float[Array, "batch 3"],
        viewdirs: Float[Array, "batch 3"],
        keys: RayKeys | None = None,
    ) -> FieldOutputs:
        """The field at a flat list of frustum Gaussians (`keys`: one per point, or `None`).

        A flat list makes each dense layer one matrix product over every point (a field
        vmapped over rays and then over samples ran about 1.5x slower on the CPU:
        `benchmarks/LOG.md`, "Profile of the training step").
        """
        evaluate = type(self.field).evaluate_batch
        if self.remat:
            evaluate = jax.checkpoint(evaluate)
        return evaluate(self.field, means, covs, viewdirs, keys)

    def query_field(self, samples: RaySamples, rays: RayBundle, keys: RayKeys | None = None) -> FieldOutputs:
        """The field at every sample of a flat batch of rays (`keys`: one per ray, or `None`)."""
        num_rays, num_samples = samples.means.shape[:2]
        points = num_rays * num_samples
        viewdirs = jnp.broadcast_to(rays.viewdirs[:, None, :], (num_rays, num_samples, 3))
        point_keys = None
        if keys is not None:
            # Per ray, one key per sample, as `jax.random.split(ray_key, num_samples)`.
            point_keys = jax.vmap(lambda k: jax.random.split(k, num_samples))(keys)
            point_keys = point_keys.reshape(points, *point_keys.shape[2:])
        outputs = self.query_points(
            samples.means.reshape(points, 3),
            samples.covs.reshape(points, 3),
            viewdirs.reshape(points, 3),
            point_keys,
        )
        return jax.tree_util.tree_map(lambda x: x.reshape(num_rays, num_samples, *x.shape[1:]), outputs)

    def composite(self, outputs: FieldOutputs, samples: RaySamples, rays: RayBundle) -> LevelOutputs:
        """The renderer over a flat batch of rays."""
        return jax.vmap(self.renderer)(outputs, samples.t_edges, rays)

    def _render_flat(self, rays: RayBundle, ray_keys: FourKeysPerRay | None) -> RenderOutputs:
        """Renders a flat batch of rays; `ray_keys` holds four keys per ray, or is `None`.

        A ray's keys are, in order, for the coarse sampler, the coarse density noise, the fine
        sampler and the fine density noise.
        """

        def keys(index: int):
            return None if ray_keys is None else ray_keys[:, index]

        coarse_samples = self.sample_coarse(rays, keys(0))
        coarse = self.composite(self.query_field(coarse_samples, rays, keys(1)), coarse_samples, rays)
        fine_samples = self.sample_fine(rays, coarse, keys(2))
        fine = self.composite(self.query_field(fine_samples, rays, keys(3)), fine_samples, rays)
        return RenderOutputs(coarse=coarse, fine=fine)

    def _query_live(
        self,
        samples: RaySamples,
        rays: RayBundle,
        keys: RayKeys | None,
        live,
        fraction: float,
    ):
        num_rays, num_samples = samples.means.shape[:2]
        point_keys = None
        if keys is not None:
            point_keys = jax.vmap(lambda k: jax.random.split(k, num_samples))(keys)
            point_keys = point_keys.reshape(num_rays * num_samples, *point_keys.shape[2:])
        capacity = budget_capacity(fraction, num_rays, num_samples)
        outputs, dropped, _ = evaluate_live(
            self.query_points,
            samples.means,
            samples.covs,
            rays.viewdirs,
            point_keys,
            live,
            capacity,
            with_mixture_heads=self.field.has_mixture_heads,
        )
        return outputs, dropped, capacity

    def render_within(
        self, rays: RayBundle, budget: SampleBudget, *, key: PRNGKey | None = None
    ) -> tuple[RenderOutputs, BudgetReport]:
        """Renders a flat batch of rays as `__call__` does, evaluating the field only at the
        live samples that fit the budget's buffers (`mixnerf_eqx._nn.budget`).

        With every sample live and both fractions 1 the outputs equal `__call__`'s.
        """
        flat = rays.reshape(-1)
        num_rays = flat.origins.shape[0]
        ray_keys = None
        if key is not None:
            ray_keys = jax.vmap(lambda k: jax.random.split(k, 4))(jax.random.split(key, num_rays))

        def keys(index: int):
            return None if ray_keys is None else ray_keys[:, index]

        coarse_samples = self.sample_coarse(flat, keys(0))
        coarse_live = budget.live(coarse_samples.means)
        coarse_field, coarse_dropped, coarse_capacity = self._query_live(
            coarse_samples, flat, keys(1), coarse_live, budget.coarse_fraction
        )
        coarse = self.composite(coarse_field, coarse_samples, flat)
        fine_samples = self.sample_fine(flat, coarse, keys(2))
        fine_live = budget.live(fine_samples.means)
        if budget.stop_transmittance > 0:
            centres = 0.5 * (fine_samples.t_edges[:, 1:] + fine_samples.t_edges[:, :-1])
            lit = transmittance_before(coarse.t_edges, coarse.weights, centres)
            fine_live = fine_live & (lit >= budget.stop_transmittance)
        fine_field, fine_dropped, fine_capacity = self._query_live(
            fine_samples, flat, keys(3), fine_live, budget.fine_fraction
        )
        fine = self.composite(fine_field, fine_samples, flat)
        report = BudgetReport(
            evaluations=coarse_capacity + fine_capacity,
            dense=num_rays * self.samples_per_ray,
            coarse_live=jnp.sum(coarse_live),
            fine_live=jnp.sum(fine_live),
            dropped=coarse_dropped + fine_dropped,
        )
        return RenderOutputs(coarse=coarse, fine=fine), report

    def render_ray(self, ray: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders one ray (empty batch shape); `key=None` renders deterministically."""
        ray_keys = None if key is None else jax.random.split(key, 4)[None]
        outputs = self._render_flat(ray.reshape(1), ray_keys)
        return jax.tree_util.tree_map(lambda x: x[0], outputs)

    def __call__(self, rays: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders a batch of rays of any batch shape.

        **Arguments:**

        - `rays`: the rays.
        - `key`: training randomness (jittered samples, density noise); `None` for the
          deterministic evaluation render. Ray `i` of the flattened batch renders as
          `render_ray(ray_i, key=jax.random.split(key, num_rays)[i])` does.

        **Returns:**

        A `RenderOutputs` whose leaves have `rays.batch_shape` in front.
        """
        batch_shape = rays.batch_shape
        flat = rays.reshape(-1)
        ray_keys = None
        if key is not None:
            ray_keys = jax.vmap(lambda k: jax.random.split(k, 4))(
                jax.random.split(key, flat.origins.shape[0])
            )
        outputs = self._render_flat(flat, ray_keys)
        return jax.tree_util.tree_map(lambda x: x.reshape(*batch_shape, *x.shape[1:]), outputs)


def _from_model_section(config: Config) -> dict[str, object]:
    """What every field takes from `[model]`: the view encoding, density bias, colour padding."""
    model = config.model
    return dict(
        viewdir_max_deg=model.viewdir_max_deg, density_bias=model.density_bias, rgb_padding=model.rgb_padding
    )


def _mlp_field(config: Config, *, mixture_heads: bool, key: PRNGKey, scene_box: Box | None) -> MipNeRFField:
    """The paper's field: the mip-NeRF MLP, its `[mlp]` section passed whole (each key is a
    keyword of `MipNeRFField`) with what `[model]` shares."""
    del scene_box  # the MLP's integrated encoding needs no box
    return MipNeRFField(
        **dataclasses.asdict(config.mlp), **_from_model_section(config), mixture_heads=mixture_heads, key=key
    )


# `config.grid.encoding` -> the encoding's constructor, given the `[grid]` section, the levels'
# resolutions and a key. A new encoding is its class (an `AbstractGridEncoding`) and one entry
# here (its own keys, if any, in `GridConfig` and `_config.ENCODING_KEYS`).
ENCODING_BUILDERS: dict[str, Callable[[GridConfig, tuple[int, ...], PRNGKey], AbstractGridEncoding]] = {
    "triplane": lambda grid, resolutions, key: TriPlaneEncoding(resolutions, grid.features, key=key),
    "hash": lambda grid, resolutions, key: HashEncoding(
        resolutions, grid.features, 2**grid.hash_table_log2, key=key
    ),
}

# The `[grid]` keys passed to `GridField` as they are: its keywords, less those the builder
# sets itself (the encoding, the box, the schedule) or takes from `[model]`. A `[grid]` key
# that is not one of them is read by the builder or by an encoding's entry above.
_GRID_FIELD_KEYS = frozenset(inspect.signature(GridField.__init__).parameters) - {
    "self", "encoding", "box_min", "box_max", "bounded", "coarse_to_fine_steps", "viewdir_max_deg",
    "density_bias", "rgb_padding", "mixture_heads", "key",
}


def _grid_field(config: Config, *, mixture_heads: bool, key: PRNGKey, scene_box: Box | None) -> GridField:
    """A grid encoding (`ENCODING_BUILDERS`) and a small decoder, the rest of `[grid]` passed
    through to `GridField`, with what `[model]` shares. It spans `[-r, r]^3` when
    `config.grid.box_radius = r > 0` (the scene lies inside; nothing outside), and otherwise
    `scene_box`."""
    grid = config.grid
    check_model_names(config)
    encoding_builder = ENCODING_BUILDERS[grid.encoding]
    box = radius_box(grid.box_radius)
    bounded = box is not None
    scene_box = box if bounded else scene_box
    if scene_box is None:
        raise ValueError("a grid field with grid.box_radius = 0 needs the scene's box (scene_box)")
    encoding_key, decoder_key = jax.random.split(key)
    resolutions = level_resolutions(grid.levels, grid.min_resolution, grid.max_resolution)
    passed = {name: value for name, value in dataclasses.asdict(grid).items() if name in _GRID_FIELD_KEYS}
    return GridField(
        encoding_builder(grid, resolutions, encoding_key),
        box_min=tuple(float(v) for v in scene_box[0]),
        box_max=tuple(float(v) for v in scene_box[1]),
        bounded=bounded,
        coarse_to_fine_steps=schedule_steps(config).coarse_to_fine,
        **passed,
        **_from_model_section(config),
        mixture_heads=mixture_heads,
        key=decoder_key,
    )


# `config.model.field` -> the constructor of that field. A new field is its class and one entry
# here (with a config section of its own if it has settings: `_config.FIELD_SECTIONS`);
# `tests/test_field_contract.py` then holds it to the contract every field meets.
FIELD_BUILDERS: dict[str, Callable[..., AbstractField]] = {"mlp": _mlp_field, "grid": _grid_field}


def _unknown(key: str, value: str, known: dict[str, object]) -> str:
    return f"{key} = {value!r} is none of {', '.join(sorted(known))}{did_you_mean(value, known)}"


def check_model_names(config: Config) -> None:
    """Raises a `ConfigError` if `model.field` names no entry of `FIELD_BUILDERS` or, for the
    grid field, `grid.encoding` none of `ENCODING_BUILDERS`. The config does not list the names
    (it imports no model), so `fit`, sweeps and the commands call this before they load or
    write anything."""
    if config.model.field not in FIELD_BUILDERS:
        raise ConfigError(_unknown("model.field", config.model.field, FIELD_BUILDERS))
    if config.model.field == "grid" and config.grid.encoding not in ENCODING_BUILDERS:
        raise ConfigError(_unknown("grid.encoding", config.grid.encoding, ENCODING_BUILDERS))


def build_field(config: Config, *, key: PRNGKey, scene_box: Box | None = None) -> AbstractField:
    """The field `config.model.field` names (`FIELD_BUILDERS`), with mixture heads for
    MixNeRF; `scene_box` is the training frusta's box (a grid field without
    `grid.box_radius` spans it)."""
    check_model_names(config)
    builder = FIELD_BUILDERS[config.model.field]
    return builder(config, mixture_heads=config.method == "mixnerf", key=key, scene_box=scene_box)


def build_model(
    config: Config,
    *,
    key: PRNGKey,
    frustum: str = "cone",
    white_background: bool = True,
    scene_box: Box | None = None,
) -> MixNeRF:
    """Builds the model that `config` describes.

    **Arguments:**

    - `config`: the run's configuration; `config.method` chooses MixNeRF or the mip-NeRF
      baseline, `config.model` the field and samplers, `config.loss` the mixture's numerics.
    - `key`: initialisation randomness.
    - `frustum`: the dataset's frustum shape, used when `config.model.frustum` is `"auto"`.
    - `white_background`: composite on white (Blender-style scenes).
    - `scene_box`: the training frusta's box `(min, max)`, which a grid field spans unless
      `config.grid.box_radius` is set (`mixnerf_eqx.training.scene_box` computes it).

    **Returns:**

    A `MixNeRF`; for `method = "mipnerf"`, without mixture heads and mixture.
    """
    model_cfg = config.model
    shape = frustum if model_cfg.frustum == "auto" else model_cfg.frustum
    mixture_model = config.method == "mixnerf"
    field = build_field(config, key=key, scene_box=scene_box)
    mixture = None
    if mixture_model:
        mixture = LaplaceMixture(
            weight_eps=config.loss.weight_eps,
            likelihood_floor=config.loss.likelihood_floor or None,
            depth_scale=config.loss.depth_scale,
            evaluation=config.loss.nll_evaluation,
            background=(1.0, 1.0, 1.0) if white_background and config.loss.background_component else None,
            background_scale=config.loss.background_scale,
        )
    return MixNeRF(
        field=field,
        coarse_sampler=StratifiedSampler(model_cfg.num_coarse_samples, shape, model_cfg.lindisp),
        fine_sampler=HierarchicalSampler(model_cfg.num_fine_samples, shape, model_cfg.resample_padding),
        renderer=VolumeRenderer((1.0, 1.0, 1.0) if white_background else None),
        mixture=mixture,
        remat=model_cfg.remat,
    )
