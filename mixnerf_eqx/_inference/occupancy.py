"""An occupancy grid of the scene's density, for skipping empty space when rendering.

The grid covers an axis-aligned box in the space where the samples live: world space for
bounded scenes (Blender, DTU, the built-in scene) and normalised device coordinates for
forward-facing LLFF scenes, whose rays are already in NDC. Each cell holds a running maximum
of the field's density at random points in it; a cell is occupied where that value exceeds a
threshold (optionally dilated to its neighbours). A cell never evaluated yet holds `inf`, so
it counts as occupied: the grid only ever skips space it has looked at.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._custom_types import PRNGKey
from .._nn.budget import AbstractOccupancy
from .._nn.field import AbstractField
from .._nn.rays import RayBundle


class OccupiedCells(AbstractOccupancy):
    """A grid's occupied cells, fixed (the dilated mask computed once): the occupancy test a
    training step's `SampleBudget` asks at both levels."""

    mask: Bool[Array, "resolution resolution resolution"]
    box_min: Float[Array, "3"]
    cell_size: Float[Array, "3"]
    outside_occupied: bool = eqx.field(static=True)

    def occupied(self, points: Float[Array, "*batch 3"]) -> Bool[Array, "*batch"]:
        resolution = self.mask.shape[0]
        cells = jnp.floor((points - self.box_min) / self.cell_size).astype(jnp.int32)
        inside = jnp.all((cells >= 0) & (cells < resolution), axis=-1)
        cells = jnp.clip(cells, 0, resolution - 1)
        return jnp.where(inside, self.mask[cells[..., 0], cells[..., 1], cells[..., 2]], self.outside_occupied)


class OccupancyGrid(eqx.Module):
    """A density grid over the box `[box_min, box_max]`.

    **Fields:**

    - `density`: per cell, the running maximum of the sampled density (`inf`: not yet
      evaluated). Index order is `(x, y, z)`.
    - `box_min`, `box_max`: the corners of the box.
    - `threshold`: a cell is occupied where its density exceeds this. An array leaf, so a
      grid with another threshold (`with_threshold`) reuses every compiled render.
    - `dilation` (static): occupied cells also mark this many neighbours on every side.
    - `outside_occupied` (static): whether points outside the box count as occupied (the box
      is a guess) or empty (the scene is known to lie inside it).
    """

    density: Float[Array, "resolution resolution resolution"]
    box_min: Float[Array, "3"]
    box_max: Float[Array, "3"]
    threshold: Float[Array, ""]
    dilation: int = eqx.field(static=True)
    outside_occupied: bool = eqx.field(static=True)

    def __check_init__(self):
        if self.density.ndim != 3 or len(set(self.density.shape)) != 1:
            raise ValueError(f"the grid must be a cube, got shape {self.density.shape}")
        if self.dilation < 0:
            raise ValueError(f"dilation must be >= 0, got {self.dilation}")

    def with_threshold(self, threshold: float | Float[Array, ""]) -> "OccupancyGrid":
        """The same grid with another density threshold."""
        return eqx.tree_at(lambda g: g.threshold, self, jnp.asarray(threshold, jnp.float32))

    @property
    def resolution(self) -> int:
        return self.density.shape[0]

    @property
    def cell_size(self) -> Float[Array, "3"]:
        return (self.box_max - self.box_min) / self.resolution

    def mask(self) -> Bool[Array, "resolution resolution resolution"]:
        """The occupied cells, dilated by `dilation` cells on every side."""
        occupied = self.density > self.threshold
        if self.dilation == 0:
            return occupied
        width = 2 * self.dilation + 1
        dilated = jax.lax.reduce_window(
            occupied.astype(jnp.float32),
            0.0,
            jax.lax.max,
            (width, width, width),
            (1, 1, 1),
            "SAME",
        )
        return dilated > 0

    def occupied(
        self,
        points: Float[Array, "*batch 3"],
        mask: Bool[Array, "resolution resolution resolution"] | None = None,
    ) -> Bool[Array, "*batch"]:
        """Whether each point lies in an occupied cell (`mask`: a precomputed `self.mask()`)."""
        return self.cells(mask).occupied(points)

    def cells(self, mask: Bool[Array, "resolution resolution resolution"] | None = None) -> OccupiedCells:
        """The occupied cells as they are now (`mask`: a precomputed `self.mask()`)."""
        mask = self.mask() if mask is None else mask
        return OccupiedCells(mask, self.box_min, self.cell_size, self.outside_occupied)

    def fully_evaluated(self) -> Bool[Array, ""]:
        """Whether every cell has been evaluated at least once (none still `inf`)."""
        return jnp.all(jnp.isfinite(self.density))

    def occupied_fraction(self) -> Float[Array, ""]:
        """The share of the cells that `mask()` marks occupied."""
        return jnp.mean(self.mask().astype(jnp.float32))


def empty_grid(
    box_min,
    box_max,
    *,
    resolution: int = 128,
    threshold: float = 0.01,
    dilation: int = 1,
    outside_occupied: bool = True,
) -> OccupancyGrid:
    """A grid whose cells are all unevaluated (so all occupied)."""
    box_min = jnp.asarray(box_min, jnp.float32)
    box_max = jnp.asarray(box_max, jnp.float32)
    if box_min.shape != (3,) or box_max.shape != (3,) or not bool(jnp.all(box_max > box_min)):
        raise ValueError(f"need a box with box_max > box_min on every axis, got {box_min}, {box_max}")
    return OccupancyGrid(
        density=jnp.full((resolution,) * 3, jnp.inf, jnp.float32),
        box_min=box_min,
        box_max=box_max,
        threshold=jnp.asarray(threshold, jnp.float32),
        dilation=dilation,
        outside_occupied=outside_occupied,
    )


def frustum_box(rays: RayBundle, padding: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box holding every sample the rays can place between near and far.

    Every sample lies on a segment `o + t d`, `t` in `[near, far]`, and a box holds a segment
    when it holds both ends; the box is grown by `padding` of its size on every side.
    """
    flat = rays.reshape(-1)
    origins = np.asarray(flat.origins, np.float64)
    directions = np.asarray(flat.directions, np.float64)
    ends = np.concatenate(
        [origins + directions * np.asarray(flat.near), origins + directions * np.asarray(flat.far)]
    )
    low, high = ends.min(axis=0), ends.max(axis=0)
    margin = padding * np.maximum(high - low, 1e-6)
    return (low - margin).astype(np.float32), (high + margin).astype(np.float32)


def update_occupancy(
    grid: OccupancyGrid,
    field: AbstractField,
    *,
    key: PRNGKey,
    decay: float = 0.95,
    fraction: float = 1.0,
    offset: Int[Array, ""] | int = 0,
    batch_size: int = 65536,
) -> OccupancyGrid:
    """Re-evaluates a share of the cells at one random point each.

    The cells `offset, offset + stride, offset + 2 stride, ...` with `stride = round(1 /
    fraction)` are evaluated, so that calling with `offset = 0, 1, ..., stride - 1` visits
    every cell once. Every evaluated cell decays (`decay * old`) at each update, visited or
    not, as instant-ngp's grid does, so that density the field has lost leaves the grid within
    a few updates; a visited cell keeps `max(decay * old, new)` (`new` alone where it was never
    evaluated). The density is the field's noise-free density of a Gaussian with the variance
    of a uniform distribution over the cell. `decay = 0` replaces the old values.

    **Arguments:**

    - `grid`: the grid to update.
    - `field`: the radiance field; only its `density` is called.
    - `key`: randomness for the points inside the cells.
    - `decay`, `fraction`, `offset`: as above.
    - `batch_size`: points evaluated at once (bounds the memory of the update).
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    resolution = grid.resolution
    num_cells = resolution**3
    stride = max(1, round(1 / fraction))
    count = math.ceil(num_cells / stride)
    cell_ids = (offset % stride + stride * jnp.arange(count)) % num_cells
    coords = jnp.stack(jnp.unravel_index(cell_ids, (resolution,) * 3), axis=-1).astype(jnp.float32)
    jitter = jax.random.uniform(key, (count, 3), jnp.float32)
    cell_size = grid.cell_size
    points = grid.box_min + (coords + jitter) * cell_size
    covs = jnp.broadcast_to(cell_size**2 / 12, (count, 3))
    new = _batched_density(field, points, covs, batch_size)
    flat = grid.density.reshape(-1)
    flat = jnp.where(jnp.isinf(flat), flat, decay * flat)
    old = flat[cell_ids]
    kept = jnp.where(jnp.isinf(old), new, jnp.maximum(old, new))
    density = flat.at[cell_ids].set(kept).reshape(grid.density.shape)
    return eqx.tree_at(lambda g: g.density, grid, density)


def _batched_density(
    field: AbstractField, points: Float[Array, "points 3"], covs: Float[Array, "points 3"], batch_size: int
) -> Float[Array, " points"]:
    """`field.density_batch` over `batch_size` points at a time (the last batch padded)."""
    count = points.shape[0]
    if count <= batch_size:
        return field.density_batch(points, covs)
    batches = math.ceil(count / batch_size)
    pad = batches * batch_size - count

    def grouped(values: Array) -> Array:
        padded = jnp.concatenate([values, jnp.broadcast_to(values[:1], (pad, 3))])
        return padded.reshape(batches, batch_size, 3)

    densities = jax.lax.map(lambda pc: field.density_batch(pc[0], pc[1]), (grouped(points), grouped(covs)))
    return densities.reshape(-1)[:count]


def refresh_occupancy(grid: OccupancyGrid, field: AbstractField, *, key: PRNGKey) -> OccupancyGrid:
    """Every cell re-evaluated, old values dropped: the grid of `field` as it is now."""
    return update_occupancy(grid, field, key=key, decay=0.0, fraction=1.0)
