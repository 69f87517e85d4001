"""Renderers: Modules that turn one ray's field outputs into a pixel."""

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._custom_types import SampledEdges
from .compositing import accumulation, blend_weights, composite_rgb, expected_depth
from .field import FieldOutputs
from .rays import RayBundle


class LevelOutputs(eqx.Module):
    """One sampling level of one ray (or, after `vmap`, of a batch of rays).

    **Fields:**

    - `weights`: blending weights `w_i`.
    - `t_edges`: the level's interval edges.
    - `field`: the field's predictions at the samples.
    - `rgb`: composited colour (background included).
    - `depth`: expected depth along the unnormalised direction.
    - `acc`: opacity `sum_i w_i`.
    """

    weights: Float[Array, "*batch num_samples"]
    t_edges: Float[Array, "*batch num_samples+1"]
    field: FieldOutputs
    rgb: Float[Array, "*batch channels"]
    depth: Float[Array, "*batch"]
    acc: Float[Array, "*batch"]


class AbstractRenderer(eqx.Module):
    """Composites the field outputs along one ray."""

    @abc.abstractmethod
    def __call__(self, outputs: FieldOutputs, t_edges: SampledEdges, ray: RayBundle) -> LevelOutputs:
        """Renders one ray from its samples' field outputs."""


class VolumeRenderer(AbstractRenderer):
    """Emission-absorption volume rendering (paper eq. 2) over an optional constant background.

    **Fields (static):**

    - `background`: RGB composited behind the ray (`(1, 1, 1)` for Blender-style scenes), or
      `None` for none.
    """

    background: tuple[float, float, float] | None = eqx.field(static=True, default=None)

    def __call__(self, outputs: FieldOutputs, t_edges: SampledEdges, ray: RayBundle) -> LevelOutputs:
        direction_norm = jnp.linalg.norm(ray.directions)
        weights = blend_weights(outputs.density, t_edges, direction_norm)
        background = None if self.background is None else jnp.asarray(self.background, weights.dtype)
        return LevelOutputs(
            t_edges=t_edges,
            weights=weights,
            field=outputs,
            rgb=composite_rgb(weights, outputs.rgb, background),
            depth=expected_depth(weights, t_edges),
            acc=accumulation(weights),
        )
