"""Pure volume-rendering math for one ray (paper eq. 2 and eq. 8).

Everything here is a function of arrays: Modules hold parameters and call these.
"""

import warnings

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._custom_types import RGB, Edges, PerSample, PerSampleRGB, ScalarLike


def log_transmittance(
    density: PerSample, t_edges: Edges, step_scale: Float[Array, ""] | PerSample
) -> Float[Array, ""]:
    """`log T = -sum_i sigma_i delta_i`: the log of the light that passes every sample of
    `blend_weights(density, t_edges, step_scale)`, exact where `1 - sum_i w_i` has lost every
    digit (an optical depth above about 16 in float32)."""
    deltas = jnp.maximum(t_edges[1:] - t_edges[:-1], 0.0) * step_scale
    return -jnp.sum(density * deltas)


def blend_weights(density: PerSample, t_edges: Edges, step_scale: Float[Array, ""] | PerSample) -> PerSample:
    """Alpha-compositing weights `w_i = T_i (1 - exp(-sigma_i delta_i))`.

    **Arguments:**

    - `density`: `sigma_i`, non-negative.
    - `t_edges`: interval edges along the unnormalised direction.
    - `step_scale`: the length of one unit of `t`: `||d||` for the ordinary weights (eq. 2),
      or the per-sample predicted ray depth `mu_d` for the regenerated weights (eq. 8).

    **Returns:**

    The weights, which sum to at most one.
    """
    # Edges out of order by a rounding (a ray whose near and far bounds are equal or nearly so)
    # are an interval of no length, not a negative weight.
    deltas = jnp.maximum(t_edges[1:] - t_edges[:-1], 0.0) * step_scale
    density_delta = density * deltas
    alpha = -jnp.expm1(-density_delta)
    # Transmittance before sample i: exp of minus the optical depth of samples 0..i-1.
    optical_depth = jnp.concatenate([jnp.zeros((1,), density_delta.dtype), jnp.cumsum(density_delta[:-1])])
    return alpha * jnp.exp(-optical_depth)


def composite_rgb(weights: PerSample, rgb: PerSampleRGB, background: RGB | None = None) -> RGB:
    """The expected colour `sum_i w_i c_i`, plus `(1 - sum_i w_i)` of the background."""
    colour = jnp.sum(weights[:, None] * rgb, axis=0)
    if background is not None:
        colour = colour + (1 - jnp.sum(weights)) * background
    return colour


def accumulation(weights: PerSample) -> Float[Array, ""]:
    """The opacity of the ray, `sum_i w_i`."""
    return jnp.sum(weights)


def expected_depth(weights: PerSample, t_edges: Edges) -> Float[Array, ""]:
    """The weight-averaged interval midpoint, normalised by the opacity.

    As in mip-NeRF the result is clipped to `[t_edges[0], t_edges[-1]]`; a ray with zero
    opacity reports its far bound.
    """
    t_mids = 0.5 * (t_edges[1:] + t_edges[:-1])
    # The weighted mean is invariant to the weights' scale, so divide them by their largest
    # (held constant for the gradient) first. Dividing by a tiny opacity directly gives the
    # NaN `-x * total^-2 = -x * inf` in the backward pass for opacities below ~1e-19 in
    # float32. A ray whose largest weight is below the smallest normal float (whose true
    # gradient is then not representable) counts as empty.
    largest = jax.lax.stop_gradient(jnp.max(weights))
    non_empty = largest >= jnp.finfo(weights.dtype).tiny
    scaled = weights / jnp.where(non_empty, largest, 1.0)
    total = jnp.sum(scaled)
    safe_total = jnp.where(non_empty, total, 1.0)
    depth = jnp.where(non_empty, jnp.sum(scaled * t_mids) / safe_total, t_edges[-1])
    return jnp.clip(depth, t_edges[0], t_edges[-1])


def distortion(
    weights: PerSample, t_edges: Edges, near: Float[Array, ""], far: Float[Array, ""]
) -> Float[Array, ""]:
    """mip-NeRF 360's distortion loss of one ray, in `s = (t - near) / (far - near)`.

    `sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i)`, with `s_i` the interval
    midpoints. It is small when the weights gather in one short stretch of the ray, and it
    charges a semi-transparent haze spread along the ray. The double sum is computed in
    `O(num_samples)`: for sorted midpoints it is `2 sum_i w_i (s_i W_<i - (ws)_<i)`, with the
    exclusive prefix sums `W_<i = sum_{j<i} w_j` and `(ws)_<i = sum_{j<i} w_j s_j`.
    """
    s_edges = (t_edges - near) / (far - near)
    s_mids = 0.5 * (s_edges[1:] + s_edges[:-1])
    widths = s_edges[1:] - s_edges[:-1]
    weighted = weights * s_mids
    before = jnp.cumsum(weights) - weights
    weighted_before = jnp.cumsum(weighted) - weighted
    spread = 2.0 * jnp.sum(weights * (s_mids * before - weighted_before))
    return spread + jnp.sum(weights**2 * widths) / 3.0


def termination_cdf(t: Float[Array, ""], weights: PerSample, t_edges: Edges) -> Float[Array, ""]:
    """The probability that the ray terminates before `t`: interval `i` holds
    `w_i / sum_m w_m`, spread uniformly over it (a zero-width interval's mass counts from its
    edge on)."""
    total = jnp.sum(weights)
    masses = weights / jnp.where(total > 0, total, 1.0)
    widths = t_edges[1:] - t_edges[:-1]
    safe_widths = jnp.where(widths > 0, widths, 1.0)
    covered = jnp.where(widths > 0, jnp.clip((t - t_edges[:-1]) / safe_widths, 0.0, 1.0), t >= t_edges[:-1])
    return jnp.sum(masses * covered)


def termination_quantile(level: ScalarLike, weights: PerSample, t_edges: Edges) -> Float[Array, ""]:
    """The `level` quantile of where the ray terminates (0.5: the median depth).

    The termination distance has the piecewise-constant density of `termination_cdf`, so its
    distribution function is piecewise linear between the edges and the quantile is exact: the
    first interval whose cumulative mass reaches `level`, entered in proportion to the mass
    still needed (`inf {t : F(t) >= level}`; a zero-width interval answers its edge). A ray
    with zero opacity reports its far bound. `level` may be an array (under `jax.vmap`, many
    levels share one cumulative sum); it is not checked here (`depth_quantile` checks a
    number). Differentiable in the weights and edges (the interval found is held).
    """
    level = jnp.asarray(level, t_edges.dtype)
    # The distribution function at each interval's far edge, normalised by its own last value
    # so that it ends at exactly 1 (a normalised cumulative sum can end just below it, and a
    # level above that would land past the last interval with mass).
    cumulative = jnp.cumsum(weights)
    total = cumulative[-1]
    reached = cumulative / jnp.where(total > 0, total, 1.0)
    count = weights.shape[-1]
    index = jnp.minimum(jnp.searchsorted(reached, level, side="left"), count - 1)
    before = jnp.where(index > 0, reached[jnp.maximum(index - 1, 0)], 0.0)
    # The mass the search saw; zero only where a level of 0 meets leading intervals without
    # mass, answered at the first edge (F is 0 up to the first mass).
    mass = reached[index] - before
    fraction = jnp.where(mass > 0, jnp.clip((level - before) / jnp.where(mass > 0, mass, 1.0), 0.0, 1.0), 0.0)
    start, width = t_edges[index], t_edges[index + 1] - t_edges[index]
    return jnp.where(total > 0, start + fraction * width, t_edges[-1])


def depth_quantile(
    weights: PerSample, t_edges: Edges, quantile: ScalarLike = 0.5, *, tolerance: float | None = None
) -> Float[Array, ""]:
    """The `quantile` (a number in (0, 1)) of where the ray terminates: `termination_quantile`
    with its level checked. `tolerance` belonged to the former bisection: the quantile is now
    exact, and giving one warns (it goes in the next release)."""
    if tolerance is not None:
        warnings.warn(
            "depth_quantile's tolerance is no longer used (the quantile is exact); leave it out",
            FutureWarning,
            stacklevel=2,
        )
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must lie in (0, 1), got {quantile}")
    return termination_quantile(quantile, weights, t_edges)
