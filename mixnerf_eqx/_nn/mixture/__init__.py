"""Mixture heads: the distribution over a ray's samples that MixNeRF's likelihood terms score."""

from .base import AbstractMixture as AbstractMixture
from .laplace import LaplaceMixture as LaplaceMixture
