"""A grid field: multi-resolution features looked up in a grid, decoded by a small MLP.

Two encodings share one decoder (`GridField`):

- `TriPlaneEncoding`: at each level three feature planes (normal to x, y and z), each
  sampled bilinearly at the point's projection and multiplied together, as K-Planes does
  for a static scene. A plane holds `resolution^2` texels, so a level of resolution 256 costs
  what a 3D grid of resolution 40 does, and total variation on the planes is the natural
  smoothness prior for a few views.
- `HashEncoding`: instant-ngp's multi-resolution hash grid: at each level the eight corners
  of the point's cell, hashed into a table where the level has more corners than the table
  has entries, interpolated trilinearly.

Both map a point of the scene's box to `[-1, 1]^3` first. The frustum's scale enters as
Zip-NeRF weights its grid levels: a level whose cells are much smaller than the frustum
Gaussian's standard deviation would alias, so its features are scaled by
`erf(cell / (sqrt(8) sigma))`, the factor by which blurring the level with the Gaussian damps
its finest detail; `sigma` is the root mean of the covariance diagonal in the box's units.
"""

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..._custom_types import PRNGKey, RayKeys, Vec3
from ..encoding import positional_encoding
from ._lookup import plane_product, resolve_lookup, weighted_rows
from .base import AbstractField, FieldOutputs, vmap_field
from .heads import MixtureHeads, dense
from .heads import density_activation as density_activation

# instant-ngp's spatial hash primes (the first is 1, so x needs no multiplication).
_HASH_PRIMES = (1, 2654435761, 805459861)


def level_resolutions(levels: int, min_resolution: int, max_resolution: int) -> tuple[int, ...]:
    """Resolutions growing geometrically from `min_resolution` to `max_resolution`."""
    if levels < 1 or min_resolution < 2 or max_resolution < min_resolution:
        raise ValueError(
            f"need levels >= 1 and 2 <= min_resolution <= max_resolution, got {levels}, "
            f"{min_resolution}, {max_resolution}"
        )
    if levels == 1:
        return (max_resolution,)
    growth = (max_resolution / min_resolution) ** (1 / (levels - 1))
    return tuple(int(round(min_resolution * growth**level)) for level in range(levels))


class AbstractGridEncoding(eqx.Module):
    """Features of a point of `[-1, 1]^3` at several resolutions, one row per level."""

    resolutions: eqx.AbstractVar[tuple[int, ...]]

    @property
    def num_levels(self) -> int:
        return len(self.resolutions)

    @property
    @abc.abstractmethod
    def features_per_level(self) -> int:
        """The width of one level's row."""

    @property
    @abc.abstractmethod
    def cell_sizes(self) -> tuple[float, ...]:
        """Each level's cell size in the units of `[-1, 1]`."""

    @abc.abstractmethod
    def __call__(self, point: Vec3) -> Float[Array, "levels features"]:
        """The features of one point (coordinates outside `[-1, 1]` are clamped)."""

    @abc.abstractmethod
    def encode_batch(self, points: Float[Array, "batch 3"]) -> Float[Array, "batch levels features"]:
        """The features of a batch of points: `jax.vmap(self)(points)`, computed with
        `weighted_rows` or `plane_product` (the batched formulations of `mixnerf_eqx._nn.field._lookup`)."""

    @abc.abstractmethod
    def total_variation(self) -> Float[Array, ""]:
        """Mean squared difference of neighbouring grid values, summed over levels
        (`jnp.zeros(())` for an encoding without a neighbourhood structure to regularise)."""


# Plane `k` of a tri-plane level is sampled at the coordinates (column axis, row axis)
# `_PLANE_COLUMNS[k]`, `_PLANE_ROWS[k]`; corner `c` of its 2x2 window lies
# `_WINDOW_COLUMNS[c]` columns and `_WINDOW_ROWS[c]` rows from the window's first texel.
_PLANE_COLUMNS, _PLANE_ROWS = (1, 0, 0), (2, 2, 1)
_WINDOW_COLUMNS, _WINDOW_ROWS = (0, 1, 0, 1), (0, 0, 1, 1)


def _plane_corners(
    resolution: int, points: Float[Array, "*batch 3"]
) -> tuple[Int[Array, "3 4 *batch"], Float[Array, "3 4 *batch"]]:
    """The four texels around each point's projection onto each of a level's three planes, as
    rows of the planes flattened to `(3 * resolution^2, features)`, and their bilinear weights
    (corners aligned), plane by plane. Plane `k` is sampled at the two coordinates other than
    `k`, the first along its columns.

    Written as broadcasts over a (plane, corner) grid rather than stacks of per-plane arrays:
    on the CPU, XLA emits a stack as a loop that selects its source element by element (about
    6 ns an element here, against well under 1 ns for the broadcast form).
    """
    res = resolution
    scaled = (jnp.clip(points, -1.0, 1.0) + 1.0) * 0.5 * (res - 1)
    low = jnp.clip(jnp.floor(scaled), 0, res - 2).astype(jnp.int32)
    frac = scaled - low
    batch = (1,) * (points.ndim - 1)

    def per_plane(values, axes):
        # (3, 1, *batch): the coordinate each plane reads along `axes`.
        return jnp.moveaxis(values[..., axes], -1, 0)[:, None]

    def per_corner(offsets):
        return jnp.asarray(offsets, jnp.int32).reshape(1, 4, *batch)

    low_u, low_v = per_plane(low, _PLANE_COLUMNS), per_plane(low, _PLANE_ROWS)
    frac_u, frac_v = per_plane(frac, _PLANE_COLUMNS), per_plane(frac, _PLANE_ROWS)
    du, dv = per_corner(_WINDOW_COLUMNS), per_corner(_WINDOW_ROWS)
    plane = jnp.arange(3, dtype=jnp.int32).reshape(3, 1, *batch)
    indices = (plane * res + low_v + dv) * res + low_u + du
    weights = jnp.where(du == 1, frac_u, 1 - frac_u) * jnp.where(dv == 1, frac_v, 1 - frac_v)
    return indices, weights


def _plane_lookup(
    planes: Float[Array, "3 _resolution _resolution features"], point: Vec3
) -> Float[Array, "3 features"]:
    """Each of a level's three planes sampled bilinearly at one point's projection onto it.

    The twelve texels are gathered at once from the flattened planes, each a contiguous row
    of features (the per-point formulation: `jax.vmap` makes the backward pass one scatter
    per level).
    """
    indices, weights = _plane_corners(planes.shape[1], point)
    texels = planes.reshape(-1, planes.shape[-1])[indices]
    return jnp.einsum("pc,pcf->pf", weights, texels)


class TriPlaneEncoding(AbstractGridEncoding):
    """K-Planes' static-scene factorisation: per level, the product of three planes' features.

    Plane `k` of a level is normal to axis `k`: plane 0 is indexed by (y, z), plane 1 by
    (x, z), plane 2 by (x, y), the first coordinate along its columns. The planes start
    uniform in `[0.1, 0.5]` (K-Planes' initialisation), so products start well away from zero.
    """

    planes: tuple[Float[Array, "3 _resolution _resolution features"], ...]
    resolutions: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, resolutions: tuple[int, ...], features: int, *, key: PRNGKey):
        if features < 1 or any(res < 2 for res in resolutions):
            raise ValueError(f"need features >= 1 and resolutions >= 2, got {features}, {resolutions}")
        keys = jax.random.split(key, len(resolutions))
        self.planes = tuple(
            jax.random.uniform(k, (3, res, res, features), minval=0.1, maxval=0.5)
            for k, res in zip(keys, resolutions, strict=True)
        )
        self.resolutions = tuple(resolutions)

    @property
    def features_per_level(self) -> int:
        return self.planes[0].shape[-1]

    @property
    def cell_sizes(self) -> tuple[float, ...]:
        return tuple(2.0 / (res - 1) for res in self.resolutions)

    def __call__(self, point: Vec3) -> Float[Array, "levels features"]:
        return jnp.stack([jnp.prod(_plane_lookup(planes, point), axis=0) for planes in self.planes])

    def encode_batch(self, points: Float[Array, "batch 3"]) -> Float[Array, "batch levels features"]:
        rows = [plane_product(planes, *_plane_corners(planes.shape[1], points)) for planes in self.planes]
        return jnp.stack(rows, axis=1)

    def total_variation(self) -> Float[Array, ""]:
        total = jnp.zeros(())
        for planes in self.planes:
            total = total + jnp.mean((planes[:, 1:] - planes[:, :-1]) ** 2)
            total = total + jnp.mean((planes[:, :, 1:] - planes[:, :, :-1]) ** 2)
        return total


def hash_corner_index(
    corner: Int[Array, "*batch 3"], resolution: int, table_size: int
) -> Int[Array, "*batch"]:
    """The table entry of integer grid corners at one level.

    A level with at most `table_size` corners indexes them one to one (x fastest); a finer
    level XORs the coordinates times instant-ngp's primes, modulo the table size.
    """
    side = resolution + 1
    if side**3 <= table_size:
        return corner[..., 0] + side * (corner[..., 1] + side * corner[..., 2])
    unsigned = corner.astype(jnp.uint32)
    hashed = unsigned[..., 0] * jnp.uint32(_HASH_PRIMES[0])
    hashed = hashed ^ (unsigned[..., 1] * jnp.uint32(_HASH_PRIMES[1]))
    hashed = hashed ^ (unsigned[..., 2] * jnp.uint32(_HASH_PRIMES[2]))
    return (hashed % jnp.uint32(table_size)).astype(jnp.int32)


# The eight corners of a cell, as offsets from its lowest corner.
_CORNERS = tuple((dx, dy, dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1))


class HashEncoding(AbstractGridEncoding):
    """instant-ngp's multi-resolution hash encoding, trilinearly interpolated.

    Level `l` has `resolution_l` cells per axis; its table holds `min(table_size,
    (resolution_l + 1)^3)` entries, initialised uniform in `[-1e-4, 1e-4]` as instant-ngp does.
    """

    tables: tuple[Float[Array, "_entries features"], ...]
    resolutions: tuple[int, ...] = eqx.field(static=True)
    table_size: int = eqx.field(static=True)

    def __init__(self, resolutions: tuple[int, ...], features: int, table_size: int, *, key: PRNGKey):
        if features < 1 or table_size < 8 or any(res < 1 for res in resolutions):
            raise ValueError(
                f"need features >= 1, table_size >= 8, resolutions >= 1; got {features}, {table_size}, "
                f"{resolutions}"
            )
        keys = jax.random.split(key, len(resolutions))
        self.tables = tuple(
            jax.random.uniform(k, (min(table_size, (res + 1) ** 3), features), minval=-1e-4, maxval=1e-4)
            for k, res in zip(keys, resolutions, strict=True)
        )
        self.resolutions = tuple(resolutions)
        self.table_size = table_size

    @property
    def features_per_level(self) -> int:
        return self.tables[0].shape[1]

    @property
    def cell_sizes(self) -> tuple[float, ...]:
        return tuple(2.0 / res for res in self.resolutions)

    def _corners(
        self, level: int, points: Float[Array, "*batch 3"]
    ) -> tuple[Int[Array, "8 *batch"], Float[Array, "8 *batch"]]:
        """The table entries of the eight corners of each point's cell at `level`, and their
        trilinear weights."""
        res, entries = self.resolutions[level], self.tables[level].shape[0]
        scaled = (jnp.clip(points, -1.0, 1.0) + 1.0) * 0.5 * res
        low = jnp.clip(jnp.floor(scaled), 0, res - 1).astype(jnp.int32)
        frac = scaled - low
        indices, weights = [], []
        for offset in _CORNERS:
            corner = low + jnp.asarray(offset, jnp.int32)
            indices.append(hash_corner_index(corner, res, entries))
            weights.append(jnp.prod(jnp.where(jnp.asarray(offset) == 1, frac, 1 - frac), axis=-1))
        return jnp.stack(indices), jnp.stack(weights)

    def __call__(self, point: Vec3) -> Float[Array, "levels features"]:
        rows = []
        for level, table in enumerate(self.tables):
            indices, weights = self._corners(level, point)
            row = jnp.zeros(table.shape[1:], table.dtype)
            for k in range(len(_CORNERS)):
                row = row + weights[k] * table[indices[k]]
            rows.append(row)
        return jnp.stack(rows)

    def encode_batch(self, points: Float[Array, "batch 3"]) -> Float[Array, "batch levels features"]:
        rows = []
        for level, table in enumerate(self.tables):
            rows.append(weighted_rows(table, *self._corners(level, points)))
        return jnp.stack(rows, axis=1)

    def total_variation(self) -> Float[Array, ""]:
        return jnp.zeros(())  # hashed entries have no neighbours to regularise


def level_scale_weights(
    cov: Vec3, half_extent: Vec3, cell_sizes: tuple[float, ...]
) -> Float[Array, "levels"]:
    """Zip-NeRF's per-level weights `erf(cell / (sqrt(8) sigma))` for one frustum Gaussian.

    `sigma` is the root mean of `cov / half_extent^2`, the Gaussian's standard deviation in
    the units of `[-1, 1]^3`. A point (zero covariance) weights every level 1.
    """
    sigma = jnp.sqrt(jnp.mean(cov / half_extent**2))
    cells = jnp.asarray(cell_sizes, cov.dtype)
    return jax.scipy.special.erf(cells / jnp.maximum(math.sqrt(8.0) * sigma, 1e-12))


class GridField(AbstractField):
    """A grid encoding and a small decoder, with MixNeRF's heads placed as in the MLP field.

    The density branch maps the weighted, flattened levels through one ReLU layer of
    `decoder_width` to the raw density and `geo_features` features; the colour branch joins
    those features with the encoded view direction in one ReLU layer of `view_width`, from
    which the colour, `beta = softplus(Dense(3))` and `ray_depth = ||Dense(3)||` come (the
    MLP field's heads, so MixNeRF's mixture and losses work unchanged).

    **Fields:**

    - `encoding`: the grid encoding.
    - `level_weights`: the coarse-to-fine mask over levels, all ones in a stored model; the
      training step replaces it (`at_step`), so it is never trained.
    - `box_min`, `box_max` (static): the box mapped to `[-1, 1]^3`.
    - `bounded` (static): the scene lies inside the box, so the density outside it is zero;
      otherwise points outside take the features of the box's surface.
    - `scale_weighting` (static): weight levels by the frustum's scale (Zip-NeRF).
    - `tv_weight` (static): weight of the encoding's total variation in the loss.
    - `coarse_to_fine_steps` (static): steps over which the levels are revealed one after
      another, coarsest first (0: all from the start).
    - `heads`: the colour, `beta` and ray-depth heads and the density's noise and activation
      (`MixtureHeads`, shared with `MipNeRFField`). The activation (the argument
      `density_activation`) is `"softplus"` (the MLP field's) or `"exp"`; the exponential
      lets a few steps make a surface opaque within one sample interval (density grows by a
      factor per step of the optimiser, not by a constant).
    - `density_bias`, `viewdir_max_deg` (static): as in `MipNeRFField`.
    - `lookup` (static): how `evaluate_batch` reads the grid: `"vmap"` (the encoding per
      point, lifted by `jax.vmap`) or `"batched"` (`encoding.encode_batch`, whose gradient
      scatters once per level; faster on a CPU). Both give the same values and gradients.
    """

    encoding: AbstractGridEncoding
    density_layer: eqx.nn.Linear
    density_out: eqx.nn.Linear
    view_layer: eqx.nn.Linear
    heads: MixtureHeads
    level_weights: Float[Array, "levels"]
    box_min: tuple[float, float, float] = eqx.field(static=True)
    box_max: tuple[float, float, float] = eqx.field(static=True)
    bounded: bool = eqx.field(static=True)
    scale_weighting: bool = eqx.field(static=True)
    tv_weight: float = eqx.field(static=True)
    coarse_to_fine_steps: int = eqx.field(static=True)
    density_bias: float = eqx.field(static=True)
    viewdir_max_deg: int = eqx.field(static=True)
    lookup: str = eqx.field(static=True)

    def __init__(
        self,
        encoding: AbstractGridEncoding,
        *,
        box_min: tuple[float, float, float],
        box_max: tuple[float, float, float],
        bounded: bool,
        decoder_width: int = 64,
        geo_features: int = 15,
        view_width: int = 64,
        viewdir_max_deg: int = 4,
        scale_weighting: bool = True,
        tv_weight: float = 0.0,
        coarse_to_fine_steps: int = 0,
        density_activation: str = "softplus",
        density_noise: float = 0.0,
        density_bias: float = -1.0,
        rgb_padding: float = 0.001,
        mixture_heads: bool = True,
        lookup: str = "auto",
        key: PRNGKey,
    ):
        box_min = tuple(float(v) for v in box_min)
        box_max = tuple(float(v) for v in box_max)
        if (
            len(box_min) != 3
            or len(box_max) != 3
            or any(lo >= hi for lo, hi in zip(box_min, box_max, strict=True))
        ):
            raise ValueError(f"the box must have three sides of positive length, got {box_min}, {box_max}")
        if decoder_width < 1 or view_width < 1 or geo_features < 0:
            raise ValueError("decoder_width and view_width must be positive and geo_features >= 0")
        view_size = 3 + 2 * 3 * viewdir_max_deg
        keys = iter(jax.random.split(key, 6))
        in_size = encoding.num_levels * encoding.features_per_level
        self.encoding = encoding
        self.density_layer = dense(in_size, decoder_width, key=next(keys))
        self.density_out = dense(decoder_width, 1 + geo_features, key=next(keys))
        self.view_layer = dense(geo_features + view_size, view_width, key=next(keys))
        self.heads = MixtureHeads(
            view_width,
            mixture=mixture_heads,
            density_noise=density_noise,
            rgb_padding=rgb_padding,
            activation=density_activation,
            keys=(next(keys), next(keys), next(keys)),
        )
        self.level_weights = jnp.ones(encoding.num_levels)
        self.box_min = box_min
        self.box_max = box_max
        self.bounded = bounded
        self.scale_weighting = scale_weighting
        self.tv_weight = tv_weight
        self.coarse_to_fine_steps = coarse_to_fine_steps
        self.density_bias = density_bias
        self.viewdir_max_deg = viewdir_max_deg
        # "auto" is resolved here, for the backend the field is built on.
        self.lookup = resolve_lookup(lookup)

    @property
    def has_mixture_heads(self) -> bool:
        return self.heads.has_mixture

    def at_step(self, step: Int[Array, ""] | int) -> "GridField":
        """The field as training step `step` (from 1) sees it: level `l` (coarsest 0) is
        weighted `clip(1 + (levels - 1) step / coarse_to_fine_steps - l, 0, 1)`."""
        if self.coarse_to_fine_steps <= 0:
            return self
        levels = self.encoding.num_levels
        progress = jnp.clip(jnp.asarray(step, jnp.float32) / self.coarse_to_fine_steps, 0.0, 1.0)
        visible = 1.0 + (levels - 1) * progress
        mask = jnp.clip(visible - jnp.arange(levels, dtype=jnp.float32), 0.0, 1.0)
        return eqx.tree_at(lambda f: f.level_weights, self, mask)

    def regulariser(self) -> Float[Array, ""]:
        if self.tv_weight == 0:
            return jnp.zeros(())
        return self.tv_weight * self.encoding.total_variation()

    def _unit_point(self, mean: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
        """A point of the box in the encoding's `[-1, 1]^3`."""
        low, high = jnp.asarray(self.box_min), jnp.asarray(self.box_max)
        half = 0.5 * (high - low)
        return (mean - (low + half)) / half

    def _density_from_rows(
        self, rows: Float[Array, "levels features"], point: Vec3, cov: Vec3
    ) -> tuple[Float[Array, ""], Float[Array, "out_features"]]:
        """The raw density (before noise and activation) and the geometry features, from the
        encoded `rows` of the point `point` (in `[-1, 1]^3`)."""
        weights = jax.lax.stop_gradient(self.level_weights)
        if self.scale_weighting:
            half = 0.5 * (jnp.asarray(self.box_max) - jnp.asarray(self.box_min))
            weights = weights * level_scale_weights(cov, half, self.encoding.cell_sizes)
        hidden = jax.nn.relu(self.density_layer((rows * weights[:, None]).reshape(-1)))
        out = self.density_out(hidden)
        raw = out[0] + self.density_bias
        if self.bounded:
            # Nothing lies outside the box: a large negative raw density gives zero density.
            raw = jnp.where(jnp.all(jnp.abs(point) <= 1.0), raw, -1e4)
        return raw, out[1:]

    def _density_branch(self, mean: Vec3, cov: Vec3) -> tuple[Float[Array, ""], Float[Array, "out_features"]]:
        """The raw density and the geometry features at one Gaussian."""
        point = self._unit_point(mean)
        return self._density_from_rows(self.encoding(point), point, cov)

    def density(self, mean: Vec3, cov: Vec3) -> Float[Array, ""]:
        return self.heads.density(self._density_branch(mean, cov)[0])

    def density_batch(self, means: Float[Array, "batch 3"], covs: Float[Array, "batch 3"]) -> Float[Array, " batch"]:
        if self.lookup == "vmap":
            return jax.vmap(self.density)(means, covs)
        points = self._unit_point(means)
        rows = self.encoding.encode_batch(points)
        return jax.vmap(lambda r, p, c: self.heads.density(self._density_from_rows(r, p, c)[0]))(rows, points, covs)

    def _decode(
        self,
        rows: Float[Array, "levels features"],
        point: Vec3,
        cov: Vec3,
        viewdir: Vec3,
        key: PRNGKey | None,
    ) -> FieldOutputs:
        """The outputs at one point from its encoded `rows`."""
        raw_density, geometry = self._density_from_rows(rows, point, cov)
        view_features = positional_encoding(viewdir, 0, self.viewdir_max_deg, append_identity=True)
        hidden = jax.nn.relu(self.view_layer(jnp.concatenate([geometry, view_features])))
        return self.heads(raw_density, hidden, key)

    def __call__(self, mean: Vec3, cov: Vec3, viewdir: Vec3, *, key: PRNGKey | None = None) -> FieldOutputs:
        point = self._unit_point(mean)
        return self._decode(self.encoding(point), point, cov, viewdir, key)

    def evaluate_batch(
        self,
        means: Float[Array, "batch 3"],
        covs: Float[Array, "batch 3"],
        viewdirs: Float[Array, "batch 3"],
        keys: RayKeys | None = None,
    ) -> FieldOutputs:
        if self.lookup == "vmap":
            return vmap_field(self, means, covs, viewdirs, keys)
        points = self._unit_point(means)
        rows = self.encoding.encode_batch(points)
        if keys is None:
            return jax.vmap(lambda r, p, c, v: self._decode(r, p, c, v, None))(rows, points, covs, viewdirs)
        return jax.vmap(self._decode)(rows, points, covs, viewdirs, keys)
