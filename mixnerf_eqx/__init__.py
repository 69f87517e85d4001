"""MixNeRF (CVPR 2023) on JAX and Equinox: few-shot novel view synthesis with mixture densities.

Importing the package installs jaxtyping's import hook with beartype for its modules, so every
annotated function and Module checks the shapes and dtypes of its arguments while JAX traces
(a compiled step pays nothing). `mixnerf_eqx.set_typecheck(False)`, `--no-typecheck` or
`JAXTYPING_DISABLE=1` turn the checks off: see `mixnerf_eqx._typecheck`.
"""

from ._allocator import preload_for_commands as _preload_for_commands
from ._interrupt import redeliver_dropped_interrupts as _redeliver_dropped_interrupts

# Before anything heavy is imported: `python -m mixnerf_eqx.<command>` starts itself again
# with mimalloc preloaded where it is installed (a faster CPU step; `mixnerf_eqx._allocator`).
_preload_for_commands()
# Before JAX is imported: a Ctrl-C that lands in its garbage-collection callback is not lost.
_redeliver_dropped_interrupts()

import jaxtyping as _jaxtyping  # noqa: E402

with _jaxtyping.install_import_hook(__name__, "beartype.beartype"):
    from . import data as data
    from . import metrics as metrics
    from ._allocator import allocator_in_use as allocator_in_use
    from ._allocator import allocator_library as allocator_library
    from ._allocator import preload_allocator as preload_allocator
    from ._calibrate import ThresholdChoice as ThresholdChoice
    from ._calibrate import calibrate_threshold as calibrate_threshold
    from ._calibrate import calibration_rays as calibration_rays
    from ._calibrate import psnr_drop_bound as psnr_drop_bound
    from ._camera_path import camera_path as camera_path
    from ._camera_path import orbit_path as orbit_path
    from ._camera_path import spiral_path as spiral_path
    from ._checkpoint import CheckpointError as CheckpointError
    from ._checkpoint import latest_checkpoint as latest_checkpoint
    from ._checkpoint import load_checkpoint as load_checkpoint
    from ._checkpoint import read_checkpoint_meta as read_checkpoint_meta
    from ._checkpoint import save_checkpoint as save_checkpoint
    from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
    from ._config import Config as Config
    from ._config import ConfigError as ConfigError
    from ._config import ScheduleSteps as ScheduleSteps
    from ._config import SettingWarning as SettingWarning
    from ._config import config_from_dict as config_from_dict
    from ._config import config_names as config_names
    from ._config import config_path as config_path
    from ._config import config_to_dict as config_to_dict
    from ._config import load_config as load_config
    from ._config import schedule_steps as schedule_steps
    from ._config import setting_warnings as setting_warnings
    from ._encoding import conical_frustum_moments as conical_frustum_moments
    from ._encoding import frustum_gaussians as frustum_gaussians
    from ._encoding import integrated_positional_encoding as integrated_positional_encoding
    from ._encoding import positional_encoding as positional_encoding
    from ._evaluate import Evaluation as Evaluation
    from ._evaluate import Rendered as Rendered
    from ._evaluate import evaluate as evaluate
    from ._evaluate import image_metrics as image_metrics
    from ._evaluate import render_rays as render_rays
    from ._evaluate import render_views as render_views
    from ._field import AbstractField as AbstractField
    from ._field import AbstractGridEncoding as AbstractGridEncoding
    from ._field import FieldOutputs as FieldOutputs
    from ._field import GridField as GridField
    from ._field import HashEncoding as HashEncoding
    from ._field import MipNeRFField as MipNeRFField
    from ._field import TriPlaneEncoding as TriPlaneEncoding
    from ._field import level_resolutions as level_resolutions
    from ._field import level_scale_weights as level_scale_weights
    from ._lock import FolderBusyError as FolderBusyError
    from ._lock import hold_folder as hold_folder
    from ._loss import LossInputs as LossInputs
    from ._loss import LossTerm as LossTerm
    from ._loss import LossTerms as LossTerms
    from ._loss import LossWeights as LossWeights
    from ._loss import loss_fn as loss_fn
    from ._loss import loss_term_names as loss_term_names
    from ._loss import loss_terms as loss_terms
    from ._loss import register_loss_term as register_loss_term
    from ._loss import unregister_loss_term as unregister_loss_term
    from ._mixture import AbstractMixture as AbstractMixture
    from ._mixture import LaplaceMixture as LaplaceMixture
    from ._mixture.laplace import laplace_log_density as laplace_log_density
    from ._model import FIELD_BUILDERS as FIELD_BUILDERS
    from ._model import MixNeRF as MixNeRF
    from ._model import RenderOutputs as RenderOutputs
    from ._model import build_field as build_field
    from ._model import build_model as build_model
    from ._occupancy import OccupancyGrid as OccupancyGrid
    from ._occupancy import empty_grid as empty_grid
    from ._occupancy import refresh_occupancy as refresh_occupancy
    from ._occupancy import update_occupancy as update_occupancy
    from ._predictive import ColourMixture as ColourMixture
    from ._predictive import Predictive as Predictive
    from ._predictive import PredictiveSummary as PredictiveSummary
    from ._predictive import TerminationDistribution as TerminationDistribution
    from ._predictive import predictive as predictive
    from ._predictive import summarise as summarise
    from ._rays import RayBundle as RayBundle
    from ._rays import RaySamples as RaySamples
    from ._rays import camera_rays as camera_rays
    from ._rays import pixel_directions as pixel_directions
    from ._render import blend_weights as blend_weights
    from ._render import composite_rgb as composite_rgb
    from ._render import depth_quantile as depth_quantile
    from ._render import expected_depth as expected_depth
    from ._renderer import AbstractRenderer as AbstractRenderer
    from ._renderer import LevelOutputs as LevelOutputs
    from ._renderer import VolumeRenderer as VolumeRenderer
    from ._run import Run as Run
    from ._run import grid_for_rendering as grid_for_rendering
    from ._run import make_skipping as make_skipping
    from ._run import render_summary as render_summary
    from ._run import restore_run as restore_run
    from ._run import write_view_renders as write_view_renders
    from ._sampler import AbstractSampler as AbstractSampler
    from ._sampler import HierarchicalSampler as HierarchicalSampler
    from ._sampler import StratifiedSampler as StratifiedSampler
    from ._sampler import blur_weights as blur_weights
    from ._sampler import sample_piecewise_constant as sample_piecewise_constant
    from ._schedule import anneal_sample_space as anneal_sample_space
    from ._schedule import learning_rate_schedule as learning_rate_schedule
    from ._schedule import linear_ramp as linear_ramp
    from ._sharding import DataParallel as DataParallel
    from ._sharding import data_parallel_mesh as data_parallel_mesh
    from ._sharding import initialize_distributed as initialize_distributed
    from ._skipping import RenderCounts as RenderCounts
    from ._skipping import Skipping as Skipping
    from ._skipping import render_skipping as render_skipping
    from ._sweep import plan_sweep as plan_sweep
    from ._train import TrainingDiverged as TrainingDiverged
    from ._train import TrainResult as TrainResult
    from ._train import fit as fit
    from ._train_state import Batch as Batch
    from ._train_state import StepMetrics as StepMetrics
    from ._train_state import TrainingRays as TrainingRays
    from ._train_state import TrainState as TrainState
    from ._train_state import draw_batch as draw_batch
    from ._train_state import init_key as init_key
    from ._train_state import init_train_state as init_train_state
    from ._train_state import make_occupancy_grid as make_occupancy_grid
    from ._train_state import make_optimizer as make_optimizer
    from ._train_state import make_train_step as make_train_step
    from ._train_state import occupancy_key as occupancy_key
    from ._train_state import scene_box as scene_box
    from ._train_state import training_rays as training_rays
    from ._train_state import update_grid as update_grid
    from ._typecheck import set_typecheck as set_typecheck
    from ._typecheck import typecheck_enabled as typecheck_enabled
    from ._uncertainty import Sparsification as Sparsification
    from ._uncertainty import calibration_report as calibration_report
    from ._uncertainty import collect_mixtures as collect_mixtures
    from ._uncertainty import fit_temperature as fit_temperature
    from ._uncertainty import interval_coverage as interval_coverage
    from ._uncertainty import predict_rays as predict_rays
    from ._uncertainty import predict_views as predict_views
    from ._uncertainty import sparsification as sparsification
    from ._video import Video as Video
    from ._video import render_video as render_video
