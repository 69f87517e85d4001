"""What every sampler is: an Equinox module that places a ray's samples, choosing the interval
edges along it (for the fine level, from the coarse level's weights) and their frustum Gaussians."""

import abc
from typing import Literal

import equinox as eqx

from ..._custom_types import PreviousEdges, PreviousWeights, PRNGKey, SampledEdges
from ..encoding import frustum_gaussians
from ..rays import RayBundle, RaySamples


class AbstractSampler(eqx.Module):
    """Places the samples (frustums) along one ray.

    Subclasses choose the interval edges; the frustum Gaussians follow from them. A sampler
    is deterministic when called without a `key` (evaluation) and random with one (training).
    """

    num_samples: eqx.AbstractVar[int]
    frustum: eqx.AbstractVar[Literal["cone", "cylinder"]]

    def __check_init__(self):
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be at least 1, got {self.num_samples}")

    @abc.abstractmethod
    def sample_edges(
        self,
        ray: RayBundle,
        previous_edges: PreviousEdges | None,
        previous_weights: PreviousWeights | None,
        *,
        key: PRNGKey | None,
    ) -> SampledEdges:
        """The `num_samples + 1` sorted interval edges for `ray`.

        **Arguments:**

        - `ray`: one ray (empty batch shape).
        - `previous_edges`, `previous_weights`: the previous level's edges and blending
          weights, for hierarchical samplers (`None` at the first level).
        - `key`: randomness for training; `None` gives deterministic samples.
        """

    def __call__(
        self,
        ray: RayBundle,
        previous_edges: PreviousEdges | None = None,
        previous_weights: PreviousWeights | None = None,
        *,
        key: PRNGKey | None = None,
    ) -> RaySamples:
        """Samples `ray` and returns the intervals with their frustum Gaussians."""
        t_edges = self.sample_edges(ray, previous_edges, previous_weights, key=key)
        means, covs = frustum_gaussians(t_edges, ray.origins, ray.directions, ray.radii, self.frustum)
        return RaySamples(t_edges=t_edges, means=means, covs=covs)
