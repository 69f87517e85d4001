"""MixNeRF (CVPR 2023) on JAX and Equinox: few-shot novel view synthesis with mixture densities.

Runtime shape checking: unless the environment sets `MIXNERF_EQX_TYPECHECK=0`, the package's
modules are imported through `jaxtyping.install_import_hook(..., "beartype.beartype")`, so every
annotated function and Module checks the shapes and dtypes of its arguments. The checks run in
Python, that is while JAX traces a jitted function: a compiled step pays nothing for them.
"""

import contextlib as _contextlib
import os as _os

import jaxtyping as _jaxtyping

TYPECHECK_ON_IMPORT = _os.environ.get("MIXNERF_EQX_TYPECHECK", "1") != "0"

with (
    _jaxtyping.install_import_hook(__name__, "beartype.beartype")
    if TYPECHECK_ON_IMPORT
    else _contextlib.nullcontext()
):
    # Imported here, under the hook, so that their annotations are checked too: a module
    # first imported after this block would not be.
    from . import _calibrate as _calibrate
    from . import _checkpoint as _checkpoint
    from . import _evaluate as _evaluate
    from . import _schedule as _schedule
    from . import _train as _train
    from . import data as data
    from . import metrics as metrics
    from ._calibrate import ThresholdChoice as ThresholdChoice
    from ._calibrate import calibrate_threshold as calibrate_threshold
    from ._calibrate import calibration_rays as calibration_rays
    from ._config import Config as Config
    from ._config import ConfigError as ConfigError
    from ._config import build_model as build_model
    from ._config import load_config as load_config
    from ._encoding import frustum_gaussians as frustum_gaussians
    from ._encoding import integrated_positional_encoding as integrated_positional_encoding
    from ._encoding import positional_encoding as positional_encoding
    from ._evaluate import evaluate as evaluate
    from ._evaluate import render_rays as render_rays
    from ._evaluate import render_views as render_views
    from ._field import AbstractField as AbstractField
    from ._field import FieldOutputs as FieldOutputs
    from ._field import MipNeRFField as MipNeRFField
    from ._loss import LossTerms as LossTerms
    from ._loss import LossWeights as LossWeights
    from ._loss import loss_fn as loss_fn
    from ._mixture import AbstractMixture as AbstractMixture
    from ._mixture import LaplaceMixture as LaplaceMixture
    from ._mixture.laplace import laplace_log_density as laplace_log_density
    from ._model import MixNeRF as MixNeRF
    from ._model import RenderOutputs as RenderOutputs
    from ._occupancy import OccupancyGrid as OccupancyGrid
    from ._occupancy import empty_grid as empty_grid
    from ._occupancy import refresh_occupancy as refresh_occupancy
    from ._occupancy import update_occupancy as update_occupancy
    from ._rays import RayBundle as RayBundle
    from ._rays import RaySamples as RaySamples
    from ._rays import camera_rays as camera_rays
    from ._render import blend_weights as blend_weights
    from ._render import composite_rgb as composite_rgb
    from ._render import depth_quantile as depth_quantile
    from ._render import expected_depth as expected_depth
    from ._renderer import AbstractRenderer as AbstractRenderer
    from ._renderer import LevelOutputs as LevelOutputs
    from ._renderer import VolumeRenderer as VolumeRenderer
    from ._sampler import AbstractSampler as AbstractSampler
    from ._sampler import HierarchicalSampler as HierarchicalSampler
    from ._sampler import StratifiedSampler as StratifiedSampler
    from ._skipping import RenderStats as RenderStats
    from ._skipping import Skipping as Skipping
    from ._train import TrainingDiverged as TrainingDiverged
    from ._train import TrainResult as TrainResult
    from ._train import fit as fit
    from ._train import make_skipping as make_skipping
    from ._train import occupancy_for_model as occupancy_for_model
