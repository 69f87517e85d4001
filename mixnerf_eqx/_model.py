"""The MixNeRF model: a field, two samplers, a renderer and a mixture in one pytree."""

import equinox as eqx
import jax
import jax.numpy as jnp

from ._custom_types import PRNGKey
from ._field import AbstractField
from ._mixture import AbstractMixture
from ._rays import RayBundle
from ._renderer import AbstractRenderer, LevelOutputs
from ._sampler import AbstractSampler


class RenderOutputs(eqx.Module):
    """Both levels of a batch of rays; the fine level is the model's prediction."""

    coarse: LevelOutputs
    fine: LevelOutputs


class MixNeRF(eqx.Module):
    """mip-NeRF's two-level cone tracer with MixNeRF's mixture density (paper Sec. 3).

    The same `field` serves the coarse level (samples from `coarse_sampler`) and the fine
    level (samples from `fine_sampler`, drawn from the coarse weights). `mixture` holds the
    mixture density used by the losses; the mip-NeRF baseline is the same model whose field
    has no mixture heads and whose `mixture` is `None`. With `remat`, the field's activations
    are recomputed in the backward pass instead of stored, which bounds training memory at the
    paper's batch on small machines for about a third more compute.

    Any part can be replaced by another implementation of its abstract class, e.g.
    `eqx.tree_at(lambda m: m.fine_sampler, model, OtherSampler(...))`.
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

    def _render_level(self, samples, ray: RayBundle, key: PRNGKey | None) -> LevelOutputs:
        num_samples = samples.means.shape[0]
        viewdirs = jnp.broadcast_to(ray.viewdirs, (num_samples, 3))
        field = jax.checkpoint(type(self.field).__call__) if self.remat else type(self.field).__call__
        if key is None:
            outputs = jax.vmap(lambda m, c, v: field(self.field, m, c, v))(
                samples.means, samples.covs, viewdirs
            )
        else:
            keys = jax.random.split(key, num_samples)
            outputs = jax.vmap(lambda m, c, v, k: field(self.field, m, c, v, key=k))(
                samples.means, samples.covs, viewdirs, keys
            )
        return self.renderer(outputs, samples.t_edges, ray)

    def render_ray(self, ray: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders one ray (empty batch shape); `key=None` renders deterministically."""
        keys = (None,) * 4 if key is None else tuple(jax.random.split(key, 4))
        coarse_samples = self.coarse_sampler(ray, key=keys[0])
        coarse = self._render_level(coarse_samples, ray, keys[1])
        fine_samples = self.fine_sampler(ray, coarse.t_edges, coarse.weights, key=keys[2])
        fine = self._render_level(fine_samples, ray, keys[3])
        return RenderOutputs(coarse=coarse, fine=fine)

    def __call__(self, rays: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders a batch of rays of any batch shape.

        **Arguments:**

        - `rays`: the rays.
        - `key`: training randomness (jittered samples, density noise); `None` for the
          deterministic evaluation render.

        **Returns:**

        A `RenderOutputs` whose leaves have `rays.batch_shape` in front.
        """
        batch_shape = rays.batch_shape
        flat = rays.reshape(-1)
        if key is None:
            outputs = jax.vmap(lambda ray: self.render_ray(ray))(flat)
        else:
            keys = jax.random.split(key, flat.origins.shape[0])
            outputs = jax.vmap(lambda ray, k: self.render_ray(ray, key=k))(flat, keys)
        return jax.tree_util.tree_map(lambda x: x.reshape(*batch_shape, *x.shape[1:]), outputs)
