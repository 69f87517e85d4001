"""The configuration schema: typed, frozen dataclasses loaded from TOML files.

The package carries its configs (`mixnerf_eqx/configs/*.toml`, package data; `configs/` in a
checkout is a link to that folder), so `load_config("llff3_grid")` works after any install;
`config_names()` lists them. A path to a file of one's own works the same way.

This module is the bottom layer: it imports nothing of the model, so that loading a scene
(`data/`) or reading a run's settings does not build or import one. What each section means
for the model is decided where the model is built (`mixnerf_eqx._nn.model.build_model`).
"""

import dataclasses
import difflib
import importlib.resources
import math
import tomllib
import types
import typing
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal


class ConfigError(ValueError):
    """A configuration file or override that cannot be used."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    # The files' format: "builtin" or a format of `mixnerf_eqx.data.FORMATS` ("blender", "llff",
    # "dtu", "transforms"); an unknown one is an error naming them when the scene loads.
    dataset: str = "builtin"
    scene: str = "builtin"  # scene folder (lego, fern, scan8, ...); "builtin": the procedural scene
    data_dir: str = ""  # dataset root; empty: the environment variable MIXNERF_DATA_DIR
    protocol: Literal["mixnerf", "dietnerf"] = "mixnerf"  # Blender split: MixNeRF's or DietNeRF's views
    resolution: int = 64  # built-in scene: image height and width in pixels
    num_train_views: int = 4  # number of training views
    num_test_views: int = 8  # built-in scene: number of held-out test views
    max_test_views: int = 0  # files: keep this many of the protocol's test views, evenly spaced (0: all)
    num_val_views: int = 4  # built-in scene: number of validation views (extra cameras; 0: none)
    max_val_views: int = 8  # files: validation views, neither train nor test, evenly spaced (0: all)
    near: float = 0.0  # with far > 0: replaces the dataset's near bound
    far: float = 0.0  # > 0: replaces the dataset's far bound (transforms.json scenes need no bounds)
    image_downscale: int = 1  # files: average FxF pixel blocks of the format's resolution (cameras too)
    dtu_mask_dir: str = ""  # DTU object masks (RegNeRF's idrmasks); empty: found under the dataset root


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """What every field shares: the samplers, the view encoding, the heads and the choice of
    field; each field's own keys are in its section ([mlp] or [grid])."""

    # A name in `mx.nn.FIELD_BUILDERS`: "mlp", the mip-NeRF MLP ([mlp], the paper's), or "grid",
    # a grid and decoder ([grid]); checked when the model is built.
    field: str = "mlp"
    viewdir_max_deg: int = 4  # view-direction frequencies 2^0 .. 2^(viewdir_max_deg-1)
    num_coarse_samples: int = 128  # samples per ray at the coarse level
    num_fine_samples: int = 128  # samples per ray at the fine level
    density_bias: float = -1.0  # shift of the raw density before the softplus
    rgb_padding: float = 0.001  # colour range padding
    resample_padding: float = 0.01  # added to the blurred coarse weights before resampling
    lindisp: bool = False  # space coarse samples linearly in disparity
    frustum: Literal["auto", "cone", "cylinder"] = "auto"  # "auto": what the dataset says
    remat: bool = False  # recompute field activations in the backward pass (less memory, ~1/3 more compute)


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """The mip-NeRF MLP field (`model.field = "mlp"`, the paper's)."""

    width: int = 256  # trunk width (mip-NeRF: 256)
    depth: int = 8  # trunk depth (mip-NeRF: 8)
    view_width: int = 128  # width of the view-dependent layer (mip-NeRF: 128)
    skip_layer: int = 4  # input concatenated again after this trunk layer
    min_deg: int = 0  # lowest IPE frequency exponent
    max_deg: int = 16  # IPE frequencies 2^min_deg .. 2^(max_deg-1)
    density_noise: float = 1.0  # std of the raw-density noise in training
    matmul_dtype: Literal["float32", "bfloat16"] = "float32"  # dtype of the field's matrix products


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """The grid field (`model.field = "grid"`); the samplers and heads stay in [model]."""

    # A name in `mx.nn.ENCODING_BUILDERS`: "triplane", K-Planes-style planes, or "hash", a hash
    # grid; checked when the field is built.
    encoding: str = "triplane"
    levels: int = 4  # resolutions, growing geometrically from min_resolution to max_resolution
    min_resolution: int = 32  # coarsest level's resolution (plane texels / hash cells per axis)
    max_resolution: int = 256  # finest level's resolution
    features: int = 16  # features per level
    hash_table_log2: int = 17  # hash grid: log2 of the entries of each level's table
    decoder_width: int = 64  # width of the density decoder's hidden layer
    geo_features: int = 15  # features passed from the density decoder to the colour layer
    view_width: int = 64  # width of the view-dependent colour layer
    box_radius: float = 0.0  # > 0: the grid spans [-r, r]^3, nothing outside; 0: the training frusta's box
    scale_weighting: bool = True  # weight levels by the frustum's size (Zip-NeRF's anti-aliasing)
    tv_weight: float = 0.0  # weight of total variation on the planes (the tri-plane encoding)
    coarse_to_fine_steps: int = 0  # reveal the levels coarse to fine over this many steps (0: off)
    coarse_to_fine_fraction: float = 0.0  # > 0: ... over this fraction of the run instead (see below)
    density_noise: float = 0.0  # std of the raw-density noise in training
    density_activation: Literal["softplus", "exp"] = "softplus"  # raw density to density (exp: instant-ngp's)
    # How the field reads the grid: per point under jax.vmap ("vmap"), or batched with a
    # gradient that scatters once per level ("batched", faster on a CPU); the same values and
    # gradients. "auto": batched on the CPU, vmap on other backends.
    lookup: Literal["auto", "vmap", "batched"] = "auto"


def loss_weight(default: float, *, mixture: bool = False) -> Any:
    """A `[loss]` field that weighs a loss term (`mixnerf_eqx._train.loss.LossTerm.weight`):
    range-checked to be at least 0; with `mixture`, one of MixNeRF's own terms, of whose weights
    a MixNeRF run needs one non-zero. A new term's weight is declared this way in its section."""
    return dataclasses.field(default=default, metadata={"loss_weight": True, "mixture": mixture})


def loss_weight_keys(loss: Any) -> dict[str, bool]:
    """The `[loss]` keys that weigh loss terms, in `loss`'s section (a `LossConfig` or a
    subclass that declares more), each with whether its term is one of MixNeRF's own."""
    return {
        field.name: field.metadata["mixture"]
        for field in dataclasses.fields(loss)
        if field.metadata.get("loss_weight")
    }


@dataclasses.dataclass(frozen=True)
class LossConfig:
    coarse_mse_weight: float = loss_weight(0.1)  # MSE = MSE_fine + this * MSE_coarse
    lambda_colour_start: float = loss_weight(4.0, mixture=True)  # lambda_C at step 1
    lambda_colour_end: float = loss_weight(1e-3, mixture=True)  # lambda_C from `lambda_colour_steps` on
    lambda_colour_steps: int = 512  # length of lambda_C's linear ramp
    lambda_colour_fraction: float = 0.0  # > 0: the ramp lasts this fraction of the run instead
    lambda_depth: float = loss_weight(1e-3, mixture=True)  # lambda_D (Blender 4-view)
    lambda_regen: float = loss_weight(1e-4, mixture=True)  # lambda_hat_C (Blender 4-view)
    nll_levels: Literal["coarse", "both"] = "coarse"  # levels the NLLs apply to (released: coarse)
    # false: the colour NLLs do not train the samples' colours (their gradient stops at the
    # components' locations), only the weights and scales; true: the paper's NLLs.
    nll_trains_colour: bool = True
    weight_eps: float = 1e-10  # pi = w / (sum w + weight_eps)
    likelihood_floor: float = 1e-12  # NLL = -log(likelihood + floor); 0 for the exact NLL
    depth_scale: Literal["colour", "single"] = "colour"  # depth reuses the 3 colour scales
    nll_evaluation: Literal["log", "linear"] = "log"  # stable log space, or released arithmetic
    # The light past the last sample as a colour-mixture component of its own (the background
    # colour, Laplace scale `background_scale`) on scenes with a white background; off: the
    # weights normalised over the samples (the paper). No effect on scenes without a background.
    background_component: bool = False
    background_scale: float = 0.01  # that component's scale per channel
    distortion_weight: float = loss_weight(0.0)  # mip-NeRF 360's distortion loss on both levels (0: off, the paper)
    opacity_weight: float = loss_weight(0.0)  # mean ray opacity on both levels, a prior for empty space (0: off)
    opacity_entropy_weight: float = loss_weight(0.0)  # binary entropy of the ray opacity, both levels (0: off)
    unseen_entropy_weight: float = loss_weight(0.0)  # the same on the unseen-view patches below (0: off)
    depth_smoothness_weight: float = loss_weight(0.0)  # RegNeRF's depth smoothness on patches of unseen views (0: off)
    smoothness_patches: int = 4  # patches of unseen views rendered per step for the two unseen-view priors
    smoothness_patch_size: int = 8  # their side in pixels
    smoothness_views: int = 64  # unseen cameras to draw them from: a path through the training cameras


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    lr_init: float = 1e-3  # initial learning rate (Blender: 1e-3, LLFF/DTU: 2e-3)
    lr_final: float = 1e-5  # final learning rate of the log-linear decay
    warmup_steps: int = 512  # length of the sine warm-up
    warmup_fraction: float = 0.0  # > 0: the warm-up lasts this fraction of the run instead
    decay_steps: int = (
        0  # steps of the log-linear decay (0: train.max_steps; a continued run keeps its first)
    )
    grad_max_value: float = 0.1  # element-wise gradient clip (0 turns it off)
    grad_max_norm: float = 0.1  # global-norm gradient clip (0 turns it off)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    max_steps: int = 78125  # training steps (Blender 4-view: 500 epochs at 4096 rays)
    batch_size: int = 4096  # rays per step, all drawn from one random training image
    anneal_steps: int = 256  # sample-space annealing length N (0 turns it off)
    anneal_fraction: float = 0.0  # > 0: annealing lasts this fraction of the run instead
    anneal_start: float = 0.5  # annealing: initial fraction p of [near, far]
    anneal_mid: float = 0.5  # annealing: centre m of the initial interval
    seed: int = 0  # seed of the model initialisation and of every random draw
    eval_every: int = 0  # evaluate on validation views every this many steps (0: only at the end)
    num_eval_views: int = 2  # validation views rendered by the periodic evaluation
    checkpoint_every: int = 1000  # write a checkpoint every this many steps (and at the end)
    render_chunk: int = 4096  # rays rendered at once when rendering images
    run_dir: str = "runs/builtin"  # where checkpoints, metrics and renders go
    max_nonfinite_steps: int = 20  # stop after this many consecutive skipped (non-finite) steps
    data_parallel: Literal["auto", "on", "off"] = "auto"  # split each batch over every device (auto: if >1)
    # Where the training log goes: train_log.jsonl (always: the source of truth), and with
    # "tensorboard" also event files in RUN_DIR/tensorboard/ (the [tensorboard] extra).
    log_to: tuple[Literal["jsonl", "tensorboard"], ...] = ("jsonl",)


@dataclasses.dataclass(frozen=True)
class OccupancyConfig:
    enabled: bool = False  # keep an occupancy grid and skip empty space and finished rays when rendering
    render_skipping: bool = False  # renders of a trained run (its final evaluation, `eval`, `render`,
    # `view`) skip with a grid built from the model, even where training keeps none (enabled = false)
    resolution: int = 128  # grid cells per axis
    box_radius: float = (
        0.0  # > 0: the grid spans [-r, r]^3 and nothing lies outside; 0: the training frusta's box
    )
    density_threshold: float = 0.01  # a cell is occupied where its density exceeds this (with
    # choose_threshold: the smallest threshold tried)
    choose_threshold: bool = True  # for a trained model's renders, raise the threshold as far as
    # the threshold rays allow (mixnerf_eqx._inference.threshold)
    threshold_tolerance_db: float = 0.1  # largest PSNR lost on the threshold rays (as threshold_measure counts it)
    threshold_rays: int = 4096  # random pixels the threshold is chosen on
    threshold_views: Literal["val", "train"] = "val"  # the views those pixels come from ("val":
    # the validation views, the training views where a scene has none)
    threshold_measure: Literal["psnr", "bound"] = "psnr"  # on validation pixels: the PSNR lost
    # there ("psnr") or its worst-case bound ("bound"); training pixels always use the bound
    threshold_doublings: int = 14  # the threshold tried goes up to density_threshold * 2^this
    dilation: int = 1  # occupied cells also mark this many neighbouring cells on every side
    decay: float = 0.95  # each update keeps max(decay * old, new) per cell
    update_every: int = 16  # training steps between grid updates
    update_fraction: float = (
        0.25  # share of the cells that one update re-evaluates (every cell in 1/this updates)
    )
    stop_transmittance: float = (
        1e-4  # rendering: a ray stops once its transmittance falls below this (0: off)
    )
    segments: int = 4  # rendering: pieces of each level between which finished rays are dropped
    chunk: int = 16384  # rendering with skipping: rays per chunk
    render_chunk_points: int = 4096  # rendering with skipping: > 0, each level is one compiled
    # program evaluating chunks of this many points (chunks past the live samples skipped);
    # 0: buffers sized on the host (a compilation per size)
    # Training that skips (with `enabled`): once every cell has been evaluated, a step evaluates
    # the field only at the samples in occupied cells (and, on the fine level, in front of the
    # point where the coarse transmittance falls below `train_stop_transmittance`), gathered
    # into a buffer per level whose size is the share of samples last found live, plus
    # `train_headroom`, rounded up to a rung of 1, 0.71, 0.5, 0.35, ... (a few sizes, each step
    # compiled once); a smaller rung only when the seconds it saves over the steps left exceed
    # a compilation's (full buffers run the dense step).
    train_skipping: bool = False
    train_stop_transmittance: float = 1e-4  # 0: finished rays are evaluated in training
    train_headroom: float = 0.05  # share of the samples added to the live share measured
    train_budget_every: int = 10  # steps between measurements of the live share

    @property
    def renders_skip(self) -> bool:
        """Whether a trained run's renders skip unless told otherwise (`--skipping auto`)."""
        return self.enabled or self.render_skipping


@dataclasses.dataclass(frozen=True)
class Config:
    name: str = "mixnerf"  # a name for the run
    reproduces: str = ""  # the paper cell this config reproduces, if any
    chosen_on: str = ""  # which views chose the settings (the paper's; validation views; test: tuned)
    method: Literal["mixnerf", "mipnerf"] = "mixnerf"  # MixNeRF, or its mip-NeRF baseline (no mixture)
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    mlp: MLPConfig = MLPConfig()
    grid: GridConfig = GridConfig()
    loss: LossConfig = LossConfig()
    optim: OptimConfig = OptimConfig()
    train: TrainConfig = TrainConfig()
    occupancy: OccupancyConfig = OccupancyConfig()

    def __post_init__(self):
        validate(self)


def _at_least(low: int | float) -> tuple[Any, str]:
    return (lambda value: value >= low), f"must be >= {low:g}"


def _within(
    low: int | float, high: int | float, *, low_open: bool = False, high_open: bool = False
) -> tuple[Any, str]:
    def check(value):
        return (low < value if low_open else low <= value) and (value < high if high_open else value <= high)

    return check, f"must lie in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


_POSITIVE = ((lambda value: value > 0), "must be positive")

# The schedules that may be given in steps or as a fraction of the run: `section.name_steps`
# and `section.name_fraction`.
_SCHEDULE_KEYS = (
    ("optim", "warmup"),
    ("loss", "lambda_colour"),
    ("train", "anneal"),
    ("grid", "coarse_to_fine"),
)
_INT32_MAX = 2**31 - 1
SEED_MAX = 2**32 - 1  # the largest seed: JAX's keys take seeds modulo 2^32

# Range of every numeric setting: (section.key, check, what the check asks).
_RANGES: tuple[tuple[str, Any, str], ...] = (
    *(
        (key, *_POSITIVE)
        for key in (
            "data.num_train_views",
            "data.num_test_views",
            "data.image_downscale",
            "mlp.width",
            "mlp.depth",
            "mlp.view_width",
            "model.num_coarse_samples",
            "model.num_fine_samples",
            "optim.lr_init",
            "optim.lr_final",
            "train.max_steps",
            "train.batch_size",
            "train.render_chunk",
            "train.max_nonfinite_steps",
            "occupancy.threshold_rays",
            "occupancy.update_every",
            "occupancy.segments",
            "occupancy.chunk",
            "loss.background_scale",
            "grid.levels",
            "grid.features",
            "grid.decoder_width",
            "grid.view_width",
            "loss.smoothness_patches",
            "loss.smoothness_views",
        )
    ),
    *(
        (key, *_at_least(0))
        for key in (
            "data.max_test_views",
            "data.num_val_views",
            "data.max_val_views",
            "data.near",
            "data.far",
            "mlp.skip_layer",
            "mlp.min_deg",
            "model.viewdir_max_deg",
            "mlp.density_noise",
            "model.rgb_padding",
            "model.resample_padding",
            "loss.lambda_colour_steps",
            "loss.weight_eps",
            "loss.likelihood_floor",
            "optim.warmup_steps",
            "optim.decay_steps",
            "optim.grad_max_value",
            "optim.grad_max_norm",
            "train.anneal_steps",
            "train.eval_every",
            "train.num_eval_views",
            "train.checkpoint_every",
            "occupancy.box_radius",
            "occupancy.density_threshold",
            "occupancy.threshold_tolerance_db",
            "occupancy.threshold_doublings",
            "occupancy.dilation",
            "grid.geo_features",
            "grid.box_radius",
            "grid.tv_weight",
            "grid.coarse_to_fine_steps",
            "grid.density_noise",
        )
    ),
    ("grid.min_resolution", *_at_least(2)),
    # The held-out metrics need 32 pixels a side (LPIPS's network 31, SSIM an 11-pixel window).
    ("data.resolution", lambda value: value >= 32, "must be at least 32 (LPIPS and SSIM score images of 32 pixels a side or more)"),
    ("loss.smoothness_patch_size", *_at_least(2)),
    ("grid.hash_table_log2", *_within(3, 30)),
    ("mlp.max_deg", *_at_least(1)),
    ("train.max_steps", lambda value: value <= _INT32_MAX, f"must be at most {_INT32_MAX} (int32 steps)"),
    # JAX keys take the seed modulo 2^32: wider seeds would alias (seed 2^32 trains as seed 0).
    ("train.seed", lambda value: 0 <= value <= SEED_MAX, f"must lie in [0, {SEED_MAX}] (wider seeds alias)"),
    ("train.anneal_start", *_within(0, 1, low_open=True)),
    *((key, *_within(0, 1)) for key in (f"{section}.{name}_fraction" for section, name in _SCHEDULE_KEYS)),
    ("train.anneal_mid", *_within(0, 1)),
    ("occupancy.resolution", *_at_least(2)),
    ("occupancy.decay", *_within(0, 1)),
    ("occupancy.update_fraction", *_within(0, 1, low_open=True)),
    ("occupancy.stop_transmittance", *_within(0, 1, high_open=True)),
    ("occupancy.train_stop_transmittance", *_within(0, 1, high_open=True)),
    ("occupancy.train_headroom", *_within(0, 1)),
    ("occupancy.train_budget_every", *_at_least(1)),
    ("occupancy.render_chunk_points", *_at_least(0)),
)


def _setting(config: "Config", key: str) -> Any:
    section, name = key.split(".")
    return getattr(getattr(config, section), name)


# Each field's own section; the sections of the fields a config does not use stay at their
# defaults (a key set there would be ignored, so it is an error).
FIELD_SECTIONS = {"mlp": "mlp", "grid": "grid"}


# Grid keys that only one encoding reads: set for the other, they would be ignored.
ENCODING_KEYS = {"hash_table_log2": "hash", "tv_weight": "triplane"}


def did_you_mean(value: str, names) -> str:
    """` (did you mean 'x'?)` where `value` is close to one of `names` but none of them (the
    config knows the built-in field and encoding names only; `check_model_names` in
    `_nn/model.py` checks the model's tables with the same hint)."""
    close = [] if value in names else difflib.get_close_matches(value, list(names), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _inapplicable(config: "Config") -> list[str]:
    """The keys set in the section of a field that `model.field` does not choose, and the grid
    keys set for an encoding that does not read them."""
    problems = []
    if config.model.field == "grid":
        grid, defaults = config.grid, GridConfig()
        for name, encoding in ENCODING_KEYS.items():
            if grid.encoding != encoding and getattr(grid, name) != getattr(defaults, name):
                value, default = getattr(grid, name), getattr(defaults, name)
                hint = did_you_mean(grid.encoding, set(ENCODING_KEYS.values()))
                problems.append(
                    f"grid.{name} = {value!r} applies to grid.encoding = {encoding!r} only, and this config "
                    f"uses {grid.encoding!r}{hint}: remove it (or set it to {default!r})"
                )
    for field, section in FIELD_SECTIONS.items():
        if field == config.model.field:
            continue
        values, defaults = getattr(config, section), _SECTIONS[section]()
        changed = [
            f.name for f in dataclasses.fields(values) if getattr(values, f.name) != getattr(defaults, f.name)
        ]
        if changed:
            listed = ", ".join(f"{section}.{name} = {getattr(values, name)!r}" for name in changed)
            problems.append(
                f"{listed}: [{section}] does not apply to model.field = {config.model.field!r}"
                f"{did_you_mean(config.model.field, FIELD_SECTIONS)}; remove "
                f"{'it' if len(changed) == 1 else 'them'}, or set model.field = {field!r} (a config that "
                "sets model.field starts the other fields' sections from their defaults)"
            )
    return problems


def _consistency_problems(config: "Config") -> list[str]:
    """Settings that are each in range but cannot be used together."""
    problems = []
    data, loss, occupancy = config.data, config.loss, config.occupancy
    nll_weights = [getattr(loss, key) for key, mixture in loss_weight_keys(loss).items() if mixture]
    if config.method == "mixnerf" and nll_weights and not any(nll_weights):
        problems.append(
            'every mixture loss weight is zero: for the mip-NeRF baseline set method = "mipnerf" '
            "(the method is no longer inferred from the lambdas)"
        )
    mlp = config.mlp
    if config.model.field == "mlp" and mlp.skip_layer >= mlp.depth:
        problems.append(
            f"mlp.skip_layer must be below mlp.depth ({mlp.depth}), got {mlp.skip_layer} "
            "(0: no skip connection)"
        )
    if config.model.field == "mlp" and mlp.min_deg >= mlp.max_deg:
        problems.append(f"mlp.min_deg ({mlp.min_deg}) must be below mlp.max_deg ({mlp.max_deg})")
    problems += _inapplicable(config)
    if config.grid.max_resolution < config.grid.min_resolution:
        problems.append(
            f"grid.max_resolution ({config.grid.max_resolution}) must be at least grid.min_resolution "
            f"({config.grid.min_resolution})"
        )
    if data.far > 0 and data.near >= data.far:
        problems.append(f"data.near ({data.near:g}) must be below data.far ({data.far:g})")
    if not config.train.run_dir.strip():
        problems.append("train.run_dir must name a folder (it is empty)")
    if occupancy.train_skipping and not occupancy.enabled:
        problems.append(
            "occupancy.train_skipping needs occupancy.enabled = true (the grid that decides which samples "
            "are empty)"
        )
    if occupancy.choose_threshold and occupancy.density_threshold <= 0:
        problems.append(
            "occupancy.choose_threshold needs occupancy.density_threshold > 0 (the first threshold tried)"
        )
    if "jsonl" not in config.train.log_to:
        problems.append(
            f'train.log_to must hold "jsonl" (the log that resuming and every report read), got '
            f"{list(config.train.log_to)}"
        )
    return problems


@dataclasses.dataclass(frozen=True)
class ScheduleSteps:
    """The lengths in steps of the schedules that a config may give either way (a
    `*_fraction` > 0 of the run replaces the `*_steps` count). The run's length is the
    learning-rate decay's horizon, `optim.decay_steps` or else `train.max_steps`, so that a
    run continued to more steps keeps its schedules."""

    warmup: int
    lambda_colour: int
    anneal: int
    coarse_to_fine: int


def schedule_steps(config: "Config") -> ScheduleSteps:
    """Each schedule's length in steps (see `ScheduleSteps`); a fraction rounds to a whole
    number of steps, at least 1."""
    horizon = config.optim.decay_steps or config.train.max_steps
    lengths = {}
    for section, name in _SCHEDULE_KEYS:
        fraction = _setting(config, f"{section}.{name}_fraction")
        steps = _setting(config, f"{section}.{name}_steps")
        lengths[name] = max(1, round(fraction * horizon)) if fraction > 0 else steps
    return ScheduleSteps(**lengths)


class SettingWarning(UserWarning):
    """A setting a run accepts but cannot carry out in full (`setting_warnings`)."""


def setting_warnings(config: "Config") -> list[str]:
    """What `config` asks for that its run cannot do in full (a warning each, not an error: the
    run is still a valid one)."""
    found = []
    if config.model.field == "grid":
        reveal = schedule_steps(config).coarse_to_fine
        if reveal > config.train.max_steps:
            found.append(
                f"grid.coarse_to_fine_steps = {reveal} is longer than the run (train.max_steps = "
                f"{config.train.max_steps}): the finest levels are never fully revealed; give "
                "grid.coarse_to_fine_fraction (a fraction of the run) instead"
            )
    return found


def validate(config: "Config") -> None:
    """Raises `ConfigError` naming every setting whose value no run can use."""
    ranges = (*_RANGES, *((f"loss.{key}", *_at_least(0)) for key in loss_weight_keys(config.loss)))
    problems = [
        f"{key} {wanted}, got {_setting(config, key)!r}"
        for key, check, wanted in ranges
        if not check(_setting(config, key))
    ]
    problems += _non_finite(config)
    problems += _consistency_problems(config)
    if problems:
        raise ConfigError("; ".join(problems))


def _non_finite(config: "Config") -> list[str]:
    """Every float setting must be finite: no key documents inf or NaN (an infinite learning
    rate or bound only fails later, far from its cause)."""
    problems = []
    for section, schema in _SECTIONS.items():
        values = getattr(config, section)
        for field in dataclasses.fields(schema):
            value = getattr(values, field.name)
            if isinstance(value, float) and not math.isfinite(value):
                problems.append(f"{section}.{field.name} must be a finite number, got {value!r}")
    return problems


_TOP_LEVEL = ("name", "reproduces", "chosen_on", "method")
# Every section of `Config`, by name, in its order: the attributes that are dataclasses.
_SECTIONS = {
    field.name: type(field.default)
    for field in dataclasses.fields(Config)
    if dataclasses.is_dataclass(field.default)
}


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    """Checks (and where lossless converts) a TOML value against a field's annotation."""
    origin = typing.get_origin(annotation)
    if origin is Literal:
        if value not in typing.get_args(annotation):
            raise ConfigError(f"{where}: {value!r} is not one of {typing.get_args(annotation)}")
        return value
    if origin in (typing.Union, types.UnionType):
        for option in typing.get_args(annotation):
            try:
                return _coerce(value, option, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: {value!r} does not match {annotation}")
    if origin is tuple:
        item, *rest = typing.get_args(annotation)
        if rest != [Ellipsis] or not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return tuple(_coerce(entry, item, where) for entry in value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported annotation {annotation}")


# Keys that older versions wrote (run folders keep them in `config.json`): read, ignored, and
# named in a warning that says what replaced them.
_REMOVED_KEYS = {
    ("train", "typecheck"): "shape checks are switched by --no-typecheck (or JAXTYPING_DISABLE=1)",
}
# Keys that moved to another section or were renamed: read as the new key, with a warning
# naming it, so that old files, command lines and run folders (`config.json`) still load.
_MOVED_KEYS = {
    **{
        ("model", key): ("mlp", key)
        for key in ("width", "depth", "view_width", "skip_layer", "min_deg", "max_deg", "density_noise")
    },
    ("model", "matmul_dtype"): ("mlp", "matmul_dtype"),
    ("occupancy", "calibrate"): ("occupancy", "choose_threshold"),
    ("occupancy", "calibrate_tolerance_db"): ("occupancy", "threshold_tolerance_db"),
    ("occupancy", "calibrate_rays"): ("occupancy", "threshold_rays"),
    ("occupancy", "calibrate_doublings"): ("occupancy", "threshold_doublings"),
}


def _upgrade(values: dict[str, Any], source: str, base: "Config", written_by_a_run: bool) -> dict[str, Any]:
    """`values` with the keys of `_MOVED_KEYS` under their new names, each with a warning that
    names the new key. From a run's own files (`written_by_a_run`) they are read silently, and
    the sections of the fields the run does not use are dropped: the tool wrote them, the run
    never read them, and older versions kept whatever the config had there."""
    model = values.get("model")
    field = model.get("field", base.model.field) if isinstance(model, dict) else base.model.field
    upgraded = {key: dict(value) if isinstance(value, dict) else value for key, value in values.items()}
    for (section, key), (new_section, new_key) in _MOVED_KEYS.items():
        table, target = upgraded.get(section), upgraded.setdefault(new_section, {})
        if not isinstance(table, dict) or key not in table or not isinstance(target, dict):
            continue
        if new_key in target:
            raise ConfigError(
                f"{source}: {section}.{key} and {new_section}.{new_key} both given; {section}.{key} is "
                f"the old name of {new_section}.{new_key}"
            )
        target[new_key] = table.pop(key)
        if not written_by_a_run:
            warnings.warn(
                f"{source}: {section}.{key} is now {new_section}.{new_key}; read as that",
                FutureWarning,
                stacklevel=3,
            )
    if written_by_a_run:
        for other, section in FIELD_SECTIONS.items():
            if other != field:
                upgraded.pop(section, None)
    return {key: value for key, value in upgraded.items() if value != {} or key in values}


def _apply(base: Any, values: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(type(base))
    names = {f.name for f in dataclasses.fields(base)}
    section = next(name for name, cls in _SECTIONS.items() if isinstance(base, cls))
    updates = {}
    for key, value in values.items():
        if (section, key) in _REMOVED_KEYS:
            warnings.warn(
                f"{where}: {key} is no longer a setting and is ignored; {_REMOVED_KEYS[section, key]}",
                DeprecationWarning,
                stacklevel=2,
            )
            continue
        if key not in names:
            # The key first, on a line of its own: `where` may list every override given.
            raise ConfigError(
                f"unknown key {key!r} in [{section}] ({section}.{key})\n"
                f"  given in: {where}\n  known keys of [{section}]: {', '.join(sorted(names))}"
            )
        updates[key] = _coerce(value, hints[key], f"{section}.{key} (given in {where})")
    return dataclasses.replace(base, **updates)


def config_from_dict(
    values: dict[str, Any],
    source: str = "<dict>",
    base: Config | None = None,
    *,
    written_by_a_run: bool = False,
) -> Config:
    """Builds a `Config` from nested dictionaries (the layout of a TOML file).

    Unknown sections or keys raise a `ConfigError` naming the key and `source`. Keys that
    moved are read under their new names with a warning; `written_by_a_run` (a run's
    `config.json` or checkpoint metadata) reads them silently and ignores the sections of the
    fields the run does not use.
    """
    base = Config() if base is None else base
    values = _upgrade(values, source, base, written_by_a_run)
    model = values.get("model")
    field = model.get("field", base.model.field) if isinstance(model, dict) else base.model.field
    if field != base.model.field and base.model.field in FIELD_SECTIONS:
        # Switching the field starts from the defaults of the section it leaves (a grid config
        # extending an MLP config does not inherit the MLP's sizes).
        left = FIELD_SECTIONS[base.model.field]
        base = dataclasses.replace(base, **{left: _SECTIONS[left]()})
    top_updates = {}
    section_updates = {}
    for key, value in values.items():
        if key in _SECTIONS:
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: [{key}] must be a table")
            section_updates[key] = _apply(getattr(base, key), value, f"{source} [{key}]")
        elif key in _TOP_LEVEL:
            top_updates[key] = _coerce(value, typing.get_type_hints(Config)[key], f"{source}: {key}")
        else:
            raise ConfigError(
                f"{source}: unknown key {key!r} (known: {', '.join(_TOP_LEVEL)}, {', '.join(_SECTIONS)})"
            )
    try:
        return dataclasses.replace(base, **top_updates, **section_updates)
    except ConfigError as error:
        raise ConfigError(f"{source}: {error}") from None


def _load_file(path: Path, chain: tuple[Path, ...]) -> Config:
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    if path.resolve() in chain:
        raise ConfigError(f"{path}: 'extends' forms a cycle")
    try:
        values = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    except UnicodeDecodeError as error:
        raise ConfigError(f"{path}: not a UTF-8 text file (byte {error.start}); save it as UTF-8 TOML") from None
    base = Config()
    parent = values.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError(f"{path}: extends must be a file name")
        base = _load_file(path.parent / parent, (*chain, path.resolve()))
    return config_from_dict(values, str(path), base)


def _packaged_configs() -> Path:
    folder = importlib.resources.files("mixnerf_eqx") / "configs"
    # An installed package is a folder on disk (setuptools installs no zipped eggs), and
    # `extends` needs the files beside each other.
    return Path(str(folder))


def config_names() -> list[str]:
    """The names of the configs the package carries (`load_config(name)` loads one)."""
    return sorted(path.stem for path in _packaged_configs().glob("*.toml"))


def config_path(name_or_path: str | Path) -> Path:
    """The file that `name_or_path` names: a TOML file, or one of the package's configs by its
    name (`"llff3_grid"`, or `"llff3_grid.toml"`) when no such file exists."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    if path.parent != Path("."):
        hint = ""
        if path.suffix == ".toml" and (_packaged_configs() / path.name).is_file():
            hint = f" (the package carries one by that name: --config {path.stem})"
        raise ConfigError(f"config file {path} does not exist{hint}")
    packaged = _packaged_configs() / f"{path.stem if path.suffix == '.toml' else path.name}.toml"
    if packaged.is_file():
        return packaged
    raise ConfigError(
        f"no file {path} here and no packaged config named {packaged.stem} "
        f"(the package's: {', '.join(config_names())})"
    )


def load_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> Config:
    """Loads a TOML config (defaults when `path` is None) and applies `section.key=value`
    overrides, whose values are parsed as TOML (strings may be left unquoted).

    `path` is a file, or the name of one of the package's configs (`config_names()`). A file
    may start from another with `extends = "other.toml"` (relative to the file).
    """
    config = Config() if path is None else _load_file(config_path(path), ())
    # All overrides are applied at once, so that settings that must change together (the
    # method and its loss weights) can be given as separate overrides.
    merged: dict[str, Any] = {}
    origin: dict[tuple[str, ...], str] = {}  # who set each value: the override to blame
    for override in overrides:
        key, sep, raw = override.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {override!r} is not of the form section.key=value")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        parts = key.strip().split(".")
        cursor = merged
        for depth, part in enumerate(parts[:-1]):
            cursor = cursor.setdefault(part, {})
            if not isinstance(cursor, dict):
                culprit = origin.get(tuple(parts[: depth + 1]), override)
                raise ConfigError(
                    f"override {culprit!r}: {part} is a section, not a value; give section.key=value"
                )
        cursor[parts[-1]] = value
        origin[tuple(parts)] = override
    if not merged:
        return config
    listed = ", ".join(repr(o) for o in overrides)
    return config_from_dict(merged, f"override{'s' if len(overrides) > 1 else ''} {listed}", config)


def replace_setting(config: Config, section: str, **values: Any) -> Config:
    """`config` with `values` set in `section` (checked like a file's values)."""
    return config_from_dict({section: values}, f"[{section}] {', '.join(values)}", config)


def config_to_dict(config: Config) -> dict[str, Any]:
    """The config as plain nested dictionaries (for JSON and checkpoints)."""
    return dataclasses.asdict(config)
