"""The package's front door: a short top level, namespaces that re-export, nothing done on import,
and the flat names of the previous release still working with a warning that names their place."""

import ast
import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import mixnerf_eqx as mx

PACKAGE = Path(mx.__file__).parent
NAMESPACES = ("config", "data", "inference", "metrics", "nn", "runs", "runtime", "training", "uncertainty")

# Every name the previous release re-exported at the top level and this one keeps in a namespace.
FORMERLY_FLAT = (
    "AbstractField",
    "AbstractGridEncoding",
    "AbstractMixture",
    "AbstractRenderer",
    "AbstractSampler",
    "Batch",
    "CheckpointError",
    "ColourMixture",
    "DataParallel",
    "FIELD_BUILDERS",
    "FieldOutputs",
    "FolderBusyError",
    "GridField",
    "HashEncoding",
    "HierarchicalSampler",
    "IntervalLevels",
    "LaplaceMixture",
    "LevelOutputs",
    "LossInputs",
    "LossTerm",
    "LossTerms",
    "LossWeights",
    "MipNeRFField",
    "OccupancyGrid",
    "Predictive",
    "PredictiveSummary",
    "RayBundle",
    "RaySamples",
    "Recalibration",
    "RenderCounts",
    "RenderOutputs",
    "Rendered",
    "ScheduleSteps",
    "SettingWarning",
    "Skipping",
    "Sparsification",
    "StepMetrics",
    "StratifiedSampler",
    "TerminationDistribution",
    "ThresholdChoice",
    "TrainState",
    "TrainingDiverged",
    "TrainingRays",
    "TriPlaneEncoding",
    "Video",
    "ViewRanking",
    "ViewerCamera",
    "VolumeRenderer",
    "allocator_in_use",
    "allocator_library",
    "anneal_sample_space",
    "blend_weights",
    "blur_weights",
    "build_field",
    "calibration_pit",
    "calibration_report",
    "camera_of_view",
    "camera_path",
    "camera_rays",
    "choose_threshold",
    "collect_mixtures",
    "composite_rgb",
    "config_from_dict",
    "config_names",
    "config_path",
    "config_to_dict",
    "conical_frustum_moments",
    "coverage_report",
    "data_parallel_mesh",
    "depth_quantile",
    "draw_batch",
    "empty_grid",
    "enable_compilation_cache",
    "expected_depth",
    "farthest_first",
    "fit_recalibration",
    "fit_temperature",
    "frustum_gaussians",
    "image_metrics",
    "init_key",
    "init_train_state",
    "initialize_distributed",
    "integrated_positional_encoding",
    "interval_coverage",
    "laplace_log_density",
    "learning_rate_schedule",
    "level_resolutions",
    "level_scale_weights",
    "linear_ramp",
    "log_transmittance",
    "loss_fn",
    "loss_term_names",
    "loss_terms",
    "loss_weight",
    "make_occupancy_grid",
    "make_optimizer",
    "make_train_step",
    "occupancy_key",
    "orbit_path",
    "pixel_directions",
    "positional_encoding",
    "predict_rays",
    "predict_views",
    "preload_allocator",
    "preview_image",
    "psnr_drop_bound",
    "refresh_occupancy",
    "register_loss_term",
    "render_rays",
    "render_skipping",
    "sample_piecewise_constant",
    "scene_box",
    "scene_facing",
    "schedule_steps",
    "setting_warnings",
    "sparsification",
    "spiral_path",
    "summarise",
    "threshold_rays",
    "training_rays",
    "typecheck_enabled",
    "unregister_loss_term",
    "update_grid",
    "update_occupancy",
    "viewer_rays",
    "world_points",
    "write_depth_exports",
)

IMPORT_ONLY = """
import json, signal, sys
before = (sys.excepthook, sys.unraisablehook, signal.getsignal(signal.SIGINT), list(sys.meta_path))
import mixnerf_eqx
after = (sys.excepthook, sys.unraisablehook, signal.getsignal(signal.SIGINT), list(sys.meta_path))
heavy = sorted(m for m in ("jax", "equinox", "optax", "optimistix", "mixnerf_eqx._nn") if m in sys.modules)
print(json.dumps({
    "heavy": heavy,
    "hooks_kept": [a is b for a, b in zip(before[:3], after[:3])],
    "finders_added": [type(f).__module__ for f in after[3] if f not in before[3]],
}))
"""


def test_importing_the_package_loads_nothing_heavy_and_changes_no_handler():
    finished = subprocess.run(
        [sys.executable, "-c", IMPORT_ONLY], capture_output=True, text=True, check=True, timeout=120
    )
    report = json.loads(finished.stdout)
    assert report["heavy"] == []
    assert report["hooks_kept"] == [True, True, True]  # excepthook, unraisablehook, SIGINT
    # The one thing added: jaxtyping's import hook, for the package's own modules.
    assert report["finders_added"] == ["jaxtyping._import_hook"]


def test_a_command_starts_without_jax():
    # The start-up modules are loaded before the shape-check hook, whose checks import JAX: a
    # command restarts itself with its allocator before paying for that import.
    program = "import sys\nimport mixnerf_eqx._util.entry\nprint('jax' in sys.modules)\n"
    finished = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, check=True)
    assert finished.stdout.strip() == "False"


def test_the_top_level_is_short_and_every_name_loads_without_a_warning():
    assert 15 <= len(mx.__all__) <= 30
    assert sorted(dir(mx)) == sorted(mx.__all__)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in mx.__all__:
            assert getattr(mx, name) is not None
    assert set(NAMESPACES) <= set(mx.__all__)
    # The top level's names are the namespaces' objects, not copies.
    assert mx.fit is mx.training.fit and mx.MixNeRF is mx.nn.MixNeRF
    assert mx.predictive is mx.uncertainty.predictive and mx.load_config is mx.config.load_config


def _is_reexport(statement: ast.stmt) -> bool:
    if isinstance(statement, ast.Expr) and isinstance(statement.value, ast.Constant):
        return True  # the docstring
    if isinstance(statement, ast.ImportFrom) and statement.level >= 1:
        return all(alias.asname in (None, alias.name) for alias in statement.names)
    return False


@pytest.mark.parametrize(
    "path",
    [PACKAGE / f"{name}.py" for name in ("config", "inference", "nn", "runs", "runtime", "training", "uncertainty")]
    + sorted(path for path in PACKAGE.glob("*/__init__.py"))
    + sorted(path for path in PACKAGE.glob("*/*/__init__.py")),
    ids=lambda path: str(path.relative_to(PACKAGE)),
)
def test_namespaces_and_subpackages_only_reexport(path):
    tree = ast.parse(path.read_text())
    assert all(_is_reexport(statement) for statement in tree.body), path


def test_a_formerly_flat_name_works_with_a_warning_that_names_its_place():
    # In a fresh process: a name looked up once is kept on the package (and warned about once).
    program = (
        "import json, warnings\n"
        "import mixnerf_eqx as mx\n"
        f"names = {FORMERLY_FLAT!r}\n"
        "out = {}\n"
        "for name in names:\n"
        "    with warnings.catch_warnings(record=True) as caught:\n"
        "        warnings.simplefilter('always')\n"
        "        value = getattr(mx, name)\n"
        "    place = [str(w.message) for w in caught if w.category is DeprecationWarning]\n"
        "    namespace = place[0].rsplit('use mixnerf_eqx.', 1)[1].split('.')[0] if len(place) == 1 else None\n"
        "    same = namespace is not None and getattr(getattr(mx, namespace), name) is value\n"
        "    out[name] = [len(caught), namespace, same]\n"
        "print(json.dumps(out))\n"
    )
    finished = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, check=True, timeout=300
    )
    found = json.loads(finished.stdout)
    # Looked up again, a name is the package's own attribute: no second warning.
    again = subprocess.run(
        [sys.executable, "-W", "error::DeprecationWarning", "-c",
         "import warnings\nimport mixnerf_eqx as mx\nwith warnings.catch_warnings():\n"
         "    warnings.simplefilter('ignore')\n    first = mx.camera_rays\nassert mx.camera_rays is first\n"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    wrong = {name: got for name, got in found.items() if not (got[0] == 1 and got[1] in NAMESPACES and got[2])}
    assert wrong == {}
    assert len(found) == len(FORMERLY_FLAT) > 100


def test_unknown_and_renamed_names_are_errors():
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        mx.no_such_name  # noqa: B018
    with pytest.raises(AttributeError, match="has moved: use mixnerf_eqx.inference.choose_threshold"):
        mx.calibrate_threshold  # noqa: B018
    # Names of the namespaces that were never at the top level are not found there, nor are
    # a module the namespaces import.
    for name in ("restore_run", "load_dataset", "psnr", "Run", "vmap_field", "jax"):
        with pytest.raises(AttributeError):
            getattr(mx, name)
    with pytest.raises(AttributeError, match="has no attribute '_private'"):
        mx._private  # noqa: B018
