import abc

import equinox as eqx
from jaxtyping import Array, Float

from .._custom_types import PRNGKey, Vec3


class FieldOutputs(eqx.Module):
    """What a field predicts at a point (or, after `vmap`, at a batch of points).

    **Fields:**

    - `density`: volume density `sigma >= 0`.
    - `rgb`: colour, the Laplace location `mu^c` of the mixture component.
    - `beta`: per-channel Laplace scale (`None` for a field without mixture heads).
    - `ray_depth`: predicted ray depth `mu^d >= 0` (`None` without mixture heads).
    """

    density: Float[Array, "*batch"]
    rgb: Float[Array, "*batch channels"]
    beta: Float[Array, "*batch channels"] | None
    ray_depth: Float[Array, "*batch"] | None


class AbstractField(eqx.Module):
    """A radiance field: maps one frustum Gaussian and a view direction to `FieldOutputs`."""

    @property
    @abc.abstractmethod
    def has_mixture_heads(self) -> bool:
        """Whether the field predicts `beta` and `ray_depth` (needed by the mixture losses)."""

    @abc.abstractmethod
    def density(self, mean: Vec3, cov: Vec3) -> Float[Array, ""]:
        """The noise-free density at one Gaussian, without the view-dependent branch.

        Equal to `self(mean, cov, viewdir).density` for every `viewdir`; occupancy grids
        call this, so they pay for the density only.
        """

    @abc.abstractmethod
    def __call__(self, mean: Vec3, cov: Vec3, viewdir: Vec3, *, key: PRNGKey | None = None) -> FieldOutputs:
        """Evaluates the field at one Gaussian.

        **Arguments:**

        - `mean`, `cov`: the frustum Gaussian's mean and covariance diagonal.
        - `viewdir`: the unit view direction.
        - `key`: randomness for training-time regularisation (density noise); `None` at
          evaluation.
        """
