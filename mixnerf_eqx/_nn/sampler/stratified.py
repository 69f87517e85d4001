"""The coarse level's sampler: stratified (jittered in training) interval edges along each ray,
linear in distance or in disparity."""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._custom_types import PreviousEdges, PreviousWeights, PRNGKey, SampledEdges
from ..rays import RayBundle
from .base import AbstractSampler


class StratifiedSampler(AbstractSampler):
    """Evenly spaced intervals between the ray's near and far bounds, jittered in training.

    **Fields:**

    - `num_samples`: samples per ray.
    - `frustum`: `"cone"` or `"cylinder"`.
    - `lindisp`: space the edges linearly in disparity instead of depth.
    """

    num_samples: int = eqx.field(static=True)
    frustum: Literal["cone", "cylinder"] = eqx.field(static=True, default="cone")
    lindisp: bool = eqx.field(static=True, default=False)

    def sample_edges(
        self,
        ray: RayBundle,
        previous_edges: PreviousEdges | None,
        previous_weights: PreviousWeights | None,
        *,
        key: PRNGKey | None,
    ) -> SampledEdges:
        del previous_edges, previous_weights
        near, far = ray.near[0], ray.far[0]
        fractions = jnp.linspace(0.0, 1.0, self.num_samples + 1, dtype=ray.near.dtype)
        if self.lindisp:
            t_edges = 1 / (1 / near * (1 - fractions) + 1 / far * fractions)
        else:
            t_edges = near * (1 - fractions) + far * fractions
        if key is not None:
            # Jitter every edge within the half-intervals around it (mip-NeRF).
            mids = 0.5 * (t_edges[1:] + t_edges[:-1])
            upper = jnp.concatenate([mids, t_edges[-1:]])
            lower = jnp.concatenate([t_edges[:1], mids])
            jitter = jax.random.uniform(key, t_edges.shape, t_edges.dtype)
            t_edges = lower + (upper - lower) * jitter
        return t_edges
