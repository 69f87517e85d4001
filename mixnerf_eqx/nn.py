"""The model (re-exports only): rays, encodings, samplers, fields, the renderer, the mixture
and MixNeRF itself, each a typed Equinox module or a pure function of arrays.

    import jax
    import mixnerf_eqx as mx
    model = mx.nn.build_model(config, key=jax.random.key(0))   # also mx.build_model
    outputs = model(rays)                                       # rays: an mx.nn.RayBundle
"""

from ._nn.compositing import blend_weights as blend_weights
from ._nn.compositing import composite_rgb as composite_rgb
from ._nn.compositing import depth_quantile as depth_quantile
from ._nn.compositing import expected_depth as expected_depth
from ._nn.compositing import log_transmittance as log_transmittance
from ._nn.encoding import conical_frustum_moments as conical_frustum_moments
from ._nn.encoding import frustum_gaussians as frustum_gaussians
from ._nn.encoding import integrated_positional_encoding as integrated_positional_encoding
from ._nn.encoding import positional_encoding as positional_encoding
from ._nn.field import AbstractField as AbstractField
from ._nn.field import AbstractGridEncoding as AbstractGridEncoding
from ._nn.field import FieldOutputs as FieldOutputs
from ._nn.field import GridField as GridField
from ._nn.field import HashEncoding as HashEncoding
from ._nn.field import MipNeRFField as MipNeRFField
from ._nn.field import MixtureHeads as MixtureHeads
from ._nn.field import TriPlaneEncoding as TriPlaneEncoding
from ._nn.field import level_resolutions as level_resolutions
from ._nn.field import level_scale_weights as level_scale_weights
from ._nn.field import vmap_density as vmap_density
from ._nn.field import vmap_field as vmap_field
from ._nn.mixture import AbstractMixture as AbstractMixture
from ._nn.mixture import LaplaceMixture as LaplaceMixture
from ._nn.mixture.laplace import laplace_log_density as laplace_log_density
from ._nn.model import ENCODING_BUILDERS as ENCODING_BUILDERS
from ._nn.model import FIELD_BUILDERS as FIELD_BUILDERS
from ._nn.model import MixNeRF as MixNeRF
from ._nn.model import RenderOutputs as RenderOutputs
from ._nn.model import build_field as build_field
from ._nn.model import build_model as build_model
from ._nn.model import check_model_names as check_model_names
from ._nn.rays import RayBundle as RayBundle
from ._nn.rays import RaySamples as RaySamples
from ._nn.rays import camera_rays as camera_rays
from ._nn.rays import pixel_directions as pixel_directions
from ._nn.renderer import AbstractRenderer as AbstractRenderer
from ._nn.renderer import LevelOutputs as LevelOutputs
from ._nn.renderer import VolumeRenderer as VolumeRenderer
from ._nn.sampler import AbstractSampler as AbstractSampler
from ._nn.sampler import HierarchicalSampler as HierarchicalSampler
from ._nn.sampler import StratifiedSampler as StratifiedSampler
from ._nn.sampler import blur_weights as blur_weights
from ._nn.sampler import sample_piecewise_constant as sample_piecewise_constant
