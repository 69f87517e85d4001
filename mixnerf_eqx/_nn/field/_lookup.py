"""Interpolated lookups in a feature table, for the grid encodings.

A grid encoding reads, for every point, a few rows of a shared table (the texels around a
point's projection, the corners of its cell) and blends them with interpolation weights:
`out[..., :] = sum_k weights[k, ...] * table[indices[k, ...], :]`. Its gradient with respect
to the table is a scatter: every point adds `weights[..., k] * g` to the rows it read.

Two formulations compute the same values and gradients:

- per point (`"vmap"`): the encoding is written for one point and `jax.vmap` lifts it to the
  batch, so JAX differentiates each gather into a scatter of its own. This is the plain
  formulation and the one a GPU runs.
- for the whole batch (`"batched"`, `weighted_rows`): one gather per corner, summed in
  unrolled form, and a custom VJP that materialises the cotangent once and then scatters
  every corner's update into the table in a single scatter-add. On a CPU, XLA fuses the
  per-point formulation's gradient into loops that recompute the cotangent for every
  scattered element and reduce over the corner axis element by element; this one keeps
  each loop a plain row copy or row update (`benchmarks/LOG.md`, "The CPU step: the lookup,
  the allocator and the per-part profile"). The tri-plane encoding's product of three planes
  has one of its own, `plane_product`, whose gradient forms each plane's features once and
  scatters 2x2 windows.

Only the batch knows every point that shares a row, so this is the one place in the fields
written for a batch rather than for one point.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

LOOKUPS = ("auto", "vmap", "batched")


def resolve_lookup(lookup: str, backend: str | None = None) -> str:
    """The formulation `lookup` names; `"auto"` is `"batched"` on the CPU, `"vmap"` elsewhere."""
    if lookup not in LOOKUPS:
        raise ValueError(f"grid.lookup must be one of {', '.join(LOOKUPS)}, got {lookup!r}")
    if lookup != "auto":
        return lookup
    return "batched" if (backend or jax.default_backend()) == "cpu" else "vmap"


def _gathered_sum(
    table: Float[Array, "entries features"],
    indices: Int[Array, "corners *batch"],
    weights: Float[Array, "corners *batch"],
) -> Float[Array, "*batch features"]:
    # Unrolled over the corners (a sum over a small axis is a slow loop on the CPU), each
    # corner's indices contiguous and computed once: fused into the gathers, the arithmetic
    # that makes them would be repeated for every feature gathered.
    indices, weights = jax.lax.optimization_barrier((indices, weights))
    total = weights[0, ..., None] * table[indices[0]]
    for k in range(1, indices.shape[0]):
        total = total + weights[k, ..., None] * table[indices[k]]
    return total


@jax.custom_vjp
def weighted_rows(
    table: Float[Array, "entries features"],
    indices: Int[Array, "corners *batch"],
    weights: Float[Array, "corners *batch"],
) -> Float[Array, "*batch features"]:
    """`sum_k weights[k, ...] * table[indices[k, ...]]`, with a gradient that scatters once.

    Indices must lie in `[0, entries)` (the encodings clamp them); the weights may be anything.
    The gradient with respect to `weights` is exact too, so points can be differentiated
    through the interpolation as with the per-point formulation.
    """
    return _gathered_sum(table, indices, weights)


def _weighted_rows_fwd(table, indices, weights):
    return _gathered_sum(table, indices, weights), (table, indices, weights)


def _weighted_rows_bwd(residuals, cotangent):
    table, indices, weights = residuals
    # Materialised once: fused into the scatters below, the cotangent and the weights (and
    # whatever computes them) would be recomputed for every element scattered.
    cotangent, indices, weights = jax.lax.optimization_barrier((cotangent, indices, weights))
    features = table.shape[-1]
    corners = indices.shape[0]
    table_cotangent = jnp.zeros_like(table)
    for k in range(corners):
        update = (weights[k, ..., None] * cotangent).reshape(-1, features)
        table_cotangent = table_cotangent.at[indices[k].reshape(-1)].add(update)
    weights_cotangent = jnp.stack([jnp.sum(table[indices[k]] * cotangent, axis=-1) for k in range(corners)])
    return table_cotangent, None, weights_cotangent


weighted_rows.defvjp(_weighted_rows_fwd, _weighted_rows_bwd)


def _in_own_buffers(arrays, guard: Int[Array, ""]):
    """`arrays`, unchanged, each computed once into a buffer of its own.

    XLA's CPU compiler fuses cheap producers (gathers, products) into every consumer, so a
    value read by several loops is recomputed by each; `jax.lax.optimization_barrier` is gone
    before that pass runs. The operands of a conditional are buffers, so one stands here.
    `guard` is known to be non-negative (a clamped texel index): the zero branch is never
    taken and only keeps the conditional from being simplified away.
    """

    def zeros(xs):
        return jax.tree_util.tree_map(jnp.zeros_like, xs)

    return jax.lax.cond(guard < 0, zeros, lambda xs: xs, arrays)


@jax.custom_vjp
def plane_product(
    planes: Float[Array, "3 resolution resolution features"],
    indices: Int[Array, "3 4 *batch"],
    weights: Float[Array, "3 4 *batch"],
) -> Float[Array, "*batch features"]:
    """The product over a tri-plane level's three planes of each plane's bilinear lookup.

    `indices[p, k]` are rows of the planes flattened to `(3 * resolution^2, features)`, and the
    four corners of a plane are the 2x2 window that starts at corner 0, in the order
    `(0, 0), (0, 1), (1, 0), (1, 1)` (row, column), as `_plane_corners` in `grid.py` makes
    them; the windows must lie inside their planes (the encoding clamps them).

    The gradient is written for the CPU: the three planes' features and the cotangent are
    formed once (`_in_own_buffers`), each plane's cotangent is the product of the other
    two, and the four corners of all three planes are added into the planes in one windowed
    scatter. The gradient with respect to `weights` is exact too.
    """
    return _plane_product_fwd(planes, indices, weights)[0]


def _plane_product_fwd(planes, indices, weights):
    table = planes.reshape(-1, planes.shape[-1])
    features = tuple(_gathered_sum(table, indices[p], weights[p]) for p in range(3))
    return features[0] * features[1] * features[2], (planes, indices, weights, features)


def _plane_product_bwd(residuals, cotangent):
    planes, indices, weights, features = residuals
    guard = indices.reshape(-1)[0]
    res, width = planes.shape[1], planes.shape[-1]
    # The corner weights point by point, (3, *batch, 2, 2): transposed here once, not inside
    # the loops below, where a transpose or a stack stops XLA from vectorising them.
    corner_weights = jnp.moveaxis(weights, 1, -1).reshape(3, *weights.shape[2:], 2, 2)
    features, cotangent, corner_weights = _in_own_buffers((features, cotangent, corner_weights), guard)
    first, second, third = features
    # The cotangent of each plane's lookup.
    per_plane = (cotangent * second * third, cotangent * first * third, cotangent * first * second)
    numbers = jax.lax.ScatterDimensionNumbers(
        update_window_dims=(1, 2, 3), inserted_window_dims=(), scatter_dims_to_operand_dims=(0, 1)
    )
    gradients = []
    for plane in range(3):
        # Each window's corner 0 as (row, column) of its plane.
        starts = jnp.stack(jnp.divmod(indices[plane, 0] - plane * res * res, res), axis=-1).reshape(-1, 2)
        updates = corner_weights[plane][..., None] * per_plane[plane][..., None, None, :]
        gradients.append(
            jax.lax.scatter_add(
                jnp.zeros((res, res, width), planes.dtype),
                starts,
                updates.reshape(-1, 2, 2, width),
                numbers,
                mode=jax.lax.GatherScatterMode.CLIP,
            )
        )
    table = planes.reshape(-1, width)
    weights_cotangent = jnp.sum(table[indices] * jnp.stack(per_plane)[:, None], axis=-1)
    return jnp.stack(gradients), None, weights_cotangent


plane_product.defvjp(_plane_product_fwd, _plane_product_bwd)
