"""The outputs every field shares: density, colour and MixNeRF's two heads."""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..._custom_types import PRNGKey
from .base import FieldOutputs, safe_norm


def dense(in_size: int, out_size: int, *, key: PRNGKey) -> eqx.nn.Linear:
    """A linear layer initialised as mip-NeRF's: Glorot-uniform kernel, zero bias."""
    layer = eqx.nn.Linear(in_size, out_size, key=key)
    weight = jax.nn.initializers.glorot_uniform()(key, (out_size, in_size))
    return eqx.tree_at(lambda lin: (lin.weight, lin.bias), layer, (weight, jnp.zeros(out_size)))


def apply_dense(
    layer: eqx.nn.Linear, x: Float[Array, "in_features"], matmul_dtype: Literal["float32", "bfloat16"]
) -> Float[Array, "out_features"]:
    """`layer(x)`, with the product optionally in bfloat16 and the result always float32.

    In bfloat16 the inputs and the kernel are rounded to bfloat16 and the product accumulates
    in float32 (`preferred_element_type`), so the tensor cores do the work while the bias,
    the activations after it and everything downstream (compositing, losses) stay float32.
    The parameters themselves stay float32, so the optimiser updates are not rounded.
    """
    if matmul_dtype == "float32":
        return layer(x)
    product = jnp.matmul(
        layer.weight.astype(jnp.bfloat16), x.astype(jnp.bfloat16), preferred_element_type=jnp.float32
    )
    return product + layer.bias


# exp's argument is capped here: exp(11) ~ 6e4 is opaque over any interval a sampler makes,
# and the cap keeps the forward pass finite (instant-ngp's truncated exponential caps the
# gradient instead; here the gradient above the cap is zero, which no trained field reaches).
_EXP_DENSITY_CAP = 11.0


def density_activation(raw: Float[Array, "*batch"], kind: str) -> Float[Array, "*batch"]:
    """The density from the raw output: `softplus(raw)` (mip-NeRF) or `exp(min(raw, 11))`
    (instant-ngp's exponential, capped)."""
    if kind == "exp":
        return jnp.exp(jnp.minimum(raw, _EXP_DENSITY_CAP))
    return jax.nn.softplus(raw)


class MixtureHeads(eqx.Module):
    """The heads of every field, so that MixNeRF's mixture and losses see one contract.

    From a field's raw density: training noise (`density_noise` times a standard normal, only
    when a key is given), then the activation. From its view features (after the view
    layer, so that they see the view direction): the colour `sigmoid * (1 + 2 p) - p` with
    `p = rgb_padding`, and for MixNeRF `beta = softplus(Dense(3))` and
    `ray_depth = ||Dense(3)||`.

    **Fields:**

    - `rgb_head`, `beta_head`, `depth_head`: the layers (`beta_head` and `depth_head` are
      `None` without mixture heads, the baseline).
    - `density_noise`, `rgb_padding`, `activation` (static): as above (`"softplus"` or
      `"exp"`).
    - `matmul_dtype` (static): the dtype of the heads' products (`apply_dense`).
    """

    rgb_head: eqx.nn.Linear
    beta_head: eqx.nn.Linear | None
    depth_head: eqx.nn.Linear | None
    density_noise: float = eqx.field(static=True)
    rgb_padding: float = eqx.field(static=True)
    activation: str = eqx.field(static=True)
    matmul_dtype: Literal["float32", "bfloat16"] = eqx.field(static=True)

    def __init__(
        self,
        in_size: int,
        *,
        mixture: bool,
        density_noise: float,
        rgb_padding: float,
        activation: str = "softplus",
        matmul_dtype: Literal["float32", "bfloat16"] = "float32",
        keys: tuple[PRNGKey, PRNGKey, PRNGKey],
    ):
        if activation not in ("softplus", "exp"):
            raise ValueError(f"density_activation must be 'softplus' or 'exp', got {activation!r}")
        rgb_key, beta_key, depth_key = keys
        self.rgb_head = dense(in_size, 3, key=rgb_key)
        self.beta_head = dense(in_size, 3, key=beta_key) if mixture else None
        self.depth_head = dense(in_size, 3, key=depth_key) if mixture else None
        self.density_noise = density_noise
        self.rgb_padding = rgb_padding
        self.activation = activation
        self.matmul_dtype = matmul_dtype

    @property
    def has_mixture(self) -> bool:
        return self.beta_head is not None and self.depth_head is not None

    def density(self, raw: Float[Array, ""], key: PRNGKey | None = None) -> Float[Array, ""]:
        """The density from the raw value `raw`, with training noise where `key` is given."""
        if key is not None and self.density_noise > 0:
            raw = raw + self.density_noise * jax.random.normal(key, (), raw.dtype)
        return density_activation(raw, self.activation)

    def __call__(
        self, raw_density: Float[Array, ""], features: Float[Array, "features"], key: PRNGKey | None
    ) -> FieldOutputs:
        """The field's outputs from its raw density and its view features."""
        density = self.density(raw_density, key)
        raw_rgb = apply_dense(self.rgb_head, features, self.matmul_dtype)
        rgb = jax.nn.sigmoid(raw_rgb) * (1 + 2 * self.rgb_padding) - self.rgb_padding
        beta = ray_depth = None
        if self.beta_head is not None and self.depth_head is not None:
            beta = jax.nn.softplus(apply_dense(self.beta_head, features, self.matmul_dtype))
            ray_depth = safe_norm(apply_dense(self.depth_head, features, self.matmul_dtype))
        return FieldOutputs(density=density, rgb=rgb, beta=beta, ray_depth=ray_depth)
