"""The fine level's sampler: interval edges drawn from the coarse level's blending weights
(blurred and padded, as mip-NeRF resamples), by inverting their piecewise-constant CDF."""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..._custom_types import PreviousEdges, PreviousWeights, PRNGKey, SampledEdges
from ..rays import RayBundle
from .base import AbstractSampler


def sample_piecewise_constant(
    bins: Float[Array, "num_edges"],
    weights: Float[Array, "num_edges-1"],
    num_draws: int,
    *,
    key: PRNGKey | None,
) -> Float[Array, "num_draws"]:
    """Inverse-transform samples of the piecewise-constant density with `weights` on `bins`.

    Draws are stratified (one per `1/num_draws` of probability, jittered when a `key` is
    given, evenly spaced otherwise), so the result is sorted.

    As in the released code, `eps` is float32's machine epsilon: weights whose sum is below
    it are padded up to it (so that a ray whose weights vanish falls back to a uniform
    density, and the padding changes nothing otherwise), and the draws span `[0, 1 - eps]`.
    """
    eps = float(jnp.finfo(jnp.float32).eps)
    num_bins = weights.shape[0]
    total = jnp.sum(weights)
    padding = jnp.maximum(0.0, eps - total)
    weights = weights + padding / num_bins
    pdf = weights / (total + padding)
    cdf = jnp.minimum(1.0, jnp.cumsum(pdf[:-1]))
    cdf = jnp.concatenate([jnp.zeros((1,), cdf.dtype), cdf, jnp.ones((1,), cdf.dtype)])
    if key is None:
        u = jnp.linspace(0.0, 1.0 - eps, num_draws, dtype=bins.dtype)
    else:
        stride = 1.0 / num_draws
        jitter = jax.random.uniform(key, (num_draws,), bins.dtype, maxval=stride - eps)
        u = jnp.arange(num_draws, dtype=bins.dtype) * stride + jitter
    upper = jnp.clip(jnp.searchsorted(cdf, u, side="right"), 1, num_bins)
    lower = upper - 1
    cdf_lo, cdf_hi = cdf[lower], cdf[upper]
    span = cdf_hi - cdf_lo
    # A bin whose probability is below sqrt(tiny) (~1e-19 in float32) counts as empty: the
    # derivative of `(u - cdf_lo) / span` holds `span^-2`, which overflows for such bins and
    # turns into `0 * inf = NaN` in the weights' gradient. Its draws land on its left edge,
    # which moves the sample's CDF value by less than the bin's own probability.
    has_mass = span > jnp.sqrt(jnp.finfo(span.dtype).tiny)
    fraction = jnp.where(has_mass, (u - cdf_lo) / jnp.where(has_mass, span, 1.0), 0.0)
    fraction = jnp.clip(fraction, 0.0, 1.0)
    return bins[lower] + fraction * (bins[upper] - bins[lower])


def blur_weights(weights: Float[Array, "num_samples"], padding: float) -> Float[Array, "num_samples"]:
    """mip-NeRF's 2-tap max followed by a 2-tap average, plus a constant padding."""
    padded = jnp.concatenate([weights[:1], weights, weights[-1:]])
    maxed = jnp.maximum(padded[:-1], padded[1:])
    return 0.5 * (maxed[:-1] + maxed[1:]) + padding


class HierarchicalSampler(AbstractSampler):
    """mip-NeRF's resampler: new edges drawn from the previous level's blurred weights.

    **Fields:**

    - `num_samples`: samples per ray at this level.
    - `frustum`: `"cone"` or `"cylinder"`.
    - `resample_padding`: constant added to the blurred weights (mip-NeRF: 0.01).
    - `stop_gradient`: stop gradients through the new edges (as mip-NeRF does).
    """

    num_samples: int = eqx.field(static=True)
    frustum: Literal["cone", "cylinder"] = eqx.field(static=True, default="cone")
    resample_padding: float = eqx.field(static=True, default=0.01)
    stop_gradient: bool = eqx.field(static=True, default=True)

    def sample_edges(
        self,
        ray: RayBundle,
        previous_edges: PreviousEdges | None,
        previous_weights: PreviousWeights | None,
        *,
        key: PRNGKey | None,
    ) -> SampledEdges:
        if previous_edges is None or previous_weights is None:
            raise ValueError("HierarchicalSampler needs the previous level's edges and weights")
        weights = blur_weights(previous_weights, self.resample_padding)
        t_edges = sample_piecewise_constant(previous_edges, weights, self.num_samples + 1, key=key)
        return jax.lax.stop_gradient(t_edges) if self.stop_gradient else t_edges
