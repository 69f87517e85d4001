"""A function over many rays in fixed-size chunks: bounded device memory, one compilation.

Rendering (`_inference.rendering`) and the predictive pass (`_predictive`) both map their
jitted per-chunk work over an image's rays with `map_ray_chunks` and join the host copies with
`join_chunks`.
"""

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._util.interrupt import raise_if_interrupted
from .rays import RayBundle


def map_ray_chunks(
    fn: Callable[[RayBundle, int, Any], Any], rays: RayBundle, chunk: int, extra: Any = None
) -> tuple[list[Any], int]:
    """`fn(piece, real, extra_piece)` over `rays`, `chunk` rays at a time, on the host.

    The rays are flattened and padded once to a whole number of chunks (padding repeats the
    last ray, and the last row of `extra`, an array with one row per ray or `None`), so every
    call sees exactly `chunk` rays, of which the first `real` are real: a jitted `fn` compiles
    once, and device memory is bounded by the chunk, not by the image. Each chunk is queued
    before the previous one's outputs are copied back, so the device does not wait for the
    host between chunks. A Ctrl-C is taken between chunks.

    **Returns:**

    The outputs of every chunk, copied to the host (untrimmed: the last chunk's padding is
    still there), and the number of rays.
    """
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    flat = rays.reshape(-1)
    count = flat.origins.shape[0]
    # Memory follows the chunk: never ask for more than the rays there are.
    chunk = max(1, min(chunk, count))
    num_chunks = -(-count // chunk)
    pad = num_chunks * chunk - count

    def padded(x):
        x = jnp.asarray(x)
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    flat = jax.tree_util.tree_map(padded, flat)
    if extra is not None:
        extra = padded(jnp.asarray(extra).reshape(count, -1))
    chunks = flat.reshape(num_chunks, chunk)
    parts, pending = [], None
    for index in range(num_chunks):
        raise_if_interrupted()
        start = index * chunk
        extra_piece = None if extra is None else extra[start : start + chunk]
        outputs = fn(chunks[index], min(chunk, count - start), extra_piece)
        # JAX dispatches asynchronously: this chunk is queued before the previous one is
        # copied back, which is where the host waits.
        if pending is not None:
            parts.append(jax.device_get(pending))
        pending = outputs
    if pending is not None:
        parts.append(jax.device_get(pending))
    return parts, count


def join_chunks(parts: Sequence[np.ndarray], count: int, axis: int = 0) -> np.ndarray:
    """The chunks' arrays of `map_ray_chunks` joined along the rays' `axis`, padding dropped."""
    joined = np.concatenate([np.asarray(part) for part in parts], axis=axis)
    return joined[(slice(None),) * axis + (slice(0, count),)]
