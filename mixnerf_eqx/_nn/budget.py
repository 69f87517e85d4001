"""Training renders that evaluate the field only where a ray can still change.

A dense training step evaluates the field at every sample of every ray. With a
`SampleBudget` the model's training render evaluates, per level, at most a fixed number of
samples of the whole batch (a static share of the dense count, so the step compiles once),
chosen among the *live* samples:

- a sample is dead where an occupancy test (`AbstractOccupancy`, e.g. the occupancy grid kept
  during training) marks its point empty;
- a fine sample is also dead once the coarse level says its ray is finished: the coarse
  transmittance in front of it is below `stop_transmittance` (the light it could still add).

Live samples are gathered into the buffer in sample-major order (every ray's first sample,
then every ray's second, ...), so that when a batch has more live samples than the buffer,
the farthest samples of every ray are dropped first rather than whole rays; their number is
returned (`dropped`). Unevaluated samples get zero density, so their blending weights and
mixing coefficients are zero: the colour and depth mixtures are MixNeRF's, over the samples a
ray keeps, with the same NLLs. With every sample live and a buffer of every sample, the
render equals the dense one.

`evaluate_live` can instead hold every sample and evaluate the buffer in chunks (`chunk`
points each, `jax.lax.scan`), a chunk past the last live sample skipped (`jax.lax.cond`): the
work follows the live count and one program serves every count. The skipping render uses it
(forward only); training keeps fixed buffers, whose backward pass is one gather and one
scatter rather than a loop of branches.
"""

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, Key, UInt32

from .field import FieldOutputs

__all__ = ["AbstractOccupancy", "SampleBudget", "budget_capacity", "evaluate_live", "transmittance_before"]


class AbstractOccupancy(eqx.Module):
    """Says which points may hold density (the rest is skipped)."""

    @abc.abstractmethod
    def occupied(self, points: Float[Array, "*batch 3"]) -> Bool[Array, "*batch"]:
        """Whether each point may hold density."""


class SampleBudget(eqx.Module):
    """What a training render may leave unevaluated.

    **Fields:**

    - `occupancy`: the occupancy test, or `None` (no sample is empty).
    - `coarse_fraction`, `fine_fraction` (static): the share of each level's samples the
      buffer holds (1: every sample).
    - `stop_transmittance` (static): a fine sample is dead where the coarse transmittance in
      front of it is below this (0: never).
    """

    occupancy: AbstractOccupancy | None = None
    coarse_fraction: float = eqx.field(static=True, default=1.0)
    fine_fraction: float = eqx.field(static=True, default=1.0)
    stop_transmittance: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        for name in ("coarse_fraction", "fine_fraction"):
            value = getattr(self, name)
            if not 0 < value <= 1:
                raise ValueError(f"{name} must lie in (0, 1], got {value}")
        if not 0 <= self.stop_transmittance < 1:
            raise ValueError(f"stop_transmittance must lie in [0, 1), got {self.stop_transmittance}")

    def live(self, means: Float[Array, "batch num_samples 3"]) -> Bool[Array, "batch num_samples"]:
        """The samples the occupancy test keeps."""
        if self.occupancy is None:
            return jnp.ones(means.shape[:2], bool)
        return self.occupancy.occupied(means)


def budget_capacity(fraction: float, num_rays: int, num_samples: int) -> int:
    """The buffer's size: `fraction` of the level's samples, rounded up, at least one."""
    total = num_rays * num_samples
    return max(1, min(total, math.ceil(fraction * total - 1e-9)))


def transmittance_before(
    coarse_edges: Float[Array, "batch num_prev_edges"],
    weights: Float[Array, "batch num_prev_edges-1"],
    t: Float[Array, "batch num_samples"],
) -> Float[Array, "batch num_samples"]:
    """The coarse level's transmittance in front of the coarse interval holding each `t`:
    `1 - sum` of the weights of the intervals before it (1 before the first, the light past
    the last interval after it)."""
    before = jnp.concatenate([jnp.zeros_like(weights[:, :1]), jnp.cumsum(weights, axis=-1)], axis=-1)
    index = jax.vmap(lambda edges, points: jnp.searchsorted(edges, points, side="right") - 1)(coarse_edges, t)
    index = jnp.clip(index, 0, weights.shape[-1])
    return 1.0 - jnp.take_along_axis(before, index, axis=-1)


def evaluate_live(
    query_points,
    means: Float[Array, "batch num_samples 3"],
    covs: Float[Array, "batch num_samples 3"],
    viewdirs: Float[Array, "batch 3"],
    point_keys: Key[Array, " points"] | UInt32[Array, "points 2"] | None,
    live: Bool[Array, "batch num_samples"],
    capacity: int,
    *,
    with_mixture_heads: bool,
    chunk: int | None = None,
) -> tuple[FieldOutputs, Int[Array, ""], Int[Array, ""]]:
    """The field at (at most `capacity` of) the live samples, the others unevaluated.

    `query_points(means, covs, viewdirs, keys)` evaluates a flat list of points; `point_keys`
    holds one key per sample in ray-major order (as the dense render's), or is `None`. With
    `chunk`, the buffer is evaluated in chunks of that many points and the chunks past the
    last live sample are skipped (module docstring).

    Returns the outputs at every sample (unevaluated: density, colour and ray depth 0, scales
    1), how many live samples did not fit, and how many points the field was evaluated at.
    """
    num_rays, num_samples = live.shape
    total = num_rays * num_samples
    if capacity >= total and chunk is None:
        # A buffer of every sample: the dense evaluation, in the dense order, masked.
        dense = query_points(
            means.reshape(total, 3),
            covs.reshape(total, 3),
            jnp.repeat(viewdirs, num_samples, axis=0),
            point_keys,
        )
        mask = live.reshape(total)

        def masked(values: Array, fill: float) -> Array:
            kept = jnp.where(mask.reshape(-1, *([1] * (values.ndim - 1))), values, fill)
            return kept.reshape(num_rays, num_samples, *values.shape[1:])

        outputs = FieldOutputs(
            density=masked(dense.density, 0.0),
            rgb=masked(dense.rgb, 0.0),
            beta=masked(dense.beta, 1.0) if with_mixture_heads else None,
            ray_depth=masked(dense.ray_depth, 0.0) if with_mixture_heads else None,
        )
        return outputs, jnp.zeros((), jnp.int32), jnp.asarray(total, jnp.int32)
    if chunk is not None:
        if capacity < total:
            raise ValueError("a chunked buffer holds every sample: capacity must be the samples' count")
        chunk = min(chunk, total)
    size = capacity if chunk is None else chunk * math.ceil(min(capacity, total) / chunk)
    # Sample-major positions: position p is sample p // num_rays of ray p % num_rays.
    order = live.T.reshape(-1)
    (position,) = jnp.nonzero(order, size=size, fill_value=total)
    safe = jnp.minimum(position, total - 1)
    ray_index, sample_index = safe % num_rays, safe // num_rays
    flat_index = jnp.where(position < total, ray_index * num_samples + sample_index, total)
    keys = None if point_keys is None else point_keys[ray_index * num_samples + sample_index]
    points = (means[ray_index, sample_index], covs[ray_index, sample_index], viewdirs[ray_index], keys)
    kept = jnp.minimum(jnp.sum(live), capacity).astype(jnp.int32)
    if chunk is None:
        evaluated = query_points(*points)
        made = jnp.asarray(size, jnp.int32)
    else:
        evaluated = _chunked(query_points, points, kept, chunk)
        made = (chunk * ((kept + chunk - 1) // chunk)).astype(jnp.int32)

    def scatter(values: Array, fill: float) -> Array:
        full = jnp.full((total, *values.shape[1:]), fill, values.dtype)
        return full.at[flat_index].set(values, mode="drop").reshape(num_rays, num_samples, *values.shape[1:])

    outputs = FieldOutputs(
        density=scatter(evaluated.density, 0.0),
        rgb=scatter(evaluated.rgb, 0.0),
        beta=scatter(evaluated.beta, 1.0) if with_mixture_heads else None,
        ray_depth=scatter(evaluated.ray_depth, 0.0) if with_mixture_heads else None,
    )
    dropped = jnp.maximum(jnp.sum(live) - capacity, 0)
    return outputs, dropped, made


def _chunked(query_points, points: tuple, kept: Int[Array, ""], chunk: int) -> FieldOutputs:
    """`query_points(*points)` over the first `kept` of the points, in chunks of `chunk`: a
    chunk wholly past `kept` is not evaluated (zeros, which the caller's scatter drops)."""
    size = points[0].shape[0]
    num_chunks = size // chunk
    split = jax.tree_util.tree_map(lambda x: x.reshape(num_chunks, chunk, *x.shape[1:]), points)
    shapes = jax.eval_shape(query_points, *jax.tree_util.tree_map(lambda x: x[0], split))

    def skipped(*_):
        return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

    def body(carry, inputs):
        index, piece = inputs
        return carry, jax.lax.cond(index * chunk < kept, lambda p: query_points(*p), skipped, piece)

    _, outputs = jax.lax.scan(body, None, (jnp.arange(num_chunks), split))
    return jax.tree_util.tree_map(lambda x: x.reshape(size, *x.shape[2:]), outputs)
