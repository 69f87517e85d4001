"""MixNeRF's mixture of Laplace densities (paper eqs. 4-6): per-sample components whose mixing
coefficients are the normalised blending weights, and the log-likelihoods the losses use."""

from typing import Literal

import equinox as eqx
import jax.numpy as jnp
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float

from ..._custom_types import RGB, PerSample, PerSampleRGB
from .base import AbstractMixture


def laplace_log_density(
    x: Float[Array, "*#batch"], location: Float[Array, "*#batch"], scale: Float[Array, "*#batch"]
) -> Float[Array, "*#batch"]:
    """`log( exp(-|x - location| / scale) / (2 scale) )`, elementwise with broadcasting.

    Finite, with finite gradients, for every scale down to the smallest normal float. Two
    guards make that so. `1 / scale` is formed as `exp(-log(scale))`: then no local
    derivative is `1 / scale^2`, which overflows float32 below about 1e-19 and, multiplied by
    the exactly-zero responsibility of such a component, would give `0 * inf = NaN` in the
    backward pass. And the residual term is clipped at `-1e30`, far below any term that can
    matter in a mixture, so that a sum over channels cannot overflow to `-inf`.
    """
    tiny = jnp.finfo(scale.dtype).tiny
    log_scale = jnp.log(jnp.maximum(scale, tiny))
    residual_term = jnp.maximum(-jnp.abs(x - location) * jnp.exp(-log_scale), -1e30)
    return residual_term - log_scale - jnp.log(2.0)


def _log_where_positive(x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`log x` where `x > 0`, `-inf` elsewhere, with no NaN gradient from `log(0)`."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), -jnp.inf)


class LaplaceMixture(AbstractMixture):
    """MixNeRF's mixture of per-sample Laplace densities.

    The default reproduces the released implementation's loss function, evaluated stably in
    log space: `-log(sum_j pi_j prod_c Laplace_jc + floor)` is computed as
    `-logaddexp(logsumexp_j(log pi_j + sum_c log Laplace_jc), log floor)`, which equals the
    linear-space value wherever that is representable, and never underflows, overflows or
    returns NaN.

    **Fields (static):**

    - `weight_eps`: `pi_j = w_j / (sum_m w_m + weight_eps)`. With `0` (the released code) an
      empty ray gets uniform coefficients instead of the released NaN; with `> 0` an empty
      ray's coefficients vanish, so it contributes only the floor (a constant).
    - `likelihood_floor`: the `+1e-12` of the released code; `None` for the exact NLL (an
      empty ray, whose exact NLL is infinite, then contributes 0).
    - `depth_scale`: `"colour"` reuses the three colour scales, so the depth likelihood is
      the product of three Laplace densities of the same residual (the released code);
      `"single"` uses one Laplace density whose scale is the mean of the three.
    - `evaluation`: `"log"` (stable, default) or `"linear"` (the released arithmetic, which
      underflows in float32 for poorly fitted rays; for comparison only).
    - `background`: `None` (the paper and the released code: the colour mixture's
      coefficients are the weights normalised over the samples, so a ray that passes through
      empty space onto a white background must still be explained by its samples' colours).
      An RGB colour: the light that passes the last sample is a component of its own, the
      background colour with Laplace scale `background_scale` per channel, and the
      coefficients are the unnormalised weights `w_j` and the ray's transmittance
      `T = exp(-sum_j sigma_j delta_j)` (they sum to one without normalising; `weight_eps`
      does not apply). The losses give `T` as its logarithm, from the densities, so that an
      opaque floater in front of the background keeps its gradient toward transparency.
      This is the mixture whose mean is the rendered colour over that background. The depth
      mixture keeps the normalised weights: the background has no depth to predict.
    - `background_scale`: the background component's scale (a constant: the background
      colour is known exactly). The default 0.01 is below the scales the per-sample heads
      reach where a ray stops (the built-in quick start's, weighted by the blending weights:
      median 0.043, tenth percentile 0.023), so a ray onto the background is likeliest when
      it is transparent rather than when a white sample stops it.
    """

    weight_eps: float = eqx.field(static=True, default=1e-10)
    likelihood_floor: float | None = eqx.field(static=True, default=1e-12)
    depth_scale: Literal["colour", "single"] = eqx.field(static=True, default="colour")
    evaluation: Literal["log", "linear"] = eqx.field(static=True, default="log")
    background: tuple[float, float, float] | None = eqx.field(static=True, default=None)
    background_scale: float = eqx.field(static=True, default=0.01)

    def __check_init__(self):
        if self.weight_eps < 0:
            raise ValueError(f"weight_eps must be >= 0, got {self.weight_eps}")
        if self.likelihood_floor is not None and self.likelihood_floor <= 0:
            raise ValueError(f"likelihood_floor must be positive or None, got {self.likelihood_floor}")
        if self.depth_scale not in ("colour", "single"):
            raise ValueError(f"depth_scale must be 'colour' or 'single', got {self.depth_scale!r}")
        if self.evaluation not in ("log", "linear"):
            raise ValueError(f"evaluation must be 'log' or 'linear', got {self.evaluation!r}")
        if self.background is not None and len(self.background) != 3:
            raise ValueError(f"background must be an RGB triple or None, got {self.background!r}")
        if not self.background_scale > 0:
            raise ValueError(f"background_scale must be positive, got {self.background_scale}")

    def log_mixing_coefficients(self, weights: PerSample) -> PerSample:
        """`log pi_j` (eq. 6): `-inf` exactly where `w_j = 0`, never NaN.

        With `weight_eps = 0`, a ray whose weights all vanish gets uniform coefficients.
        """
        positive = weights > 0
        log_weights = _log_where_positive(weights)
        if self.weight_eps > 0:
            return log_weights - jnp.log(jnp.sum(weights) + self.weight_eps)
        log_weights = jnp.where(jnp.any(positive), log_weights, 0.0)
        return log_weights - logsumexp(log_weights)

    def _nll(
        self,
        weights: PerSample,
        component_log_density: PerSample,
        background: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
    ) -> Float[Array, ""]:
        """`-log sum_j pi_j p_j` (plus the floor); with `background = (log T, log p_bg)`, the
        unnormalised weights and the background component weighted by the transmittance."""
        if self.evaluation == "linear":
            if background is None:
                mixing = weights / (jnp.sum(weights) + self.weight_eps)
                likelihood = jnp.sum(mixing * jnp.exp(component_log_density))
            else:
                likelihood = jnp.sum(weights * jnp.exp(component_log_density))
                likelihood = likelihood + jnp.exp(background[0] + background[1])
            return -jnp.log(likelihood + (self.likelihood_floor or 0.0))
        if background is None:
            terms = self.log_mixing_coefficients(weights) + component_log_density
        else:
            samples = _log_where_positive(weights) + component_log_density
            terms = jnp.concatenate([samples, (background[0] + background[1])[None]])
        # A ray without mass (every term -inf) takes the safe branch, so that no gradient
        # passes through log(0).
        has_mass = jnp.any(terms > -jnp.inf)
        log_likelihood = logsumexp(jnp.where(has_mass, terms, 0.0))
        if self.likelihood_floor is None:
            # The exact NLL of an empty ray is +inf; it has no mixture to score and adds 0.
            return jnp.where(has_mass, -log_likelihood, 0.0)
        log_likelihood = jnp.where(has_mass, log_likelihood, -jnp.inf)
        return -jnp.logaddexp(log_likelihood, jnp.log(self.likelihood_floor))

    def colour_nll(
        self,
        weights: PerSample,
        rgb: PerSampleRGB,
        beta: PerSampleRGB,
        target: RGB,
        log_transmittance: Float[Array, ""] | None = None,
    ) -> Float[Array, ""]:
        """See `AbstractMixture.colour_nll`. With a `background`, `log_transmittance` (`log T =
        -sum sigma delta`, `mixnerf_eqx.nn.log_transmittance`) weights its component; without
        it, `log(1 - sum w)` stands in, which is exact only while the ray is far from opaque."""
        component = jnp.sum(laplace_log_density(target, rgb, beta), axis=-1)
        if self.background is None:
            return self._nll(weights, component)
        if log_transmittance is None:
            log_transmittance = _log_where_positive(1.0 - jnp.sum(weights))
        colour = jnp.asarray(self.background, target.dtype)
        scale = jnp.full_like(target, self.background_scale)
        background_log_density = jnp.sum(laplace_log_density(target, colour, scale))
        return self._nll(weights, component, (log_transmittance, background_log_density))

    def depth_nll(
        self,
        weights: PerSample,
        ray_depth: PerSample,
        beta: PerSampleRGB,
        target: Float[Array, ""],
    ) -> Float[Array, ""]:
        if self.depth_scale == "colour":
            component = jnp.sum(laplace_log_density(target, ray_depth[:, None], beta), axis=-1)
        else:
            component = laplace_log_density(target, ray_depth, jnp.mean(beta, axis=-1))
        return self._nll(weights, component)
