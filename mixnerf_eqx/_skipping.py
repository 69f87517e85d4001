"""Rendering that skips empty space and finished rays.

The dense renderer evaluates the field at every sample of every ray. This one evaluates it
only where it can matter:

- empty space: samples in cells that an `OccupancyGrid` marks empty get density zero without
  a field evaluation;
- finished rays: each level is evaluated in `segments` pieces along the ray, front to back;
  once a ray's transmittance falls below `stop_transmittance`, its later samples are not
  evaluated (their blending weights could add at most that much).

The samples that remain are gathered into a buffer whose size is their count rounded up to a
quarter of its power of two (at most 25% padding, and a few sizes, each compiled once),
evaluated, and scattered back; skipped samples have density zero, so they add nothing to
the compositing. Both levels use the same
samplers and renderer as the model, so with no grid and `stop_transmittance = 0` the result
equals the dense render.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._field import FieldOutputs
from ._model import MixNeRF
from ._occupancy import OccupancyGrid
from ._rays import RayBundle, RaySamples
from ._renderer import LevelOutputs


@dataclasses.dataclass(frozen=True)
class Skipping:
    """What the skipping renderer may skip.

    **Fields:**

    - `grid`: the occupancy grid, or `None` to evaluate empty space too.
    - `stop_transmittance`: stop a ray once its transmittance falls below this (0: never).
    - `segments`: pieces of each level between which finished rays are dropped.
    - `min_bucket`: the smallest buffer of gathered samples.
    """

    grid: OccupancyGrid | None = None
    stop_transmittance: float = 1e-4
    segments: int = 4
    min_bucket: int = 1024

    def __post_init__(self):
        if not 0 <= self.stop_transmittance < 1:
            raise ValueError(f"stop_transmittance must lie in [0, 1), got {self.stop_transmittance}")
        if self.segments < 1 or self.min_bucket < 1:
            raise ValueError("segments and min_bucket must be positive")


@dataclasses.dataclass
class RenderStats:
    """Counts accumulated over the rays of one or more renders.

    **Fields:**

    - `rays`: rays rendered (padding excluded).
    - `dense_evaluations`: field evaluations the dense renderer makes for them.
    - `field_evaluations`: samples actually needed (not skipped).
    - `padded_evaluations`: field evaluations made, including the buffers' padding.
    """

    rays: int = 0
    dense_evaluations: int = 0
    field_evaluations: int = 0
    padded_evaluations: int = 0

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
def _coarse_samples(model: MixNeRF, rays: RayBundle) -> RaySamples:
    return jax.vmap(lambda ray: model.coarse_sampler(ray))(rays)


@eqx.filter_jit
def _fine_samples(model: MixNeRF, rays: RayBundle, coarse: LevelOutputs) -> RaySamples:
    return jax.vmap(lambda ray, edges, weights: model.fine_sampler(ray, edges, weights))(
        rays, coarse.t_edges, coarse.weights
    )


@eqx.filter_jit
def _occupied(
    grid: OccupancyGrid | None, means: Float[Array, "rays num_samples 3"], valid: Bool[Array, " rays"]
) -> Bool[Array, "rays num_samples"]:
    if grid is None:
        return jnp.broadcast_to(valid[:, None], means.shape[:2])
    return grid.occupied(means, grid.mask()) & valid[:, None]


@eqx.filter_jit
def _live_samples(
    occupied: Bool[Array, "rays num_samples"],
    optical_depth: Float[Array, " rays"],
    max_optical_depth: float,
    lo: int,
    hi: int,
):
    """The samples of `[lo, hi)` to evaluate, and how many there are."""
    alive = optical_depth <= max_optical_depth
    live = occupied[:, lo:hi] & alive[:, None]
    return live, jnp.sum(live)


@eqx.filter_jit
def _evaluate_segment(
    model: MixNeRF,
    outputs: FieldOutputs,
    optical_depth: Float[Array, " rays"],
    samples: RaySamples,
    rays: RayBundle,
    live: Bool[Array, "rays segment"],
    lo: int,
    hi: int,
    capacity: int,
):
    """Evaluates the field at the live samples of `[lo, hi)`; the others get density zero."""
    num_rays, length = live.shape
    flat = live.reshape(-1)
    (index,) = jnp.nonzero(flat, size=capacity, fill_value=flat.size)
    safe = jnp.minimum(index, flat.size - 1)
    ray_index, sample_index = safe // length, lo + safe % length
    evaluated = jax.vmap(lambda m, c, v: model.field(m, c, v))(
        samples.means[ray_index, sample_index],
        samples.covs[ray_index, sample_index],
        rays.viewdirs[ray_index],
    )

    def scatter(full, values):
        if full is None:
            return None
        zeros = jnp.zeros((flat.size, *values.shape[1:]), values.dtype)
        piece = zeros.at[index].set(values, mode="drop").reshape(num_rays, length, *values.shape[1:])
        return full.at[:, lo:hi].set(piece)

    outputs = FieldOutputs(
        density=scatter(outputs.density, evaluated.density),
        rgb=scatter(outputs.rgb, evaluated.rgb),
        beta=None if outputs.beta is None else scatter(outputs.beta, evaluated.beta),
        ray_depth=None if outputs.ray_depth is None else scatter(outputs.ray_depth, evaluated.ray_depth),
    )
    deltas = (samples.t_edges[:, lo + 1 : hi + 1] - samples.t_edges[:, lo:hi]) * jnp.linalg.norm(
        rays.directions, axis=-1, keepdims=True
    )
    optical_depth = optical_depth + jnp.sum(outputs.density[:, lo:hi] * deltas, axis=-1)
    return outputs, optical_depth


@eqx.filter_jit
def _composite(model: MixNeRF, outputs: FieldOutputs, samples: RaySamples, rays: RayBundle) -> LevelOutputs:
    return jax.vmap(model.renderer)(outputs, samples.t_edges, rays)


def _empty_outputs(model: MixNeRF, num_rays: int, num_samples: int) -> FieldOutputs:
    def zeros(*shape):
        return jnp.zeros((num_rays, num_samples, *shape), jnp.float32)

    mixture = model.field.has_mixture_heads
    return FieldOutputs(
        density=zeros(),
        rgb=zeros(3),
        beta=zeros(3) if mixture else None,
        ray_depth=zeros() if mixture else None,
    )


def _render_level(
    model: MixNeRF,
    rays: RayBundle,
    samples: RaySamples,
    valid: Bool[Array, " rays"],
    skipping: Skipping,
    stats: RenderStats,
) -> LevelOutputs:
    num_rays, num_samples = samples.means.shape[:2]
    occupied = _occupied(skipping.grid, samples.means, valid)
    outputs = _empty_outputs(model, num_rays, num_samples)
    optical_depth = jnp.zeros((num_rays,), jnp.float32)
    stop = skipping.stop_transmittance
    max_optical_depth = -math.log(stop) if stop > 0 else math.inf
    bounds = np.linspace(0, num_samples, min(skipping.segments, num_samples) + 1).round().astype(int)
    for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
        live, count = _live_samples(occupied, optical_depth, max_optical_depth, lo, hi)
        count = int(count)
        if count == 0:
            continue
        capacity = _bucket(count, skipping.min_bucket, num_rays * (hi - lo))
        outputs, optical_depth = _evaluate_segment(
            model, outputs, optical_depth, samples, rays, live, lo, hi, capacity
        )
        stats.field_evaluations += count
        stats.padded_evaluations += capacity
    return _composite(model, outputs, samples, rays)


def render_chunk_skipping(
    model: MixNeRF, rays: RayBundle, valid: Bool[Array, " rays"], skipping: Skipping, stats: RenderStats
) -> LevelOutputs:
    """Renders a flat batch of rays deterministically with skipping; returns the fine level.

    `valid` marks the real rays (padding rays are never evaluated); `stats` is updated.
    """
    coarse_samples = _coarse_samples(model, rays)
    coarse = _render_level(model, rays, coarse_samples, valid, skipping, stats)
    fine_samples = _fine_samples(model, rays, coarse)
    fine = _render_level(model, rays, fine_samples, valid, skipping, stats)
    real = int(jnp.sum(valid))
    stats.rays += real
    stats.dense_evaluations += real * (coarse_samples.means.shape[1] + fine_samples.means.shape[1])
    return fine
