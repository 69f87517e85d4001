"""Typed, frozen configuration loaded from `configs/*.toml`, and `build_model`."""

import dataclasses
import tomllib
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import jax

from ._custom_types import PRNGKey
from ._field import MipNeRFField
from ._loss import LossWeights
from ._mixture import LaplaceMixture
from ._model import MixNeRF
from ._renderer import VolumeRenderer
from ._sampler import HierarchicalSampler, StratifiedSampler


class ConfigError(ValueError):
    """A configuration file or override that cannot be used."""


@dataclasses.dataclass(frozen=True)
class DataConfig:
    dataset: Literal["builtin", "blender", "llff", "dtu", "transforms"] = "builtin"  # the files' format
    scene: str = "builtin"  # scene folder (lego, fern, scan8, ...); "builtin": the procedural scene
    data_dir: str = ""  # dataset root; empty: the environment variable MIXNERF_DATA_DIR
    protocol: Literal["mixnerf", "dietnerf"] = "mixnerf"  # Blender split: MixNeRF's or DietNeRF's views
    resolution: int = 64  # built-in scene: image height and width in pixels
    num_train_views: int = 4  # number of training views
    num_test_views: int = 8  # built-in scene: number of held-out test views
    max_test_views: int = 0  # files: keep this many of the protocol's test views, evenly spaced (0: all)
    near: float = 0.0  # with far > 0: replaces the dataset's near bound
    far: float = 0.0  # > 0: replaces the dataset's far bound (transforms.json scenes need no bounds)
    image_downscale: int = 1  # files: average FxF pixel blocks of the format's resolution (cameras too)
    dtu_mask_dir: str = ""  # DTU object masks (RegNeRF's idrmasks); empty: found under the dataset root


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    width: int = 256  # trunk width (mip-NeRF: 256)
    depth: int = 8  # trunk depth (mip-NeRF: 8)
    view_width: int = 128  # width of the view-dependent layer (mip-NeRF: 128)
    skip_layer: int = 4  # input concatenated again after this trunk layer
    min_deg: int = 0  # lowest IPE frequency exponent
    max_deg: int = 16  # IPE frequencies 2^min_deg .. 2^(max_deg-1)
    viewdir_max_deg: int = 4  # view-direction frequencies 2^0 .. 2^(viewdir_max_deg-1)
    num_coarse_samples: int = 128  # samples per ray at the coarse level
    num_fine_samples: int = 128  # samples per ray at the fine level
    density_noise: float = 1.0  # std of the raw-density noise in training
    density_bias: float = -1.0  # shift of the raw density before the softplus
    rgb_padding: float = 0.001  # colour range padding
    resample_padding: float = 0.01  # added to the blurred coarse weights before resampling
    lindisp: bool = False  # space coarse samples linearly in disparity
    frustum: Literal["auto", "cone", "cylinder"] = "auto"  # "auto": what the dataset says
    remat: bool = False  # recompute MLP activations in the backward pass (less memory, ~1/3 more compute)
    matmul_dtype: Literal["float32", "bfloat16"] = "float32"  # dtype of the field's matrix products


@dataclasses.dataclass(frozen=True)
class LossConfig:
    coarse_mse_weight: float = 0.1  # MSE = MSE_fine + this * MSE_coarse
    lambda_colour_start: float = 4.0  # lambda_C at step 0
    lambda_colour_end: float = 1e-3  # lambda_C from `lambda_colour_steps` on
    lambda_colour_steps: int = 512  # length of lambda_C's linear ramp
    lambda_depth: float = 1e-3  # lambda_D (Blender 4-view)
    lambda_regen: float = 1e-4  # lambda_hat_C (Blender 4-view)
    nll_levels: Literal["coarse", "both"] = "coarse"  # levels the NLLs apply to (released: coarse)
    weight_eps: float = 1e-10  # pi = w / (sum w + weight_eps)
    likelihood_floor: float = 1e-12  # NLL = -log(likelihood + floor); 0 for the exact NLL
    depth_scale: Literal["colour", "single"] = "colour"  # depth reuses the 3 colour scales
    nll_evaluation: Literal["log", "linear"] = "log"  # stable log space, or released arithmetic

    @property
    def is_baseline(self) -> bool:
        """True when every NLL weight is zero: the mip-NeRF baseline."""
        return (
            self.lambda_colour_start == 0
            and self.lambda_colour_end == 0
            and self.lambda_depth == 0
            and self.lambda_regen == 0
        )

    def weights(self) -> LossWeights:
        return LossWeights(
            coarse_mse=self.coarse_mse_weight,
            colour_nll=self.lambda_colour_start != 0 or self.lambda_colour_end != 0,
            depth_nll=self.lambda_depth,
            regen_nll=self.lambda_regen,
            nll_levels=self.nll_levels,
        )


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    lr_init: float = 1e-3  # initial learning rate (Blender: 1e-3, LLFF/DTU: 2e-3)
    lr_final: float = 1e-5  # final learning rate of the log-linear decay
    warmup_steps: int = 512  # length of the sine warm-up
    grad_max_value: float = 0.1  # element-wise gradient clip (0 turns it off)
    grad_max_norm: float = 0.1  # global-norm gradient clip (0 turns it off)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    max_steps: int = 78125  # training steps (Blender 4-view: 500 epochs at 4096 rays)
    batch_size: int = 4096  # rays per step, all drawn from one random training image
    anneal_steps: int = 256  # sample-space annealing length N (0 turns it off)
    anneal_start: float = 0.5  # annealing: initial fraction p of [near, far]
    anneal_mid: float = 0.5  # annealing: centre m of the initial interval
    seed: int = 0  # seed of the model initialisation and of every random draw
    eval_every: int = 0  # evaluate on held-out views every this many steps (0: only at the end)
    num_eval_views: int = 2  # held-out views rendered by the periodic evaluation
    checkpoint_every: int = 1000  # write a checkpoint every this many steps (and at the end)
    render_chunk: int = 4096  # rays rendered at once when rendering images
    run_dir: str = "runs/builtin"  # where checkpoints, metrics and renders go
    typecheck: bool = True  # runtime jaxtyping/beartype checks (trace time only)
    max_nonfinite_steps: int = 20  # stop after this many consecutive skipped (non-finite) steps


@dataclasses.dataclass(frozen=True)
class OccupancyConfig:
    enabled: bool = False  # keep an occupancy grid and skip empty space and finished rays when rendering
    resolution: int = 128  # grid cells per axis
    box_radius: float = (
        0.0  # > 0: the grid spans [-r, r]^3 and nothing lies outside; 0: the training frusta's box
    )
    density_threshold: float = 0.01  # a cell is occupied where its density exceeds this (with
    # calibrate: the smallest threshold tried)
    calibrate: bool = True  # for a trained model's renders, raise the threshold as far as the
    # calibration rays allow (mixnerf_eqx._calibrate)
    calibrate_tolerance_db: float = 0.1  # largest bound on the PSNR lost on the calibration rays
    calibrate_rays: int = 4096  # calibration rays: random pixels of the training views
    calibrate_doublings: int = 14  # the threshold tried goes up to density_threshold * 2^this
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


@dataclasses.dataclass(frozen=True)
class Config:
    name: str = "mixnerf"  # a name for the run
    reproduces: str = ""  # the paper cell this config reproduces, if any
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    loss: LossConfig = LossConfig()
    optim: OptimConfig = OptimConfig()
    train: TrainConfig = TrainConfig()
    occupancy: OccupancyConfig = OccupancyConfig()

    def __post_init__(self):
        validate(self)


def validate(config: Config) -> None:
    """Raises `ConfigError` for values no run can use."""
    problems = []
    positive = {
        "model.width": config.model.width,
        "model.depth": config.model.depth,
        "model.view_width": config.model.view_width,
        "model.num_coarse_samples": config.model.num_coarse_samples,
        "model.num_fine_samples": config.model.num_fine_samples,
        "train.max_steps": config.train.max_steps,
        "train.batch_size": config.train.batch_size,
        "train.render_chunk": config.train.render_chunk,
        "data.resolution": config.data.resolution,
        "data.num_train_views": config.data.num_train_views,
        "optim.lr_init": config.optim.lr_init,
        "optim.lr_final": config.optim.lr_final,
    }
    problems += [f"{name} must be positive, got {value}" for name, value in positive.items() if value <= 0]
    if config.loss.likelihood_floor < 0:
        problems.append("loss.likelihood_floor must be >= 0")
    if not 0 < config.train.anneal_start <= 1:
        problems.append("train.anneal_start must lie in (0, 1]")
    occupancy = config.occupancy
    if occupancy.resolution < 2:
        problems.append(f"occupancy.resolution must be at least 2, got {occupancy.resolution}")
    if occupancy.box_radius < 0:
        problems.append("occupancy.box_radius must be >= 0")
    if occupancy.density_threshold < 0:
        problems.append("occupancy.density_threshold must be >= 0")
    if occupancy.dilation < 0:
        problems.append("occupancy.dilation must be >= 0")
    if occupancy.calibrate and occupancy.density_threshold <= 0:
        problems.append(
            "occupancy.calibrate needs occupancy.density_threshold > 0 (the first threshold tried)"
        )
    if occupancy.calibrate_tolerance_db < 0 or occupancy.calibrate_doublings < 0:
        problems.append("occupancy.calibrate_tolerance_db and occupancy.calibrate_doublings must be >= 0")
    if occupancy.calibrate_rays < 1:
        problems.append("occupancy.calibrate_rays must be positive")
    if not 0 <= occupancy.decay <= 1:
        problems.append("occupancy.decay must lie in [0, 1]")
    if occupancy.update_every < 1:
        problems.append("occupancy.update_every must be positive")
    if not 0 < occupancy.update_fraction <= 1:
        problems.append("occupancy.update_fraction must lie in (0, 1]")
    if not 0 <= occupancy.stop_transmittance < 1:
        problems.append("occupancy.stop_transmittance must lie in [0, 1)")
    if occupancy.segments < 1 or occupancy.chunk < 1:
        problems.append("occupancy.segments and occupancy.chunk must be positive")
    if problems:
        raise ConfigError("; ".join(problems))


_SECTIONS = {
    "data": DataConfig,
    "model": ModelConfig,
    "loss": LossConfig,
    "optim": OptimConfig,
    "train": TrainConfig,
    "occupancy": OccupancyConfig,
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


def _apply(base: Any, values: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(type(base))
    names = {f.name for f in dataclasses.fields(base)}
    updates = {}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(names))})")
        updates[key] = _coerce(value, hints[key], f"{where}: {key}")
    return dataclasses.replace(base, **updates)


def config_from_dict(values: dict[str, Any], source: str = "<dict>", base: Config | None = None) -> Config:
    """Builds a `Config` from nested dictionaries (the layout of a TOML file).

    Unknown sections or keys raise a `ConfigError` naming the key and `source`.
    """
    base = Config() if base is None else base
    top_updates = {}
    section_updates = {}
    for key, value in values.items():
        if key in _SECTIONS:
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: [{key}] must be a table")
            section_updates[key] = _apply(getattr(base, key), value, f"{source} [{key}]")
        elif key in ("name", "reproduces"):
            top_updates[key] = _coerce(value, str, f"{source}: {key}")
        else:
            raise ConfigError(
                f"{source}: unknown key {key!r} (known: name, reproduces, {', '.join(_SECTIONS)})"
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
        values = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    base = Config()
    parent = values.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError(f"{path}: extends must be a file name")
        base = _load_file(path.parent / parent, (*chain, path.resolve()))
    return config_from_dict(values, str(path), base)


def load_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> Config:
    """Loads a TOML config (defaults when `path` is None) and applies `section.key=value`
    overrides, whose values are parsed as TOML (strings may be left unquoted).

    A file may start from another with `extends = "other.toml"` (relative to the file).
    """
    config = Config() if path is None else _load_file(Path(path), ())
    for override in overrides:
        key, sep, raw = override.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {override!r} is not of the form section.key=value")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        nested: dict[str, Any] = {}
        parts = key.strip().split(".")
        cursor = nested
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = value
        config = config_from_dict(nested, f"override {override!r}", config)
    return config


def config_to_dict(config: Config) -> dict[str, Any]:
    """The config as plain nested dictionaries (for JSON and checkpoints)."""
    return dataclasses.asdict(config)


def build_model(
    config: Config, *, key: PRNGKey, frustum: str = "cone", white_background: bool = True
) -> MixNeRF:
    """Builds the model that `config` describes.

    **Arguments:**

    - `config`: the run's configuration.
    - `key`: initialisation randomness.
    - `frustum`: the dataset's frustum shape, used when `config.model.frustum` is `"auto"`.
    - `white_background`: composite on white (Blender-style scenes).

    **Returns:**

    A `MixNeRF`; with all NLL weights zero, the mip-NeRF baseline (no mixture heads).
    """
    model_cfg = config.model
    shape = frustum if model_cfg.frustum == "auto" else model_cfg.frustum
    baseline = config.loss.is_baseline
    field = MipNeRFField(
        width=model_cfg.width,
        depth=model_cfg.depth,
        view_width=model_cfg.view_width,
        skip_layer=model_cfg.skip_layer,
        min_deg=model_cfg.min_deg,
        max_deg=model_cfg.max_deg,
        viewdir_max_deg=model_cfg.viewdir_max_deg,
        density_noise=model_cfg.density_noise,
        density_bias=model_cfg.density_bias,
        rgb_padding=model_cfg.rgb_padding,
        mixture_heads=not baseline,
        matmul_dtype=model_cfg.matmul_dtype,
        key=key,
    )
    mixture = None
    if not baseline:
        mixture = LaplaceMixture(
            weight_eps=config.loss.weight_eps,
            likelihood_floor=config.loss.likelihood_floor or None,
            depth_scale=config.loss.depth_scale,
            evaluation=config.loss.nll_evaluation,
        )
    return MixNeRF(
        field=field,
        coarse_sampler=StratifiedSampler(model_cfg.num_coarse_samples, shape, model_cfg.lindisp),
        fine_sampler=HierarchicalSampler(model_cfg.num_fine_samples, shape, model_cfg.resample_padding),
        renderer=VolumeRenderer((1.0, 1.0, 1.0) if white_background else None),
        mixture=mixture,
        remat=model_cfg.remat,
    )


def init_key(config: Config) -> PRNGKey:
    """The root random key of a run."""
    return jax.random.key(config.train.seed)
