"""The dimension vocabulary and array aliases shared by every module.

Every jaxtyping shape string in the package uses these dimension names (`tests/test_vocabulary.py`
checks it):

- `*batch`: any leading batch dimensions (none, or rays in any layout, pixels, images).
- `batch`: exactly one flat batch dimension (a chunk of rays, a training batch, a flat list of points).
- `num_samples`: samples (frustums, mixture components) along one ray.
- `num_samples+1`: the interval edges that bound those samples.
- `3`: spatial x, y, z only (points, directions, covariances, pose rows).
- `channels`: colour channels (3 for RGB, 4 for RGBA files before compositing).
- `height width`: image dimensions.
- `num_views`: images (cameras) in a set of views.
- `num_pixels`: pixels of one view, flattened.
- `features`: the width of an encoding, a hidden layer or a feature map.
- `resolution`: grid cells per axis (the occupancy grid, one level of a grid field).
- `levels`: the levels of a multi-resolution grid encoding.

A few functions need a symbol of their own, for a dimension that differs from the shared one
within one call: the input and output sizes of a layer or an encoding (`in_features`,
`out_features`), a resize's `out_height out_width`, a sampler's edges before they are tied to
samples (`num_edges`, `num_prev_edges`, `num_draws`), a slice of the sample axis (`segment`),
a convolution's `kernel` size and a hash table's `entries`. A name prefixed with `_` only
documents a size and is not checked (sizes that differ between the entries of a tuple).
"""

from typing import TypeAlias

import numpy as np
from jaxtyping import Array, Bool, Float, Int, Key, PRNGKeyArray, Shaped, UInt32

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | int | np.floating | np.integer | Float[Array, ""] | Float[np.ndarray, ""]
PRNGKey: TypeAlias = PRNGKeyArray
# One key per ray or point (typed keys, or raw uint32 pairs), and four per ray (see `MixNeRF`).
RayKeys: TypeAlias = Key[Array, " batch"] | UInt32[Array, "batch 2"]
FourKeysPerRay: TypeAlias = Key[Array, "batch 4"] | UInt32[Array, "batch 4 2"]

# Per-ray quantities (a renderer sees one ray; vmap adds `*batch`).
Vec3: TypeAlias = Float[Array, "3"]
RGB: TypeAlias = Float[Array, "channels"]
Edges: TypeAlias = Float[Array, "num_samples+1"]
# Edges whose count is not yet tied to a sample dimension (a sampler's output, a previous
# level's edges); the samples they bound are `num_edges-1`.
SampledEdges: TypeAlias = Float[Array, "num_edges"]
PreviousEdges: TypeAlias = Float[Array, "num_prev_edges"]
PreviousWeights: TypeAlias = Float[Array, "num_prev_edges-1"]
PerSample: TypeAlias = Float[Array, "num_samples"]
PerSample3: TypeAlias = Float[Array, "num_samples 3"]
PerSampleRGB: TypeAlias = Float[Array, "num_samples channels"]

# Host-side (numpy) image data.
ImageArray: TypeAlias = Float[np.ndarray, "height width channels"]
ImageStack: TypeAlias = Float[np.ndarray, "num_views height width channels"]
DepthStack: TypeAlias = Float[np.ndarray, "num_views height width"]
PoseStack: TypeAlias = Float[np.ndarray, "num_views 3 4"]

__all__ = [
    "Array",
    "Bool",
    "DepthStack",
    "Edges",
    "Float",
    "ImageArray",
    "ImageStack",
    "Int",
    "PRNGKey",
    "RayKeys",
    "FourKeysPerRay",
    "PerSample",
    "PerSample3",
    "PerSampleRGB",
    "PoseStack",
    "RGB",
    "Scalar",
    "ScalarLike",
    "SampledEdges",
    "PreviousEdges",
    "PreviousWeights",
    "Shaped",
    "Vec3",
]
