"""The dimension vocabulary and array aliases shared by every module.

Dimension names used throughout the package:

- `*batch`: any leading batch dimensions (rays, pixels, images).
- `num_samples`: samples (frustums, mixture components) along one ray.
- `num_samples+1`: the interval edges that bound those samples.
- `channels`: colour channels (always 3 here, named for readability).
- `height width`: image dimensions.
- `features`: the width of an encoding or hidden layer.
"""

from typing import TypeAlias

import numpy as np
from jaxtyping import Array, Bool, Float, Int, Key, PRNGKeyArray, Shaped, UInt32

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | Float[Array, ""]
PRNGKey: TypeAlias = PRNGKeyArray
# One key per ray (typed keys, or raw uint32 pairs), and four per ray (see `MixNeRF`).
RayKeys: TypeAlias = Key[Array, " rays"] | UInt32[Array, "rays 2"]
FourKeysPerRay: TypeAlias = Key[Array, "rays 4"] | UInt32[Array, "rays 4 2"]

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
ImageArray: TypeAlias = Float[np.ndarray, "height width 3"]
ImageStack: TypeAlias = Float[np.ndarray, "num_views height width 3"]
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
