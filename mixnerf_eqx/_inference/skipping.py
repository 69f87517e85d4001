"""Rendering that skips empty space and finished rays, through the model's own steps.

The dense render evaluates the field at every sample of every ray. This one runs the same
three steps of the model (`MixNeRF.sample_*`, `query_points`, `composite`) but evaluates
the field only where it can matter:

- empty space: samples in cells that an `OccupancyGrid` marks empty get the outputs of zero
  density without a field evaluation;
- finished rays: each level is evaluated in `segments` pieces along the ray, front to back;
  once the renderer's accumulated opacity leaves a ray less than `stop_transmittance` of its
  light, its later samples are not evaluated (their blending weights could add at most that).

With `chunk` (the default), each level is one compiled program: the samples that remain in a
segment are gathered into a buffer evaluated in chunks of `chunk` points, the chunks past the
last live sample skipped on the device (`mixnerf_eqx._nn.budget`), and scattered back, so a
render compiles once and never waits for the host between segments. With `chunk = None` the
buffer's size is decided on the host: the count rounded up to a quarter of its power of two
(at most 25% padding, a compilation per size).

Because the samplers, the field and the renderer are the model's own, replacing any of them
(`eqx.tree_at`) changes both renders alike: with no grid and `stop_transmittance = 0` the
result equals the dense render.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._nn.budget import evaluate_live
from .._nn.field import FieldOutputs
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle, RaySamples
from .._nn.renderer import LevelOutputs
from .occupancy import OccupancyGrid


class Skipping(eqx.Module):
    """What the skipping render may skip.

    **Fields:**

    - `grid`: the occupancy grid, or `None` to evaluate empty space too.
    - `stop_transmittance` (static): stop a ray once its transmittance falls below this
      (0: never).
    - `segments` (static): pieces of each level between which finished rays are dropped.
    - `min_bucket` (static): the smallest buffer of gathered samples.
    - `chunk` (static): a number of points: every level is one compiled program evaluating
      chunks of that many points (the default); `None`: buffers sized on the host, a
      compilation per size and a wait for the host between segments.
    """

    grid: OccupancyGrid | None = None
    stop_transmittance: float = eqx.field(static=True, default=1e-4)
    segments: int = eqx.field(static=True, default=4)
    min_bucket: int = eqx.field(static=True, default=1024)
    chunk: int | None = eqx.field(static=True, default=4096)

    def __check_init__(self):
        if not 0 <= self.stop_transmittance < 1:
            raise ValueError(f"stop_transmittance must lie in [0, 1), got {self.stop_transmittance}")
        if self.segments < 1 or self.min_bucket < 1:
            raise ValueError("segments and min_bucket must be positive")
        if self.chunk is not None and self.chunk < 1:
            raise ValueError(f"chunk must be a positive number of points, got {self.chunk}")


@dataclasses.dataclass(frozen=True)
class RenderCounts:
    """Ray and field-evaluation counts of one or more renders; counts add with `+`.

    **Fields:**

    - `rays`: rays rendered (padding excluded).
    - `dense_evaluations`: field evaluations the dense render makes for them.
    - `field_evaluations`: samples actually needed (not skipped).
    - `padded_evaluations`: field evaluations made, including the buffers' padding.
    """

    rays: int = 0
    dense_evaluations: int = 0
    field_evaluations: int = 0
    padded_evaluations: int = 0

    def __add__(self, other: "RenderCounts") -> "RenderCounts":
        return RenderCounts(
            *(a + b for a, b in zip(dataclasses.astuple(self), dataclasses.astuple(other), strict=True))
        )

    @property
    def reduction(self) -> float:
        """Dense evaluations per evaluation made (padding included)."""
        return self.dense_evaluations / max(self.padded_evaluations, 1)


def _bucket(count: int, minimum: int, maximum: int) -> int:
    """`count` rounded up to a quarter of its power of two: at most 25% padding, and only
    four buffer sizes (so four compilations) per doubling of the count."""
    count = max(count, minimum)
    step = max(1, (1 << (count.bit_length() - 1)) // 4)
    return min(maximum, -(-count // step) * step)


@eqx.filter_jit
def _sample_coarse(model: MixNeRF, rays: RayBundle) -> RaySamples:
    return model.sample_coarse(rays)


@eqx.filter_jit
def _sample_fine(model: MixNeRF, rays: RayBundle, coarse: LevelOutputs) -> RaySamples:
    return model.sample_fine(rays, coarse)


@eqx.filter_jit
def _composite(model: MixNeRF, outputs: FieldOutputs, samples: RaySamples, rays: RayBundle) -> LevelOutputs:
    return model.composite(outputs, samples, rays)


@eqx.filter_jit
def _occupied(
    grid: OccupancyGrid | None, means: Float[Array, "batch num_samples 3"], valid: Bool[Array, " batch"]
) -> Bool[Array, "batch num_samples"]:
    if grid is None:
        return jnp.broadcast_to(valid[:, None], means.shape[:2])
    return grid.occupied(means, grid.mask()) & valid[:, None]


@eqx.filter_jit
def _live_samples(
    occupied: Bool[Array, "batch num_samples"], alive: Bool[Array, " batch"], lo: int, hi: int
) -> tuple[Bool[Array, "batch segment"], Array]:
    """The samples of `[lo, hi)` to evaluate, and how many there are."""
    live = occupied[:, lo:hi] & alive[:, None]
    return live, jnp.sum(live)


def _segments(num_samples: int, segments: int) -> list[tuple[int, int]]:
    """The `[lo, hi)` sample ranges a level is evaluated in, front to back: `segments` of them
    (at most one per sample), as even as whole samples allow."""
    bounds = np.linspace(0, num_samples, min(segments, num_samples) + 1).round().astype(int).tolist()
    return list(zip(bounds[:-1], bounds[1:], strict=True))


@eqx.filter_jit
def _still_lit(
    model: MixNeRF, outputs: FieldOutputs, samples: RaySamples, rays: RayBundle, stop_transmittance: float
) -> Bool[Array, " batch"]:
    """Rays whose transmittance, with the samples not yet evaluated at zero density, is at
    least `stop_transmittance`: the renderer's own opacity `acc` is `1 - transmittance`."""
    return 1.0 - model.composite(outputs, samples, rays).acc >= stop_transmittance


@eqx.filter_jit
def _evaluate_segment(
    model: MixNeRF,
    outputs: FieldOutputs,
    samples: RaySamples,
    rays: RayBundle,
    live: Bool[Array, "batch segment"],
    lo: int,
    capacity: int,
) -> FieldOutputs:
    """The field at the live samples of `[lo, lo + segment)` written into `outputs`."""
    num_rays, length = live.shape
    flat = live.reshape(-1)
    (index,) = jnp.nonzero(flat, size=capacity, fill_value=flat.size)
    safe = jnp.minimum(index, flat.size - 1)
    ray_index, sample_index = safe // length, lo + safe % length
    evaluated = model.query_points(
        samples.means[ray_index, sample_index],
        samples.covs[ray_index, sample_index],
        rays.viewdirs[ray_index],
    )

    def scatter(full, values):
        zeros = jnp.zeros((flat.size, *values.shape[1:]), values.dtype)
        piece = zeros.at[index].set(values, mode="drop").reshape(num_rays, length, *values.shape[1:])
        return full.at[:, lo : lo + length].set(piece)

    return jax.tree_util.tree_map(scatter, outputs, evaluated)


def _unevaluated(model: MixNeRF, samples: RaySamples, rays: RayBundle) -> FieldOutputs:
    """Zeros shaped like the field's outputs at every sample: density zero adds nothing."""
    shapes = jax.eval_shape(model.query_field, samples, rays)
    return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def _render_level(
    model: MixNeRF, rays: RayBundle, samples: RaySamples, valid: Bool[Array, " batch"], skipping: Skipping
) -> tuple[LevelOutputs, RenderCounts]:
    num_rays, num_samples = samples.means.shape[:2]
    occupied = _occupied(skipping.grid, samples.means, valid)
    outputs = _unevaluated(model, samples, rays)
    alive = jnp.ones((num_rays,), bool)
    needed = made = 0
    for lo, hi in _segments(num_samples, skipping.segments):
        if lo > 0 and skipping.stop_transmittance > 0:
            alive = _still_lit(model, outputs, samples, rays, skipping.stop_transmittance)
        live, count = _live_samples(occupied, alive, lo, hi)
        count = int(count)
        if count == 0:
            continue
        capacity = _bucket(count, skipping.min_bucket, num_rays * (hi - lo))
        outputs = _evaluate_segment(model, outputs, samples, rays, live, lo, capacity)
        needed, made = needed + count, made + capacity
    counts = RenderCounts(field_evaluations=needed, padded_evaluations=made)
    return _composite(model, outputs, samples, rays), counts


@eqx.filter_jit
def _render_level_chunked(
    model: MixNeRF, rays: RayBundle, samples: RaySamples, valid: Bool[Array, " batch"], skipping: Skipping
) -> tuple[LevelOutputs, Int[Array, ""], Int[Array, ""]]:
    """`_render_level` as one program (`Skipping.chunk`): the level's outputs, the samples
    needed and the field evaluations made."""
    assert skipping.chunk is not None
    num_rays, num_samples = samples.means.shape[:2]
    occupied = _occupied(skipping.grid, samples.means, valid)
    outputs = _unevaluated(model, samples, rays)
    alive = jnp.ones((num_rays,), bool)
    needed = made = jnp.zeros((), jnp.int32)
    for lo, hi in _segments(num_samples, skipping.segments):
        if lo > 0 and skipping.stop_transmittance > 0:
            alive = _still_lit(model, outputs, samples, rays, skipping.stop_transmittance)
        live = occupied[:, lo:hi] & alive[:, None]
        part, _, part_made = evaluate_live(
            model.query_points,
            samples.means[:, lo:hi],
            samples.covs[:, lo:hi],
            rays.viewdirs,
            None,
            live,
            num_rays * (hi - lo),
            with_mixture_heads=model.field.has_mixture_heads,
            chunk=skipping.chunk,
        )
        outputs = jax.tree_util.tree_map(lambda full, values: full.at[:, lo:hi].set(values), outputs, part)
        needed, made = needed + jnp.sum(live), made + part_made
    return model.composite(outputs, samples, rays), needed, made


def render_skipping(
    model: MixNeRF, rays: RayBundle, valid: Bool[Array, " batch"], skipping: Skipping
) -> tuple[LevelOutputs, RenderCounts]:
    """Renders a flat batch of rays deterministically with skipping.

    **Arguments:**

    - `model`: the model; its samplers, field and renderer do the work.
    - `rays`: a flat batch of rays.
    - `valid`: the real rays (padding rays are never evaluated).
    - `skipping`: what may be skipped.

    **Returns:**

    `(fine level, counts)`.
    """
    real = int(jnp.sum(valid))
    if skipping.chunk is not None:
        fine, needed, made = _render_chunked(model, rays, valid, skipping)
        counts = RenderCounts(
            rays=real,
            dense_evaluations=real * model.samples_per_ray,
            field_evaluations=int(needed),
            padded_evaluations=int(made),
        )
        return fine, counts
    coarse_samples = _sample_coarse(model, rays)
    coarse, coarse_counts = _render_level(model, rays, coarse_samples, valid, skipping)
    fine_samples = _sample_fine(model, rays, coarse)
    fine, fine_counts = _render_level(model, rays, fine_samples, valid, skipping)
    totals = RenderCounts(rays=real, dense_evaluations=real * model.samples_per_ray)
    return fine, totals + coarse_counts + fine_counts


@eqx.filter_jit
def _render_chunked(
    model: MixNeRF, rays: RayBundle, valid: Bool[Array, " batch"], skipping: Skipping
) -> tuple[LevelOutputs, Int[Array, ""], Int[Array, ""]]:
    """Both levels of `render_skipping` in one program (`Skipping.chunk`)."""
    coarse_samples = model.sample_coarse(rays)
    coarse, coarse_needed, coarse_made = _render_level_chunked(model, rays, coarse_samples, valid, skipping)
    fine_samples = model.sample_fine(rays, coarse)
    fine, fine_needed, fine_made = _render_level_chunked(model, rays, fine_samples, valid, skipping)
    return fine, coarse_needed + fine_needed, coarse_made + fine_made
