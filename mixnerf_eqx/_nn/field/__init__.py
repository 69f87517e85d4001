"""Radiance fields: the paper's MLP and the grid field, behind one abstract interface."""

from .base import AbstractField as AbstractField
from .base import FieldOutputs as FieldOutputs
from .base import vmap_density as vmap_density
from .base import vmap_field as vmap_field
from .grid import AbstractGridEncoding as AbstractGridEncoding
from .grid import GridField as GridField
from .grid import HashEncoding as HashEncoding
from .grid import TriPlaneEncoding as TriPlaneEncoding
from .grid import level_resolutions as level_resolutions
from .grid import level_scale_weights as level_scale_weights
from .heads import MixtureHeads as MixtureHeads
from .mip_mlp import MipNeRFField as MipNeRFField
