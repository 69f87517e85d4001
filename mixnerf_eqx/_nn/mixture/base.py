"""What a mixture head is: the per-ray mixture over a level's samples whose log-likelihood the
NLL terms score."""

import abc

import equinox as eqx
from jaxtyping import Array, Float

from ..._custom_types import RGB, PerSample, PerSampleRGB


class AbstractMixture(eqx.Module):
    """A per-ray mixture density whose components are the ray's samples (paper Sec. 3.2-3.3).

    The mixing coefficients are the normalised blending weights (eq. 6); each method returns
    the negative log-likelihood of one ray's ground truth.
    """

    @abc.abstractmethod
    def colour_nll(
        self,
        weights: PerSample,
        rgb: PerSampleRGB,
        beta: PerSampleRGB,
        target: RGB,
        log_transmittance: Float[Array, ""] | None = None,
    ) -> Float[Array, ""]:
        """`-log p(c_GT | r)` under the colour mixture (eqs. 4-6), or eq. 9 when `weights`
        are the regenerated ones. `log_transmittance`, the log of the light that passes the
        last sample under those weights, is for mixtures with a background component."""

    @abc.abstractmethod
    def depth_nll(
        self,
        weights: PerSample,
        ray_depth: PerSample,
        beta: PerSampleRGB,
        target: Float[Array, ""],
    ) -> Float[Array, ""]:
        """`-log p(d_GT | r)` under the ray-depth mixture (eq. 7)."""
