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
  each loop a plain row copy or row update (`benchmarks/README.md`, "The CPU step").

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
