"""Names that left the top level of `mixnerf_eqx`.

Until this release the package re-exported 127 more names flat; they now live in namespaces
(`mx.nn`, `mx.training`, ...) and the top level keeps a few (`__init__.pyi`). An old flat name
still works for this release, with a `DeprecationWarning` that names its new place. Names that
left the top level in an earlier release are errors that name their new place.
"""

import importlib
from typing import Any

# The previous release's top-level names, by the namespace that holds each now.
FORMERLY_FLAT: dict[str, tuple[str, ...]] = {
    "nn": (
        "AbstractField", "AbstractGridEncoding", "AbstractMixture", "AbstractRenderer",
        "AbstractSampler", "FIELD_BUILDERS", "FieldOutputs", "GridField", "HashEncoding",
        "HierarchicalSampler", "LaplaceMixture", "LevelOutputs", "MipNeRFField", "RayBundle",
        "RaySamples", "RenderOutputs", "StratifiedSampler", "TriPlaneEncoding", "VolumeRenderer",
        "blend_weights", "blur_weights", "build_field", "camera_rays", "composite_rgb",
        "conical_frustum_moments", "depth_quantile", "expected_depth", "frustum_gaussians",
        "integrated_positional_encoding", "laplace_log_density", "level_resolutions",
        "level_scale_weights", "log_transmittance", "pixel_directions", "positional_encoding",
        "sample_piecewise_constant",
    ),
    "training": (
        "Batch", "DataParallel", "LossInputs", "LossTerm", "LossTerms", "LossWeights", "StepMetrics",
        "TrainState", "TrainingDiverged", "TrainingRays", "anneal_sample_space", "data_parallel_mesh",
        "draw_batch", "init_key", "init_train_state", "initialize_distributed",
        "learning_rate_schedule", "linear_ramp", "loss_fn", "loss_term_names", "loss_terms",
        "make_occupancy_grid", "make_optimizer", "make_train_step", "occupancy_key",
        "register_loss_term", "scene_box", "training_rays", "unregister_loss_term", "update_grid",
    ),
    "inference": (
        "OccupancyGrid", "RenderCounts", "Rendered", "Skipping", "ThresholdChoice", "Video",
        "ViewerCamera", "camera_of_view", "camera_path", "choose_threshold", "empty_grid",
        "image_metrics", "orbit_path", "preview_image", "psnr_drop_bound", "refresh_occupancy",
        "render_rays", "render_skipping", "scene_facing", "spiral_path", "threshold_rays",
        "update_occupancy", "viewer_rays",
    ),
    "uncertainty": (
        "ColourMixture", "IntervalLevels", "Predictive", "PredictiveSummary", "Recalibration",
        "Sparsification", "TerminationDistribution", "ViewRanking", "calibration_pit",
        "calibration_report", "collect_mixtures", "coverage_report", "farthest_first",
        "fit_recalibration", "fit_temperature", "interval_coverage", "predict_rays", "predict_views",
        "sparsification", "summarise", "world_points", "write_depth_exports",
    ),
    "config": (
        "ScheduleSteps", "SettingWarning", "config_from_dict", "config_names", "config_path",
        "config_to_dict", "loss_weight", "schedule_steps", "setting_warnings",
    ),
    "runtime": (
        "allocator_in_use", "allocator_library", "enable_compilation_cache", "preload_allocator",
        "typecheck_enabled",
    ),
    "runs": (
        "CheckpointError", "FolderBusyError",
    ),
}
_PLACES = {name: namespace for namespace, names in FORMERLY_FLAT.items() for name in names}
# Left the top level earlier: an error naming the new place.
GONE = {
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
    "calibrate_threshold": "mixnerf_eqx.inference.choose_threshold",
    "calibration_rays": "mixnerf_eqx.inference.threshold_rays",
}


def new_place(name: str) -> str | None:
    """`mixnerf_eqx.<namespace>.<name>` for a name of the previous release's top level."""
    namespace = _PLACES.get(name)
    return None if namespace is None else f"mixnerf_eqx.{namespace}.{name}"


def moved_name(name: str) -> tuple[str, Any]:
    """The new place of an old top-level `name` and the object it stands for (the package's
    `__getattr__` warns); `AttributeError` for a name that left earlier or is not the package's."""
    if name in GONE:
        raise AttributeError(f"mixnerf_eqx.{name} has moved: use {GONE[name]}")
    place = new_place(name)
    if place is None:
        raise AttributeError(f"module 'mixnerf_eqx' has no attribute {name!r}")
    namespace, _, attribute = place.rpartition(".")
    return place, getattr(importlib.import_module(namespace), attribute)
