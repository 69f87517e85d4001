"""Samplers: where along each ray the field is evaluated (coarse: stratified; fine: from the
coarse weights)."""

from .base import AbstractSampler as AbstractSampler
from .hierarchical import HierarchicalSampler as HierarchicalSampler
from .hierarchical import blur_weights as blur_weights
from .hierarchical import sample_piecewise_constant as sample_piecewise_constant
from .stratified import StratifiedSampler as StratifiedSampler
