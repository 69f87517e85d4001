"""MixNeRF (CVPR 2023) on JAX and Equinox: few-shot novel view synthesis with mixture densities.

Importing the package installs jaxtyping's import hook with beartype for its modules, so every
annotated function and Module checks the shapes and dtypes of its arguments while JAX traces
(a compiled step pays nothing). `mixnerf_eqx.set_typecheck(False)`, `--no-typecheck` or
`JAXTYPING_DISABLE=1` turn the checks off: see `mixnerf_eqx._util.typecheck`.
"""

from ._util.allocator import preload_for_commands as _preload_for_commands
from ._util.allocator import started_as_command as _started_as_command
from ._util.interrupt import quiet_interrupts_while_starting as _quiet_interrupts_while_starting
from ._util.interrupt import redeliver_dropped_interrupts as _redeliver_dropped_interrupts

# Before anything heavy is imported: `python -m mixnerf_eqx.<command>` starts itself again
# with mimalloc preloaded where it is installed (a faster CPU step; `mixnerf_eqx._util.allocator`).
_preload_for_commands()
# Before JAX is imported: a Ctrl-C that lands in its garbage-collection callback is not lost,
# and one while a command is still importing ends it with one line, not a traceback.
_redeliver_dropped_interrupts()
if _started_as_command():
    _quiet_interrupts_while_starting()

import jaxtyping as _jaxtyping  # noqa: E402

with _jaxtyping.install_import_hook(__name__, "beartype.beartype"):
    from . import data as data
    from . import metrics as metrics
    from . import runs as runs
    from ._config import Config as Config
    from ._config import ConfigError as ConfigError
    from ._config import ScheduleSteps as ScheduleSteps
    from ._config import SettingWarning as SettingWarning
    from ._config import config_from_dict as config_from_dict
    from ._config import config_names as config_names
    from ._config import config_path as config_path
    from ._config import config_to_dict as config_to_dict
    from ._config import load_config as load_config
    from ._config import loss_weight as loss_weight
    from ._config import schedule_steps as schedule_steps
    from ._config import setting_warnings as setting_warnings
    from ._inference.camera_path import camera_path as camera_path
    from ._inference.camera_path import orbit_path as orbit_path
    from ._inference.camera_path import spiral_path as spiral_path
    from ._inference.evaluation import Evaluation as Evaluation
    from ._inference.evaluation import Rendered as Rendered
    from ._inference.evaluation import evaluate as evaluate
    from ._inference.evaluation import image_metrics as image_metrics
    from ._inference.evaluation import render_rays as render_rays
    from ._inference.evaluation import render_views as render_views
    from ._inference.occupancy import OccupancyGrid as OccupancyGrid
    from ._inference.occupancy import empty_grid as empty_grid
    from ._inference.occupancy import refresh_occupancy as refresh_occupancy
    from ._inference.occupancy import update_occupancy as update_occupancy
    from ._inference.skipping import RenderCounts as RenderCounts
    from ._inference.skipping import Skipping as Skipping
    from ._inference.skipping import render_skipping as render_skipping
    from ._inference.threshold import ThresholdChoice as ThresholdChoice
    from ._inference.threshold import choose_threshold as choose_threshold
    from ._inference.threshold import psnr_drop_bound as psnr_drop_bound
    from ._inference.threshold import threshold_rays as threshold_rays
    from ._inference.video import Video as Video
    from ._inference.video import render_video as render_video
    from ._inference.viewer import Viewer as Viewer
    from ._inference.viewer import ViewerCamera as ViewerCamera
    from ._inference.viewer import camera_of_view as camera_of_view
    from ._inference.viewer import preview_image as preview_image
    from ._inference.viewer import scene_facing as scene_facing
    from ._inference.viewer import viewer_rays as viewer_rays
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
    from ._nn.field import TriPlaneEncoding as TriPlaneEncoding
    from ._nn.field import level_resolutions as level_resolutions
    from ._nn.field import level_scale_weights as level_scale_weights
    from ._nn.mixture import AbstractMixture as AbstractMixture
    from ._nn.mixture import LaplaceMixture as LaplaceMixture
    from ._nn.mixture.laplace import laplace_log_density as laplace_log_density
    from ._nn.model import FIELD_BUILDERS as FIELD_BUILDERS
    from ._nn.model import MixNeRF as MixNeRF
    from ._nn.model import RenderOutputs as RenderOutputs
    from ._nn.model import build_field as build_field
    from ._nn.model import build_model as build_model
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
    from ._predictive.distribution import ColourMixture as ColourMixture
    from ._predictive.distribution import IntervalLevels as IntervalLevels
    from ._predictive.distribution import Predictive as Predictive
    from ._predictive.distribution import PredictiveSummary as PredictiveSummary
    from ._predictive.distribution import TerminationDistribution as TerminationDistribution
    from ._predictive.distribution import predictive as predictive
    from ._predictive.distribution import summarise as summarise
    from ._predictive.exports import world_points as world_points
    from ._predictive.exports import write_depth_exports as write_depth_exports
    from ._predictive.next_view import ViewRanking as ViewRanking
    from ._predictive.next_view import farthest_first as farthest_first
    from ._predictive.next_view import next_view as next_view
    from ._predictive.recalibration import Recalibration as Recalibration
    from ._predictive.uncertainty import Sparsification as Sparsification
    from ._predictive.uncertainty import calibration_pit as calibration_pit
    from ._predictive.uncertainty import calibration_report as calibration_report
    from ._predictive.uncertainty import collect_mixtures as collect_mixtures
    from ._predictive.uncertainty import coverage_report as coverage_report
    from ._predictive.uncertainty import fit_recalibration as fit_recalibration
    from ._predictive.uncertainty import fit_temperature as fit_temperature
    from ._predictive.uncertainty import interval_coverage as interval_coverage
    from ._predictive.uncertainty import predict_rays as predict_rays
    from ._predictive.uncertainty import predict_views as predict_views
    from ._predictive.uncertainty import sparsification as sparsification
    from ._train.checkpoint import CheckpointError as CheckpointError
    from ._train.loop import TrainingDiverged as TrainingDiverged
    from ._train.loop import TrainResult as TrainResult
    from ._train.loop import fit as fit
    from ._train.loss import LossInputs as LossInputs
    from ._train.loss import LossTerm as LossTerm
    from ._train.loss import LossTerms as LossTerms
    from ._train.loss import LossWeights as LossWeights
    from ._train.loss import loss_fn as loss_fn
    from ._train.loss import loss_term_names as loss_term_names
    from ._train.loss import loss_terms as loss_terms
    from ._train.loss import register_loss_term as register_loss_term
    from ._train.loss import unregister_loss_term as unregister_loss_term
    from ._train.schedule import anneal_sample_space as anneal_sample_space
    from ._train.schedule import learning_rate_schedule as learning_rate_schedule
    from ._train.schedule import linear_ramp as linear_ramp
    from ._train.sharding import DataParallel as DataParallel
    from ._train.sharding import data_parallel_mesh as data_parallel_mesh
    from ._train.sharding import initialize_distributed as initialize_distributed
    from ._train.state import Batch as Batch
    from ._train.state import StepMetrics as StepMetrics
    from ._train.state import TrainingRays as TrainingRays
    from ._train.state import TrainState as TrainState
    from ._train.state import draw_batch as draw_batch
    from ._train.state import init_key as init_key
    from ._train.state import init_train_state as init_train_state
    from ._train.state import make_occupancy_grid as make_occupancy_grid
    from ._train.state import make_optimizer as make_optimizer
    from ._train.state import make_train_step as make_train_step
    from ._train.state import occupancy_key as occupancy_key
    from ._train.state import scene_box as scene_box
    from ._train.state import training_rays as training_rays
    from ._train.state import update_grid as update_grid
    from ._train.sweep import plan_sweep as plan_sweep
    from ._util.allocator import allocator_in_use as allocator_in_use
    from ._util.allocator import allocator_library as allocator_library
    from ._util.allocator import preload_allocator as preload_allocator
    from ._util.compilation_cache import enable_compilation_cache as enable_compilation_cache
    from ._util.lock import FolderBusyError as FolderBusyError
    from ._util.typecheck import set_typecheck as set_typecheck
    from ._util.typecheck import typecheck_enabled as typecheck_enabled


# Names that moved: an old script gets an error that names the new place.
_MOVED = {
    **{
        name: f"mixnerf_eqx.runs.{name}"
        for name in (
            "Run",
            "restore_run",
            "grid_for_rendering",
            "make_skipping",
            "render_summary",
            "write_view_renders",
            "hold_folder",
            "save_checkpoint",
            "load_checkpoint",
            "latest_checkpoint",
            "read_checkpoint_meta",
        )
    },
    "calibrate_threshold": "mixnerf_eqx.choose_threshold",
    "calibration_rays": "mixnerf_eqx.threshold_rays",
}


def __getattr__(name: str):
    if name in _MOVED:
        raise AttributeError(f"mixnerf_eqx.{name} has moved: use {_MOVED[name]}")
    raise AttributeError(f"module 'mixnerf_eqx' has no attribute {name!r}")
