"""Step-dependent schedules: learning rate, lambda_C, and sample-space annealing."""

import jax.numpy as jnp
import optax
from jaxtyping import Array, Float, Int

from .._nn.rays import RayBundle


def learning_rate_schedule(
    lr_init: float, lr_final: float, max_steps: int, warmup_steps: int
) -> optax.Schedule:
    """Log-linear decay from `lr_init` to `lr_final` over `max_steps`, times the warm-up
    factor `0.01 + 0.99 sin(pi/2 clip(step / warmup_steps, 0, 1))` (mip-NeRF, RegNeRF)."""

    def schedule(step: Int[Array, ""] | int) -> Float[Array, ""]:
        step = jnp.asarray(step, jnp.float32)
        progress = jnp.clip(step / max(max_steps, 1), 0.0, 1.0)
        log_lr = jnp.log(lr_init) * (1 - progress) + jnp.log(lr_final) * progress
        if warmup_steps > 0:
            warmup = 0.01 + 0.99 * jnp.sin(0.5 * jnp.pi * jnp.clip(step / warmup_steps, 0.0, 1.0))
        else:
            warmup = 1.0
        return warmup * jnp.exp(log_lr)

    return schedule


def linear_ramp(step: Int[Array, ""] | int, start: float, end: float, num_steps: int) -> Float[Array, ""]:
    """`start` at step 0, linear to `end` at `num_steps`, constant after (lambda_C)."""
    if num_steps <= 0:
        return jnp.asarray(end, jnp.float32)
    progress = jnp.clip(jnp.asarray(step, jnp.float32) / num_steps, 0.0, 1.0)
    return start * (1 - progress) + end * progress


def anneal_sample_space(
    rays: RayBundle, step: Int[Array, ""] | int, num_steps: int, start: float, mid: float
) -> RayBundle:
    """RegNeRF's sample-space annealing: sampling starts in a small interval around
    `mid = n + m (f - n)` (`start` = p of its full size) and widens to `[near, far]` by
    `num_steps`. `num_steps <= 0` turns it off."""
    if num_steps <= 0:
        return rays
    near, far = rays.near, rays.far
    centre = near + mid * (far - near)
    near_start = centre + start * (near - centre)
    far_start = centre + start * (far - centre)
    progress = jnp.clip(jnp.asarray(step, near.dtype) / num_steps, start, 1.0)
    return RayBundle(
        origins=rays.origins,
        directions=rays.directions,
        viewdirs=rays.viewdirs,
        radii=rays.radii,
        near=near_start + progress * (near - near_start),
        far=far_start + progress * (far - far_start),
    )
