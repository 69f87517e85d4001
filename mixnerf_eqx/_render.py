"""Pure volume-rendering math for one ray (paper eq. 2 and eq. 8).

Everything here is a function of arrays: Modules hold parameters and call these.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._custom_types import RGB, Edges, PerSample, PerSampleRGB


def blend_weights(
    density: PerSample, t_edges: Edges, step_scale: Float[Array, ""] | PerSample
) -> PerSample:
    """Alpha-compositing weights `w_i = T_i (1 - exp(-sigma_i delta_i))`.

    **Arguments:**

    - `density`: `sigma_i`, non-negative.
    - `t_edges`: interval edges along the unnormalised direction.
    - `step_scale`: the length of one unit of `t`: `||d||` for the ordinary weights (eq. 2),
      or the per-sample predicted ray depth `mu_d` for the regenerated weights (eq. 8).

    **Returns:**

    The weights, which sum to at most one.
    """
    deltas = (t_edges[1:] - t_edges[:-1]) * step_scale
    density_delta = density * deltas
    alpha = -jnp.expm1(-density_delta)
    # Transmittance before sample i: exp of minus the optical depth of samples 0..i-1.
    optical_depth = jnp.concatenate([jnp.zeros((1,), density_delta.dtype), jnp.cumsum(density_delta[:-1])])
    return alpha * jnp.exp(-optical_depth)


def composite_rgb(
    weights: PerSample, rgb: PerSampleRGB, background: RGB | None = None
) -> RGB:
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
    total = jnp.sum(weights)
    safe_total = jnp.where(total > 0, total, 1.0)
    depth = jnp.where(total > 0, jnp.sum(weights * t_mids) / safe_total, t_edges[-1])
    return jnp.clip(depth, t_edges[0], t_edges[-1])
