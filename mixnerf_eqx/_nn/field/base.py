"""What a radiance field is (`AbstractField`) and what it returns at a point (`FieldOutputs`):
density, colour and, for MixNeRF, the mixture's per-sample heads."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..._custom_types import PRNGKey, RayKeys, Vec3


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
    def regulariser(self) -> Float[Array, ""]:
        """The field's own term of the training loss, already weighted (`jnp.zeros(())`: none)."""

    @abc.abstractmethod
    def at_step(self, step: Int[Array, ""] | int) -> "AbstractField":
        """The field as training step `step` (from 1) sees it.

        A field without a schedule returns itself. A field with one (a grid revealing its
        levels coarse to fine) returns a copy whose schedule-dependent arrays are set for
        `step`; the training step calls this before rendering, and stored models keep the
        fully revealed field.
        """

    @abc.abstractmethod
    def density(self, mean: Vec3, cov: Vec3) -> Float[Array, ""]:
        """The noise-free density at one Gaussian, without the view-dependent branch.

        Equal to `self(mean, cov, viewdir).density` for every `viewdir`; occupancy grids
        call this, so they pay for the density only.
        """

    @abc.abstractmethod
    def density_batch(self, means: Float[Array, "batch 3"], covs: Float[Array, "batch 3"]) -> Float[Array, " batch"]:
        """`density` at a batch of Gaussians, with the same values: `vmap_density(self, ...)`,
        or one batched lookup of a grid field's tables (as its `evaluate_batch` does)."""

    @abc.abstractmethod
    def __call__(self, mean: Vec3, cov: Vec3, viewdir: Vec3, *, key: PRNGKey | None = None) -> FieldOutputs:
        """Evaluates the field at one Gaussian.

        **Arguments:**

        - `mean`, `cov`: the frustum Gaussian's mean and covariance diagonal.
        - `viewdir`: the unit view direction.
        - `key`: randomness for training-time regularisation (density noise); `None` at
          evaluation.
        """

    @abc.abstractmethod
    def evaluate_batch(
        self,
        means: Float[Array, "batch 3"],
        covs: Float[Array, "batch 3"],
        viewdirs: Float[Array, "batch 3"],
        keys: RayKeys | None = None,
    ) -> FieldOutputs:
        """The field at a flat batch of Gaussians (`keys`: one per point, or `None`), with the
        values of `__call__`: `vmap_field(self, ...)`, or a formulation that gains from seeing
        the whole batch (the grid field's batched lookups on a CPU)."""


def vmap_density(
    field: AbstractField, means: Float[Array, "batch 3"], covs: Float[Array, "batch 3"]
) -> Float[Array, " batch"]:
    """`field.density` lifted to a flat batch of Gaussians by `jax.vmap`."""
    return jax.vmap(field.density)(means, covs)


def vmap_field(
    field: AbstractField,
    means: Float[Array, "batch 3"],
    covs: Float[Array, "batch 3"],
    viewdirs: Float[Array, "batch 3"],
    keys: RayKeys | None = None,
) -> FieldOutputs:
    """`field.__call__` lifted to a flat batch of Gaussians by `jax.vmap`."""
    if keys is None:
        return jax.vmap(lambda m, c, v: field(m, c, v))(means, covs, viewdirs)
    return jax.vmap(lambda m, c, v, k: field(m, c, v, key=k))(means, covs, viewdirs, keys)


def safe_norm(vector: Vec3) -> Float[Array, ""]:
    """The Euclidean norm of a 3-vector, with a gradient that stays finite at zero."""
    squared = jnp.sum(vector**2)
    safe = jnp.where(squared > 0, squared, 1.0)
    return jnp.where(squared > 0, jnp.sqrt(safe), 0.0)
