"""The paper's field: mip-NeRF's MLP over integrated positional encodings, with MixNeRF's
extra heads (per-sample scale and ray depth) beside density and colour."""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..._custom_types import PRNGKey, RayKeys, Vec3
from ..encoding import integrated_positional_encoding, positional_encoding
from .base import AbstractField, FieldOutputs, vmap_density, vmap_field
from .heads import MixtureHeads, apply_dense, dense


class MipNeRFField(AbstractField):
    """The mip-NeRF MLP with MixNeRF's scale (`beta`) and ray-depth heads.

    Trunk of `depth` ReLU layers of `width` with the encoded input concatenated after layer
    `skip_layer`; density from the trunk; a linear bottleneck joined with the encoded view
    direction; one ReLU layer of `view_width`; colour from it. MixNeRF's heads sit after the
    view layer, so they see the view direction: `beta = softplus(Dense(3))` and
    `ray_depth = ||Dense(3)||`.

    **Fields (static):**

    - `min_deg`, `max_deg`: IPE frequencies `2^min_deg .. 2^(max_deg-1)`.
    - `viewdir_max_deg`: view-direction frequencies `2^0 .. 2^(viewdir_max_deg-1)`.
    - `skip_layer`: the trunk layer after which the input is concatenated again.
    - `density_bias`: shift of the raw density before the softplus (mip-NeRF: -1).
    - `matmul_dtype`: `"bfloat16"` runs every dense layer's product in bfloat16 with float32
      accumulation; the encodings, biases, activations and heads' outputs stay float32.

    `heads` (`MixtureHeads`, shared with `GridField`) holds the colour, `beta` and ray-depth
    layers, the training noise on the raw density (`density_noise`, its std) and the colour's
    padding (`rgb_padding`: `sigmoid * (1 + 2 p) - p`).
    """

    trunk: tuple[eqx.nn.Linear, ...]
    density_head: eqx.nn.Linear
    bottleneck: eqx.nn.Linear
    view_layer: eqx.nn.Linear
    heads: MixtureHeads
    min_deg: int = eqx.field(static=True)
    max_deg: int = eqx.field(static=True)
    viewdir_max_deg: int = eqx.field(static=True)
    skip_layer: int = eqx.field(static=True)
    density_bias: float = eqx.field(static=True)
    matmul_dtype: Literal["float32", "bfloat16"] = eqx.field(static=True)

    def __init__(
        self,
        *,
        width: int = 256,
        depth: int = 8,
        view_width: int = 128,
        skip_layer: int = 4,
        min_deg: int = 0,
        max_deg: int = 16,
        viewdir_max_deg: int = 4,
        density_noise: float = 1.0,
        density_bias: float = -1.0,
        rgb_padding: float = 0.001,
        mixture_heads: bool = True,
        matmul_dtype: Literal["float32", "bfloat16"] = "float32",
        key: PRNGKey,
    ):
        if depth < 1 or width < 1 or view_width < 1:
            raise ValueError("depth, width and view_width must be positive")
        if not 0 <= min_deg < max_deg:
            raise ValueError(f"need 0 <= min_deg < max_deg, got {min_deg}, {max_deg}")
        if matmul_dtype not in ("float32", "bfloat16"):
            raise ValueError(f"matmul_dtype must be 'float32' or 'bfloat16', got {matmul_dtype!r}")
        input_size = 2 * 3 * (max_deg - min_deg)
        view_size = 3 + 2 * 3 * viewdir_max_deg
        keys = iter(jax.random.split(key, depth + 6))
        trunk = []
        in_size = input_size
        for layer_index in range(depth):
            trunk.append(dense(in_size, width, key=next(keys)))
            in_size = width + input_size if self._skips_after(layer_index, skip_layer) else width
        self.trunk = tuple(trunk)
        self.density_head = dense(in_size, 1, key=next(keys))
        self.bottleneck = dense(in_size, width, key=next(keys))
        self.view_layer = dense(width + view_size, view_width, key=next(keys))
        self.heads = MixtureHeads(
            view_width,
            mixture=mixture_heads,
            density_noise=density_noise,
            rgb_padding=rgb_padding,
            matmul_dtype=matmul_dtype,
            keys=(next(keys), next(keys), next(keys)),
        )
        self.min_deg = min_deg
        self.max_deg = max_deg
        self.viewdir_max_deg = viewdir_max_deg
        self.skip_layer = skip_layer
        self.density_bias = density_bias
        self.matmul_dtype = matmul_dtype

    def _dense(self, layer: eqx.nn.Linear, x: Float[Array, "in_features"]) -> Float[Array, "out_features"]:
        return apply_dense(layer, x, self.matmul_dtype)

    @staticmethod
    def _skips_after(layer_index: int, skip_layer: int) -> bool:
        return skip_layer > 0 and layer_index > 0 and layer_index % skip_layer == 0

    @property
    def has_mixture_heads(self) -> bool:
        return self.heads.has_mixture

    def _trunk(self, mean: Vec3, cov: Vec3) -> tuple[Float[Array, "features"], Float[Array, ""]]:
        """The trunk's last features and the raw density (before noise and softplus)."""
        inputs = integrated_positional_encoding(mean, cov, self.min_deg, self.max_deg)
        hidden = inputs
        for layer_index, layer in enumerate(self.trunk):
            hidden = jax.nn.relu(self._dense(layer, hidden))
            if self._skips_after(layer_index, self.skip_layer):
                hidden = jnp.concatenate([hidden, inputs])
        return hidden, self._dense(self.density_head, hidden)[0] + self.density_bias

    def density(self, mean: Vec3, cov: Vec3) -> Float[Array, ""]:
        return self.heads.density(self._trunk(mean, cov)[1])

    def density_batch(self, means: Float[Array, "batch 3"], covs: Float[Array, "batch 3"]) -> Float[Array, " batch"]:
        return vmap_density(self, means, covs)

    def evaluate_batch(
        self,
        means: Float[Array, "batch 3"],
        covs: Float[Array, "batch 3"],
        viewdirs: Float[Array, "batch 3"],
        keys: RayKeys | None = None,
    ) -> FieldOutputs:
        return vmap_field(self, means, covs, viewdirs, keys)

    def regulariser(self) -> Float[Array, ""]:
        return jnp.zeros(())  # the MLP's training has no term of its own

    def at_step(self, step: Int[Array, ""] | int) -> "MipNeRFField":
        del step
        return self  # no schedule

    def __call__(self, mean: Vec3, cov: Vec3, viewdir: Vec3, *, key: PRNGKey | None = None) -> FieldOutputs:
        hidden, raw_density = self._trunk(mean, cov)
        view_features = positional_encoding(viewdir, 0, self.viewdir_max_deg, append_identity=True)
        hidden = jnp.concatenate([self._dense(self.bottleneck, hidden), view_features])
        hidden = jax.nn.relu(self._dense(self.view_layer, hidden))
        return self.heads(raw_density, hidden, key)
