from .base import AbstractMixture as AbstractMixture
from .laplace import LaplaceMixture as LaplaceMixture
