"""The MixNeRF training objective (paper eq. 11)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._config import LossConfig
from ._custom_types import PRNGKey
from ._model import MixNeRF, RenderOutputs
from ._rays import RayBundle
from ._render import blend_weights, distortion
from ._renderer import LevelOutputs


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Static loss weights: a term whose weight is zero is not computed at all.

    **Fields:**

    - `coarse_mse`: weight of the coarse level's MSE (mip-NeRF: 0.1).
    - `colour_nll`: whether lambda_C can be non-zero (its value comes per step).
    - `depth_nll`: lambda_D.
    - `regen_nll`: lambda_hat_C.
    - `nll_levels`: `"coarse"` (the released code) or `"both"`.
    - `distortion`: weight of the distortion loss (mip-NeRF 360), both levels.
    - `opacity`: weight of the mean ray opacity, both levels.
    - `opacity_entropy`: weight of the binary entropy of the ray opacity, both levels.
    - `unseen_entropy`: the same on the unseen-view patches.
    - `smoothness`: weight of the depth smoothness of unseen-view patches (RegNeRF).
    - `patch_size`: the side of those patches.
    """

    coarse_mse: float = 0.1
    colour_nll: bool = True
    depth_nll: float = 1e-3
    regen_nll: float = 1e-4
    nll_levels: str = "coarse"
    distortion: float = 0.0
    opacity: float = 0.0
    opacity_entropy: float = 0.0
    unseen_entropy: float = 0.0
    smoothness: float = 0.0
    patch_size: int = 8

    @classmethod
    def from_config(cls, loss: LossConfig, method: str) -> "LossWeights":
        """The weights `loss` sets for `method` (`"mipnerf"`: no mixture term at all)."""
        # The priors on the weights apply to both methods alike, so the comparison stays fair.
        priors = dict(
            distortion=loss.distortion_weight,
            opacity=loss.opacity_weight,
            opacity_entropy=loss.opacity_entropy_weight,
            unseen_entropy=loss.unseen_entropy_weight,
            smoothness=loss.depth_smoothness_weight,
            patch_size=loss.smoothness_patch_size,
        )
        if method == "mipnerf":
            return cls(
                coarse_mse=loss.coarse_mse_weight, colour_nll=False, depth_nll=0.0, regen_nll=0.0, **priors
            )
        return cls(
            **priors,
            coarse_mse=loss.coarse_mse_weight,
            colour_nll=loss.lambda_colour_start != 0 or loss.lambda_colour_end != 0,
            depth_nll=loss.lambda_depth,
            regen_nll=loss.lambda_regen,
            nll_levels=loss.nll_levels,
        )

    @property
    def uses_mixture(self) -> bool:
        return self.colour_nll or self.depth_nll > 0 or self.regen_nll > 0


class LossTerms(eqx.Module):
    """The terms of one step's loss, averaged over rays (zero where not computed).

    `mse_fine` and `mse_coarse` are per-element mean squared errors (over rays and
    channels), the quantity PSNR is defined on. The objective uses the squared error summed
    over the channels and averaged over rays (the paper's `||c_hat - c||^2`, and the released
    code), which is `channels` times larger: `total` holds that.
    """

    total: Float[Array, ""]
    mse_fine: Float[Array, ""]
    mse_coarse: Float[Array, ""]
    nll_colour: Float[Array, ""]
    nll_depth: Float[Array, ""]
    nll_regen: Float[Array, ""]
    regulariser: Float[Array, ""]
    distortion: Float[Array, ""]
    opacity: Float[Array, ""]
    opacity_entropy: Float[Array, ""]
    unseen_entropy: Float[Array, ""]
    smoothness: Float[Array, ""]


def opacity_entropy(acc: Float[Array, "*batch"], eps: float = 1e-4) -> Float[Array, ""]:
    """The mean binary entropy `-a log a - (1 - a) log(1 - a)` of the ray opacities `acc`.

    Zero where a ray is empty or opaque, `log 2` at half opacity: a prior that every ray
    either passes through empty space or stops at a solid surface. `acc` is clipped to
    `[eps, 1 - eps]`, which bounds the gradient by `log((1 - eps) / eps)`.
    """
    a = jnp.clip(acc, eps, 1.0 - eps)
    return jnp.mean(-(a * jnp.log(a) + (1.0 - a) * jnp.log1p(-a)))


def _level_nlls(
    model: MixNeRF,
    level: LevelOutputs,
    target_rgb: Float[Array, "batch channels"],
    direction_norm: Float[Array, "batch"],
    weights: LossWeights,
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    mixture = model.mixture
    outputs = level.field
    zero = jnp.zeros((), target_rgb.dtype)
    if mixture is None or outputs.beta is None or outputs.ray_depth is None:
        raise ValueError("the mixture losses need a model with a mixture and mixture heads")
    nll_colour = nll_depth = nll_regen = zero
    if weights.colour_nll:
        nll_colour = jnp.mean(
            jax.vmap(mixture.colour_nll)(level.weights, outputs.rgb, outputs.beta, target_rgb)
        )
    if weights.depth_nll > 0:
        nll_depth = jnp.mean(
            jax.vmap(mixture.depth_nll)(level.weights, outputs.ray_depth, outputs.beta, direction_norm)
        )
    if weights.regen_nll > 0:
        # Eq. 8: the same densities composited with the predicted ray depth in place of ||d||.
        regen_weights = jax.vmap(blend_weights)(outputs.density, level.t_edges, outputs.ray_depth)
        nll_regen = jnp.mean(
            jax.vmap(mixture.colour_nll)(regen_weights, outputs.rgb, outputs.beta, target_rgb)
        )
    return nll_colour, nll_depth, nll_regen


def loss_terms(
    outputs: RenderOutputs,
    model: MixNeRF,
    rays: RayBundle,
    target_rgb: Float[Array, "batch channels"],
    lambda_colour: Float[Array, ""],
    weights: LossWeights,
) -> LossTerms:
    """All terms of `L = MSE + lambda_C NLL_C + lambda_D NLL_D + lambda_hat_C NLL_hat_C + R + P`.

    `R` is the field's own regulariser (a grid's total variation; 0 for the MLP field). `P`
    holds the optional priors on the weights, all off in the paper's configs: the distortion
    loss, the mean opacity and the opacity's binary entropy, each summed over the two levels and
    averaged over rays (the unseen-view priors are added by `loss_fn`).

    `MSE = mean_rays ||rgb_fine - c||^2 + coarse_mse * mean_rays ||rgb_coarse - c||^2`, the
    squared error summed over the colour channels (paper eq. 11; the released `train.py`
    divides the sum over rays and channels by the number of rays). The NLLs are means over
    rays, on the coarse level unless `weights.nll_levels` says both.

    **Arguments:**

    - `outputs`: the model's render of `rays` (batch shape `(batch,)`).
    - `model`: the model (for its mixture).
    - `rays`: the rays; `||d||` is the ray-depth target.
    - `target_rgb`: ground-truth colours.
    - `lambda_colour`: lambda_C at this step.
    - `weights`: the static weights.
    """
    channels = target_rgb.shape[-1]
    mse_fine = jnp.mean((outputs.fine.rgb - target_rgb) ** 2)
    mse_coarse = jnp.mean((outputs.coarse.rgb - target_rgb) ** 2)
    regulariser = model.field.regulariser()
    # ||c_hat - c||^2 summed over the channels, averaged over rays: `channels` per-element MSEs.
    total = channels * (mse_fine + weights.coarse_mse * mse_coarse) + regulariser
    zero = jnp.zeros((), mse_fine.dtype)
    distortion_term = opacity_term = entropy_term = zero
    both_levels = (outputs.coarse, outputs.fine)
    if weights.distortion > 0:
        for level in both_levels:
            distortion_term = distortion_term + jnp.mean(
                jax.vmap(distortion)(level.weights, level.t_edges, rays.near[:, 0], rays.far[:, 0])
            )
        total = total + weights.distortion * distortion_term
    if weights.opacity > 0:
        opacity_term = sum(jnp.mean(level.acc) for level in both_levels)
        total = total + weights.opacity * opacity_term
    if weights.opacity_entropy > 0:
        entropy_term = sum(opacity_entropy(level.acc) for level in both_levels)
        total = total + weights.opacity_entropy * entropy_term
    nll_colour = nll_depth = nll_regen = zero
    if weights.uses_mixture:
        direction_norm = jnp.linalg.norm(rays.directions, axis=-1)
        levels = [outputs.coarse] if weights.nll_levels == "coarse" else [outputs.coarse, outputs.fine]
        for level in levels:
            colour, depth, regen = _level_nlls(model, level, target_rgb, direction_norm, weights)
            nll_colour, nll_depth, nll_regen = nll_colour + colour, nll_depth + depth, nll_regen + regen
        total = (
            total + lambda_colour * nll_colour + weights.depth_nll * nll_depth + weights.regen_nll * nll_regen
        )
    return LossTerms(
        total=total,
        mse_fine=mse_fine,
        mse_coarse=mse_coarse,
        nll_colour=nll_colour,
        nll_depth=nll_depth,
        nll_regen=nll_regen,
        regulariser=regulariser,
        distortion=distortion_term,
        opacity=opacity_term,
        opacity_entropy=entropy_term,
        unseen_entropy=zero,
        smoothness=zero,
    )


def depth_smoothness(outputs: RenderOutputs, rays: RayBundle, patch_size: int) -> Float[Array, ""]:
    """RegNeRF's depth smoothness of rendered patches, summed over the two levels.

    Per patch, the sum of squared differences between the depths of neighbouring pixels
    (down and right), with depth normalised to `s = (t - near) / (far - near)` so that the
    weight does not depend on the scene's units; averaged over patches.

    **Arguments:**

    - `outputs`: the render of the patches' rays, flattened patch by patch.
    - `rays`: those rays (for `near` and `far`).
    - `patch_size`: the patches' side.
    """
    span = (rays.far - rays.near)[:, 0]
    total = jnp.zeros((), span.dtype)
    for level in (outputs.coarse, outputs.fine):
        depth = ((level.depth - rays.near[:, 0]) / span).reshape(-1, patch_size, patch_size)
        down = jnp.sum((depth[:, 1:, :] - depth[:, :-1, :]) ** 2, axis=(1, 2))
        right = jnp.sum((depth[:, :, 1:] - depth[:, :, :-1]) ** 2, axis=(1, 2))
        total = total + jnp.mean(down + right)
    return total


def loss_fn(
    model: MixNeRF,
    rays: RayBundle,
    target_rgb: Float[Array, "batch channels"],
    lambda_colour: Float[Array, ""],
    weights: LossWeights,
    *,
    key: PRNGKey,
    patches: RayBundle | None = None,
) -> tuple[Float[Array, ""], LossTerms]:
    """Renders `rays` (and the unseen-view `patches`, in the same pass) in training mode and
    returns `(total loss, terms)`, with the priors on the patches (depth smoothness, opacity
    entropy) added where their weights are positive."""
    if patches is None or (weights.smoothness == 0 and weights.unseen_entropy == 0):
        outputs = model(rays, key=key)
        terms = loss_terms(outputs, model, rays, target_rgb, lambda_colour, weights)
        return terms.total, terms
    count = rays.batch_shape[0]
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), rays, patches)
    rendered = model(both, key=key)
    outputs = jax.tree_util.tree_map(lambda leaf: leaf[:count], rendered)
    patch_outputs = jax.tree_util.tree_map(lambda leaf: leaf[count:], rendered)
    terms = loss_terms(outputs, model, rays, target_rgb, lambda_colour, weights)
    zero = jnp.zeros_like(terms.total)
    smoothness = unseen_entropy = zero
    if weights.smoothness > 0:
        smoothness = depth_smoothness(patch_outputs, patches, weights.patch_size)
    if weights.unseen_entropy > 0:
        unseen_entropy = sum(
            opacity_entropy(level.acc) for level in (patch_outputs.coarse, patch_outputs.fine)
        )
    total = terms.total + weights.smoothness * smoothness + weights.unseen_entropy * unseen_entropy
    terms = eqx.tree_at(
        lambda t: (t.total, t.smoothness, t.unseen_entropy), terms, (total, smoothness, unseen_entropy)
    )
    return terms.total, terms
