"""The MixNeRF training objective (paper eq. 11), as a registry of named terms.

A term is a function of the rendered levels (and of the rays, the target colours and the
unseen-view patches) and a weight, a `[loss]` key of the config. The total, the training log,
the range check of the weights and `LossTerms` all come from the registry, so a new term is
its function, `register_loss_term(LossTerm(...))` and its line in `LossConfig`, declared with
`loss_weight` (which range-checks it):

    def mean_depth(inputs: LossInputs) -> Float[Array, ""]:
        return jnp.mean(inputs.outputs.fine.depth)

    register_loss_term(LossTerm("mean_depth", mean_depth, weight="mean_depth_weight"))

The terms add up in registration order (the paper's terms first, then the priors).
"""

import dataclasses
from collections.abc import Callable, Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._config import LossConfig, loss_weight_keys
from .._custom_types import PRNGKey
from .._nn.budget import SampleBudget
from .._nn.compositing import blend_weights, distortion, log_transmittance
from .._nn.model import MixNeRF, RenderOutputs
from .._nn.rays import RayBundle
from .._nn.renderer import LevelOutputs


@dataclasses.dataclass(frozen=True)
class LossTerm:
    """One named term of the objective.

    **Fields:**

    - `name`: its key in `LossTerms` and in the training log.
    - `compute`: `LossInputs -> scalar`, the term's value.
    - `weight`: the `[loss]` key of its weight (at least 0; a zero weight skips the term);
      `None`: weight 1, always computed (the fine MSE, the field's regulariser).
    - `mixture`: one of MixNeRF's own terms (off for the baseline, `method = "mipnerf"`).
    - `patches`: computed on the unseen-view patches (which are drawn and rendered only when
      such a term has a non-zero weight).
    - `per_channel`: the value is a per-element mean over rays and colour channels (the
      quantity PSNR is defined on), while the objective sums the squared error over the
      channels: the total takes `channels` times the value.
    - `scheduled`: the weight follows a schedule from `<weight>_start` to `<weight>_end`, and
      its value at the step is given to `loss_terms` (lambda_C; only one term may have one).
    """

    name: str
    compute: Callable[["LossInputs"], Float[Array, ""]]
    weight: str | None = None
    mixture: bool = False
    patches: bool = False
    per_channel: bool = False
    scheduled: bool = False

    def weight_keys(self) -> tuple[str, ...]:
        if self.weight is None:
            return ()
        return (f"{self.weight}_start", f"{self.weight}_end") if self.scheduled else (self.weight,)


_REGISTRY: dict[str, LossTerm] = {}


def register_loss_term(term: LossTerm) -> LossTerm:
    """Adds `term` to the objective (after the terms registered before it)."""
    if term.name in _REGISTRY or term.name == "total":
        raise ValueError(f"a loss term named {term.name!r} is already registered")
    if term.scheduled and (term.weight is None or any(other.scheduled for other in _REGISTRY.values())):
        raise ValueError("one loss term at most has a scheduled weight, and it needs a weight key")
    _REGISTRY[term.name] = term
    return term


def unregister_loss_term(name: str) -> None:
    """Removes the term `name` from the objective."""
    _REGISTRY.pop(name)


def loss_term_names() -> tuple[str, ...]:
    """The names of the registered terms, in the order they add up."""
    return tuple(_REGISTRY)


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """The static weights of one run's terms: a term whose weight is zero is not computed.

    **Fields:**

    - `weights`: `(name, weight)` of every registered term; a scheduled term's weight is 1
      where its schedule is not zero throughout (its value comes per step).
    - `nll_levels`: the levels the NLLs apply to, `"coarse"` (the released code) or `"both"`.
    - `patch_size`: the side of the unseen-view patches.
    - `nll_trains_colour`: whether the colour NLLs' gradient reaches the samples' colours.
    """

    weights: tuple[tuple[str, float], ...]
    nll_levels: str = "coarse"
    patch_size: int = 8
    nll_trains_colour: bool = True

    @classmethod
    def from_config(cls, loss: LossConfig, method: str) -> "LossWeights":
        """The weights `loss` sets for `method` (`"mipnerf"`: no mixture term at all).

        The priors on the weights apply to both methods alike, so the comparison stays fair.
        """
        weights = []
        declared = loss_weight_keys(loss)
        for term in _REGISTRY.values():
            undeclared = [key for key in term.weight_keys() if key not in declared]
            if undeclared:
                raise ValueError(
                    f"loss term {term.name!r} is weighted by loss.{undeclared[0]}, which the [loss] section does "
                    "not declare a loss weight: add it there with loss_weight(default)"
                )
            if term.mixture and method == "mipnerf":
                value = 0.0
            elif term.weight is None:
                value = 1.0
            elif term.scheduled:
                value = float(any(getattr(loss, key) != 0 for key in term.weight_keys()))
            else:
                value = float(getattr(loss, term.weight))
            weights.append((term.name, value))
        return cls(
            tuple(weights),
            nll_levels=loss.nll_levels,
            patch_size=loss.smoothness_patch_size,
            nll_trains_colour=loss.nll_trains_colour,
        )

    def __getitem__(self, name: str) -> float:
        return dict(self.weights)[name]

    def replace(self, **weights: float) -> "LossWeights":
        """These weights with those of the terms named changed (`replace(nll_depth=0.0)`)."""
        unknown = set(weights) - {name for name, _ in self.weights}
        if unknown:
            raise ValueError(f"no loss terms named {sorted(unknown)}; the terms are {list(_REGISTRY)}")
        changed = tuple((name, float(weights.get(name, value))) for name, value in self.weights)
        return dataclasses.replace(self, weights=changed)

    def active(self) -> Iterator[LossTerm]:
        """The registered terms these weights compute."""
        for name, value in self.weights:
            if value != 0:
                yield _REGISTRY[name]

    @property
    def needs_patches(self) -> bool:
        return any(term.patches for term in self.active())

    @property
    def uses_mixture(self) -> bool:
        return any(term.mixture for term in self.active())


def needs_patches(loss: LossConfig) -> bool:
    """Whether `loss` weights a term of the unseen-view patches (which are then drawn), for
    either method (MixNeRF's terms are a superset of the baseline's)."""
    return LossWeights.from_config(loss, "mixnerf").needs_patches


@dataclasses.dataclass(frozen=True)
class LossInputs:
    """What a term may read.

    **Fields:**

    - `outputs`: the render of the training rays (batch shape `(batch,)`).
    - `model`: the model (its mixture, its field's regulariser).
    - `rays`: the training rays; `||d||` is the ray-depth target.
    - `target_rgb`: their true colours.
    - `weights`: the static weights (and the terms' options: `nll_levels`, `patch_size`).
    - `patch_outputs`, `patches`: the render of the unseen-view patches and their rays,
      flattened patch by patch (`None` unless a patch term is weighted).
    """

    outputs: RenderOutputs
    model: MixNeRF
    rays: RayBundle
    target_rgb: Float[Array, "batch channels"]
    weights: LossWeights
    patch_outputs: RenderOutputs | None = None
    patches: RayBundle | None = None

    @property
    def both_levels(self) -> tuple[LevelOutputs, LevelOutputs]:
        return (self.outputs.coarse, self.outputs.fine)

    @property
    def nll_levels(self) -> tuple[LevelOutputs, ...]:
        coarse = self.weights.nll_levels == "coarse"
        return (self.outputs.coarse,) if coarse else self.both_levels


class LossTerms(eqx.Module):
    """The terms of one step's loss, averaged over rays (zero where not computed).

    `terms["mse_fine"]` and `terms["mse_coarse"]` are per-element mean squared errors (over
    rays and channels), the quantity PSNR is defined on. The objective uses the squared error
    summed over the channels and averaged over rays (the paper's `||c_hat - c||^2`, and the
    released code), which is `channels` times larger: `total` holds that.
    """

    total: Float[Array, ""]
    values: dict[str, Float[Array, ""]]
    # With a sample budget: field evaluations made, live coarse and fine samples, live samples
    # dropped (they did not fit the buffers), and the dense render's coarse and fine samples.
    samples: Float[Array, "6"] | None = None

    def __getitem__(self, name: str) -> Float[Array, ""]:
        return self.values[name]


def opacity_entropy(acc: Float[Array, "*batch"], eps: float = 1e-4) -> Float[Array, ""]:
    """The mean binary entropy `-a log a - (1 - a) log(1 - a)` of the ray opacities `acc`.

    Zero where a ray is empty or opaque, `log 2` at half opacity: a prior that every ray
    either passes through empty space or stops at a solid surface. `acc` is clipped to
    `[eps, 1 - eps]`, which bounds the gradient by `log((1 - eps) / eps)`.
    """
    a = jnp.clip(acc, eps, 1.0 - eps)
    return jnp.mean(-(a * jnp.log(a) + (1.0 - a) * jnp.log1p(-a)))


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


def _summed(values) -> Float[Array, ""]:
    """The sum of `values`, from zero, in order."""
    return sum(values, 0.0)


def _mixture_of(inputs: LossInputs, level: LevelOutputs):
    mixture, outputs = inputs.model.mixture, level.field
    if mixture is None or outputs.beta is None or outputs.ray_depth is None:
        raise ValueError("the mixture losses need a model with a mixture and mixture heads")
    return mixture, outputs


def _log_transmittance(mixture, density, t_edges, step_scale):
    """The log transmittance under those weights, where the mixture has a background
    component to weight with it (`None` otherwise: nothing is computed)."""
    if getattr(mixture, "background", None) is None:
        return None
    return jax.vmap(log_transmittance)(density, t_edges, step_scale)


def _component_colours(inputs: LossInputs, rgb):
    """The samples' colours as the colour NLLs' component locations: without a gradient when
    `loss.nll_trains_colour` is false."""
    return rgb if inputs.weights.nll_trains_colour else jax.lax.stop_gradient(rgb)


def _nll_colour(inputs: LossInputs) -> Float[Array, ""]:
    """NLL_C (eq. 7): the colour's mixture NLL under the rendered weights."""
    direction_norm = jnp.linalg.norm(inputs.rays.directions, axis=-1)

    def level_nll(level):
        mixture, outputs = _mixture_of(inputs, level)
        log_t = _log_transmittance(mixture, outputs.density, level.t_edges, direction_norm)
        rgb = _component_colours(inputs, outputs.rgb)
        nll = jax.vmap(mixture.colour_nll)(level.weights, rgb, outputs.beta, inputs.target_rgb, log_t)
        return jnp.mean(nll)

    return _summed(level_nll(level) for level in inputs.nll_levels)


def _nll_depth(inputs: LossInputs) -> Float[Array, ""]:
    """NLL_D (eq. 9): the ray depth `||d||`'s mixture NLL."""
    direction_norm = jnp.linalg.norm(inputs.rays.directions, axis=-1)

    def level_nll(level):
        mixture, outputs = _mixture_of(inputs, level)
        nll = jax.vmap(mixture.depth_nll)(level.weights, outputs.ray_depth, outputs.beta, direction_norm)
        return jnp.mean(nll)

    return _summed(level_nll(level) for level in inputs.nll_levels)


def _nll_regen(inputs: LossInputs) -> Float[Array, ""]:
    """NLL_hat_C (eq. 8): the same densities composited with the predicted ray depth in
    place of `||d||`, and the colour's NLL under those weights."""

    def level_nll(level):
        mixture, outputs = _mixture_of(inputs, level)
        regen_weights = jax.vmap(blend_weights)(outputs.density, level.t_edges, outputs.ray_depth)
        log_t = _log_transmittance(mixture, outputs.density, level.t_edges, outputs.ray_depth)
        rgb = _component_colours(inputs, outputs.rgb)
        nll = jax.vmap(mixture.colour_nll)(regen_weights, rgb, outputs.beta, inputs.target_rgb, log_t)
        return jnp.mean(nll)

    return _summed(level_nll(level) for level in inputs.nll_levels)


def _distortion(inputs: LossInputs) -> Float[Array, ""]:
    near, far = inputs.rays.near[:, 0], inputs.rays.far[:, 0]
    return _summed(
        jnp.mean(jax.vmap(distortion)(level.weights, level.t_edges, near, far))
        for level in inputs.both_levels
    )


def _unseen_entropy(inputs: LossInputs) -> Float[Array, ""]:
    patches = inputs.patch_outputs
    return _summed(opacity_entropy(level.acc) for level in (patches.coarse, patches.fine))


# The paper's objective (eq. 11), then the optional priors on the weights (all off in the
# paper's configs), each summed over the two levels and averaged over rays or patches.
for _term in (
    LossTerm(
        "mse_fine",
        lambda inputs: jnp.mean((inputs.outputs.fine.rgb - inputs.target_rgb) ** 2),
        per_channel=True,
    ),
    LossTerm(
        "mse_coarse",
        lambda inputs: jnp.mean((inputs.outputs.coarse.rgb - inputs.target_rgb) ** 2),
        weight="coarse_mse_weight",
        per_channel=True,
    ),
    LossTerm("regulariser", lambda inputs: inputs.model.field.regulariser()),
    LossTerm("distortion", _distortion, weight="distortion_weight"),
    LossTerm(
        "opacity",
        lambda inputs: _summed(jnp.mean(level.acc) for level in inputs.both_levels),
        weight="opacity_weight",
    ),
    LossTerm(
        "opacity_entropy",
        lambda inputs: _summed(opacity_entropy(level.acc) for level in inputs.both_levels),
        weight="opacity_entropy_weight",
    ),
    LossTerm("nll_colour", _nll_colour, weight="lambda_colour", mixture=True, scheduled=True),
    LossTerm("nll_depth", _nll_depth, weight="lambda_depth", mixture=True),
    LossTerm("nll_regen", _nll_regen, weight="lambda_regen", mixture=True),
    LossTerm(
        "smoothness",
        lambda inputs: depth_smoothness(inputs.patch_outputs, inputs.patches, inputs.weights.patch_size),
        weight="depth_smoothness_weight",
        patches=True,
    ),
    LossTerm("unseen_entropy", _unseen_entropy, weight="unseen_entropy_weight", patches=True),
):
    register_loss_term(_term)


def loss_terms(
    outputs: RenderOutputs,
    model: MixNeRF,
    rays: RayBundle,
    target_rgb: Float[Array, "batch channels"],
    lambda_colour: Float[Array, ""],
    weights: LossWeights,
    *,
    patch_outputs: RenderOutputs | None = None,
    patches: RayBundle | None = None,
) -> LossTerms:
    """Every registered term, and their weighted sum: by default
    `L = MSE + lambda_C NLL_C + lambda_D NLL_D + lambda_hat_C NLL_hat_C + R + P`.

    `R` is the field's own regulariser (a grid's total variation; 0 for the MLP field). `P`
    holds the optional priors on the weights, all off in the paper's configs: the distortion
    loss, the mean opacity and the opacity's binary entropy, each summed over the two levels
    and averaged over rays, and the unseen-view priors on `patches`.

    `MSE = mean_rays ||rgb_fine - c||^2 + coarse_mse * mean_rays ||rgb_coarse - c||^2`, the
    squared error summed over the colour channels (paper eq. 11; the released `train.py`
    divides the sum over rays and channels by the number of rays). The NLLs are means over
    rays, on the coarse level unless `weights.nll_levels` says both.

    **Arguments:**

    - `outputs`: the model's render of `rays` (batch shape `(batch,)`).
    - `model`: the model (for its mixture).
    - `rays`: the rays; `||d||` is the ray-depth target.
    - `target_rgb`: ground-truth colours.
    - `lambda_colour`: the scheduled weight at this step (lambda_C).
    - `weights`: the static weights.
    - `patch_outputs`, `patches`: the unseen-view patches' render and rays (needed where a
      patch term is weighted).
    """
    inputs = LossInputs(outputs, model, rays, target_rgb, weights, patch_outputs, patches)
    channels = target_rgb.shape[-1]
    zero = jnp.zeros((), outputs.fine.rgb.dtype)
    values = {name: zero for name, _ in weights.weights}
    active = list(weights.active())
    if any(term.patches for term in active) and patch_outputs is None:
        raise ValueError("a term of the unseen-view patches is weighted, but no patches were rendered")
    for term in active:
        values[term.name] = term.compute(inputs)
    # The squared errors first, summed over the channels; then the rest, in order.
    total = channels * _summed(weights[term.name] * values[term.name] for term in active if term.per_channel)
    for term in active:
        if not term.per_channel:
            weight = lambda_colour if term.scheduled else weights[term.name]
            total = total + weight * values[term.name]
    return LossTerms(total=total, values=values)


def _render(
    model: MixNeRF, rays: RayBundle, key: PRNGKey, budget: SampleBudget | None
) -> tuple[RenderOutputs, Float[Array, "6"] | None]:
    """The training render: dense, or within `budget`; with a budget, also `LossTerms.samples`."""
    if budget is None:
        return model(rays, key=key), None
    num_rays = rays.batch_shape[0]
    outputs, report = model.render_within(rays, budget, key=key)
    counts = jnp.stack(
        [
            jnp.asarray(float(report.evaluations)),
            report.coarse_live.astype(float),
            report.fine_live.astype(float),
            report.dropped.astype(float),
            jnp.asarray(float(num_rays * model.coarse_sampler.num_samples)),
            jnp.asarray(float(num_rays * model.fine_sampler.num_samples)),
        ]
    )
    return outputs, counts


def loss_fn(
    model: MixNeRF,
    rays: RayBundle,
    target_rgb: Float[Array, "batch channels"],
    lambda_colour: Float[Array, ""],
    weights: LossWeights,
    *,
    key: PRNGKey,
    patches: RayBundle | None = None,
    budget: SampleBudget | None = None,
) -> tuple[Float[Array, ""], LossTerms]:
    """Renders `rays` (and the unseen-view `patches`, in the same pass, where a patch term is
    weighted) in training mode and returns `(total loss, terms)`. With a `budget`, the render
    evaluates only the live samples that fit it (`MixNeRF.render_within`)."""
    if patches is None or not weights.needs_patches:
        rendered, counts = _render(model, rays, key, budget)
        terms = loss_terms(rendered, model, rays, target_rgb, lambda_colour, weights)
        terms = dataclasses.replace(terms, samples=counts)
        return terms.total, terms
    count = rays.batch_shape[0]
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), rays, patches)
    rendered, counts = _render(model, both, key, budget)
    outputs = jax.tree_util.tree_map(lambda leaf: leaf[:count], rendered)
    patch_outputs = jax.tree_util.tree_map(lambda leaf: leaf[count:], rendered)
    terms = loss_terms(
        outputs,
        model,
        rays,
        target_rgb,
        lambda_colour,
        weights,
        patch_outputs=patch_outputs,
        patches=patches,
    )
    terms = dataclasses.replace(terms, samples=counts)
    return terms.total, terms
