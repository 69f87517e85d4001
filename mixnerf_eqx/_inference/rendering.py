"""Rendering rays and views in bounded memory: fixed-size chunks of rays through one compiled
renderer (dense, or skipping empty space), brought back to the host with what they cost."""

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._nn.chunks import join_chunks, map_ray_chunks
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from .._nn.renderer import LevelOutputs
from ..data import Views, rays_for_views
from .skipping import RenderCounts, Skipping, render_skipping


@eqx.filter_jit
def _render_dense(model: MixNeRF, rays: RayBundle) -> LevelOutputs:
    return model(rays).fine


@dataclasses.dataclass(frozen=True)
class Rendered:
    """Rendered rays on the host, with what rendering them cost.

    **Fields:**

    - `rgb`, `depth`, `acc`: colour, expected depth and opacity, with the rays' batch shape
      in front.
    - `counts`: rays and field evaluations.
    """

    rgb: np.ndarray
    depth: np.ndarray
    acc: np.ndarray
    counts: RenderCounts

    def select(self, index: int) -> "Rendered":
        """The rays of position `index` along the first batch dimension (e.g. one view)."""
        return dataclasses.replace(self, rgb=self.rgb[index], depth=self.depth[index], acc=self.acc[index])


def _render_chunk(
    model: MixNeRF, piece: RayBundle, real: int, skipping: Skipping | None
) -> tuple[LevelOutputs, RenderCounts]:
    """One chunk of rays, of which the first `real` are real, dense or with skipping."""
    if skipping is not None:
        return render_skipping(model, piece, jnp.arange(piece.batch_shape[0]) < real, skipping)
    per_ray = model.samples_per_ray
    counts = RenderCounts(
        rays=real,
        dense_evaluations=real * per_ray,
        field_evaluations=real * per_ray,
        padded_evaluations=piece.batch_shape[0] * per_ray,
    )
    return _render_dense(model, piece), counts


def render_rays(
    model: MixNeRF, rays: RayBundle, chunk: int = 4096, *, skipping: Skipping | None = None
) -> Rendered:
    """Deterministically renders any number of rays, `chunk` rays at a time
    (`map_ray_chunks`: one compiled renderer, memory bounded by the chunk).

    **Arguments:**

    - `model`: the model.
    - `rays`: rays of any batch shape.
    - `chunk`: rays rendered at once.
    - `skipping`: skip empty space and finished rays (`mixnerf_eqx.inference.Skipping`); `None`
      evaluates the field at every sample.

    **Returns:**

    A `Rendered` with `rays.batch_shape` in front.
    """
    batch_shape = rays.batch_shape

    def render(piece: RayBundle, real: int, _) -> tuple[tuple[Array, Array, Array], RenderCounts]:
        level, counts = _render_chunk(model, piece, real, skipping)
        return (level.rgb, level.depth, level.acc), counts

    parts, count = map_ray_chunks(render, rays, chunk)
    if not parts:
        empty = np.empty((0,), np.float32)
        return Rendered(
            rgb=np.empty((*batch_shape, 3), np.float32),
            depth=empty.reshape(batch_shape),
            acc=empty.reshape(batch_shape),
            counts=RenderCounts(),
        )
    rgb, depth, acc = (join_chunks([outputs[i] for outputs, _ in parts], count) for i in range(3))
    counts = sum((chunk_counts for _, chunk_counts in parts), RenderCounts())
    return Rendered(
        rgb=rgb.astype(np.float32, copy=False).reshape(*batch_shape, 3),
        depth=depth.astype(np.float32, copy=False).reshape(batch_shape),
        acc=acc.astype(np.float32, copy=False).reshape(batch_shape),
        counts=counts,
    )


def render_views(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    chunk: int = 4096,
    *,
    skipping: Skipping | None = None,
) -> Rendered:
    """Renders every view of `views`; the rays of one view at a time exist on the host.

    **Returns:**

    A `Rendered` stacked over the views (`skipping` as in `render_rays`).
    """
    rgb = np.empty((views.num_views, views.height, views.width, 3), np.float32)
    depth = np.empty((views.num_views, views.height, views.width), np.float32)
    acc = np.empty_like(depth)
    counts = RenderCounts()
    for index in range(views.num_views):
        rays = rays_for_views(views.select([index]), near, far)
        view = render_rays(model, rays, chunk, skipping=skipping)
        rgb[index], depth[index], acc[index] = view.rgb[0], view.depth[0], view.acc[0]
        counts = counts + view.counts
    return Rendered(rgb=rgb, depth=depth, acc=acc, counts=counts)
