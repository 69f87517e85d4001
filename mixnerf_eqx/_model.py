"""The MixNeRF model: a field, two samplers, a renderer and a mixture in one pytree."""

import equinox as eqx
import jax
import jax.numpy as jnp

from ._custom_types import FourKeysPerRay, PRNGKey, RayKeys
from ._field import AbstractField
from ._mixture import AbstractMixture
from ._rays import RayBundle, RaySamples
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

    def _render_level(self, samples: RaySamples, rays: RayBundle, level_keys: RayKeys | None) -> LevelOutputs:
        """One level of a flat batch of rays: the field at every sample, then compositing.

        The samples of all rays are flattened into one list before the field is called, so
        that each dense layer is one matrix product over every sample of the batch (a field
        vmapped over rays and then over samples ran about 1.5x slower on the CPU:
        `benchmarks/README.md`, profile of the training step).
        """
        num_rays, num_samples = samples.means.shape[:2]
        points = num_rays * num_samples
        viewdirs = jnp.broadcast_to(rays.viewdirs[:, None, :], (num_rays, num_samples, 3))
        inputs = (
            samples.means.reshape(points, 3),
            samples.covs.reshape(points, 3),
            viewdirs.reshape(points, 3),
        )
        field = jax.checkpoint(type(self.field).__call__) if self.remat else type(self.field).__call__
        if level_keys is None:
            outputs = jax.vmap(lambda m, c, v: field(self.field, m, c, v))(*inputs)
        else:
            # Per ray, one key per sample, as `jax.random.split(ray_key, num_samples)`.
            keys = jax.vmap(lambda k: jax.random.split(k, num_samples))(level_keys)
            keys = keys.reshape(points, *keys.shape[2:])
            outputs = jax.vmap(lambda m, c, v, k: field(self.field, m, c, v, key=k))(*inputs, keys)
        outputs = jax.tree_util.tree_map(lambda x: x.reshape(num_rays, num_samples, *x.shape[1:]), outputs)
        return jax.vmap(self.renderer)(outputs, samples.t_edges, rays)

    def _render_flat(self, rays: RayBundle, ray_keys: FourKeysPerRay | None) -> RenderOutputs:
        """Renders a flat batch of rays; `ray_keys` holds four keys per ray, or is `None`.

        A ray's keys are, in order, for the coarse sampler, the coarse density noise, the fine
        sampler and the fine density noise.
        """

        def keys(index: int):
            return None if ray_keys is None else ray_keys[:, index]

        def sample(sampler, *args, key):
            if key is None:
                return jax.vmap(lambda *a: sampler(*a))(*args)
            return jax.vmap(lambda k, *a: sampler(*a, key=k))(key, *args)

        coarse_samples = sample(self.coarse_sampler, rays, key=keys(0))
        coarse = self._render_level(coarse_samples, rays, keys(1))
        fine_samples = sample(self.fine_sampler, rays, coarse.t_edges, coarse.weights, key=keys(2))
        fine = self._render_level(fine_samples, rays, keys(3))
        return RenderOutputs(coarse=coarse, fine=fine)

    def render_ray(self, ray: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders one ray (empty batch shape); `key=None` renders deterministically."""
        ray_keys = None if key is None else jax.random.split(key, 4)[None]
        outputs = self._render_flat(ray.reshape(1), ray_keys)
        return jax.tree_util.tree_map(lambda x: x[0], outputs)

    def __call__(self, rays: RayBundle, *, key: PRNGKey | None = None) -> RenderOutputs:
        """Renders a batch of rays of any batch shape.

        **Arguments:**

        - `rays`: the rays.
        - `key`: training randomness (jittered samples, density noise); `None` for the
          deterministic evaluation render. Ray `i` of the flattened batch renders as
          `render_ray(ray_i, key=jax.random.split(key, num_rays)[i])` does.

        **Returns:**

        A `RenderOutputs` whose leaves have `rays.batch_shape` in front.
        """
        batch_shape = rays.batch_shape
        flat = rays.reshape(-1)
        ray_keys = None
        if key is not None:
            ray_keys = jax.vmap(lambda k: jax.random.split(k, 4))(
                jax.random.split(key, flat.origins.shape[0])
            )
        outputs = self._render_flat(flat, ray_keys)
        return jax.tree_util.tree_map(lambda x: x.reshape(*batch_shape, *x.shape[1:]), outputs)
