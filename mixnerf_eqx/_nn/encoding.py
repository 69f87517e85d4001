"""Positional encoding, and mip-NeRF's integrated positional encoding of frustum Gaussians.

All functions take the samples of one ray; `jax.vmap` lifts them to a batch.
"""

from typing import Literal

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._custom_types import SampledEdges, Vec3


def positional_encoding(
    x: Float[Array, "*batch in_features"], min_deg: int, max_deg: int, append_identity: bool = True
) -> Float[Array, "*batch features"]:
    """NeRF's encoding `[x, sin(2^k x), sin(2^k x + pi/2)]` for `k` in `[min_deg, max_deg)`."""
    scales = 2.0 ** jnp.arange(min_deg, max_deg, dtype=x.dtype)
    scaled = (x[..., None, :] * scales[:, None]).reshape(*x.shape[:-1], -1)
    features = jnp.sin(jnp.concatenate([scaled, scaled + 0.5 * jnp.pi], axis=-1))
    return jnp.concatenate([x, features], axis=-1) if append_identity else features


def integrated_positional_encoding(
    means: Float[Array, "*batch 3"],
    covs: Float[Array, "*batch 3"],
    min_deg: int,
    max_deg: int,
) -> Float[Array, "*batch features"]:
    """mip-NeRF's IPE: the expected positional encoding of a Gaussian with diagonal covariance.

    `E[sin(a x)] = sin(a mu) exp(-a^2 var / 2)` for `x ~ N(mu, var)`, applied to every frequency
    `2^k`, `k` in `[min_deg, max_deg)`, and to the cosine (sine shifted by pi/2).
    """
    scales = 2.0 ** jnp.arange(min_deg, max_deg, dtype=means.dtype)
    scaled_means = (means[..., None, :] * scales[:, None]).reshape(*means.shape[:-1], -1)
    scaled_vars = (covs[..., None, :] * scales[:, None] ** 2).reshape(*covs.shape[:-1], -1)
    phases = jnp.concatenate([scaled_means, scaled_means + 0.5 * jnp.pi], axis=-1)
    damping = jnp.exp(-0.5 * jnp.concatenate([scaled_vars, scaled_vars], axis=-1))
    return damping * jnp.sin(phases)


def conical_frustum_moments(
    t0: Float[Array, "*batch"], t1: Float[Array, "*batch"], base_radius: Float[Array, "*batch"]
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch"]]:
    """Mean and variance along the ray, and variance across it, of a conical frustum.

    The stable form of mip-NeRF (eq. 7 of its paper) in terms of the interval's midpoint
    `mu` and half-width `hw`.
    """
    # The moments are homogeneous in t (degree 1 for the mean, 2 for the variances), so they
    # are evaluated in units of the larger |edge|, held constant for the gradient (which is
    # then still exact). Unscaled, `hw^4` and `denom^2` overflow float32 for intervals longer
    # than ~1e9 (inf / inf = NaN), and `t0 = t1 = 0` gave `0 * tiny^-2 = NaN` gradients.
    # Scaled, `3 mu^2 + hw^2 >= 3/4`, so no division is ever by a small number.
    scale = jax.lax.stop_gradient(jnp.maximum(jnp.abs(t0), jnp.abs(t1)))
    has_extent = scale > 0
    scale = jnp.where(has_extent, scale, 1.0)
    mu = 0.5 * (t0 + t1) / scale
    hw = 0.5 * (t1 - t0) / scale
    # At t0 = t1 = 0 every moment is 0 (mu = hw = 0); only the 0 / 0 needs a safe denominator.
    denom = jnp.where(has_extent, 3 * mu**2 + hw**2, 1.0)
    hw_sq_ratio = hw**2 / denom
    t_mean = scale * (mu + 2 * mu * hw_sq_ratio)
    t_var = scale**2 * (hw**2 / 3 - (4 / 15) * hw**2 * hw_sq_ratio * (12 * mu**2 - hw**2) / denom)
    r_var = base_radius**2 * scale**2 * (mu**2 / 4 + (5 / 12) * hw**2 - (4 / 15) * hw**2 * hw_sq_ratio)
    return t_mean, t_var, r_var


def cylinder_moments(
    t0: Float[Array, "*batch"], t1: Float[Array, "*batch"], radius: Float[Array, "*batch"]
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch"]]:
    """Mean and variance along the ray, and variance across it, of a cylinder segment."""
    t_mean = 0.5 * (t0 + t1)
    t_var = (t1 - t0) ** 2 / 12
    r_var = radius**2 / 4
    return t_mean, t_var, jnp.broadcast_to(r_var, t_mean.shape)


def frustum_gaussians(
    t_edges: SampledEdges,
    origin: Vec3,
    direction: Vec3,
    radius: Float[Array, "1"],
    shape: Literal["cone", "cylinder"],
) -> tuple[Float[Array, "num_edges-1 3"], Float[Array, "num_edges-1 3"]]:
    """World-space Gaussians (means, diagonal covariances) of the frustums between edges.

    **Arguments:**

    - `t_edges`: sorted interval edges along the (unnormalised) direction.
    - `origin`, `direction`: the ray.
    - `radius`: the cone's base radius at `t = 1` (or the cylinder's radius).
    - `shape`: `"cone"` for perspective rays, `"cylinder"` for NDC rays.

    **Returns:**

    `(means, covs)`, one Gaussian per interval.
    """
    t0, t1 = t_edges[:-1], t_edges[1:]
    moments = conical_frustum_moments if shape == "cone" else cylinder_moments
    t_mean, t_var, r_var = moments(t0, t1, jnp.broadcast_to(radius, t0.shape))
    means = origin + t_mean[:, None] * direction
    # Lift the 1D Gaussian along the ray and the isotropic one across it (mip-NeRF eq. 8,
    # diagonal form): the across-ray variance lives in the plane orthogonal to `direction`.
    dir_sq = direction**2
    dir_norm_sq = jnp.maximum(jnp.sum(dir_sq), 1e-10)
    null_outer_diag = 1 - dir_sq / dir_norm_sq
    covs = t_var[:, None] * dir_sq + r_var[:, None] * null_outer_diag
    return means, covs
