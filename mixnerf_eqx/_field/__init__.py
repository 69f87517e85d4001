from .base import AbstractField as AbstractField
from .base import FieldOutputs as FieldOutputs
from .mip_mlp import MipNeRFField as MipNeRFField
