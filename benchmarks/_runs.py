"""Shared pieces of `error_vs_time.py` and `sample_count.py` (not a benchmark itself).

- Scene and variant specs from the command line, and the configs they resolve to.
- Cheap evaluation views: a fixed subset of the test views, optionally area-downsampled.
- `TrainingRun`: one model trained by the library's jitted step, compiled ahead of time with
  `.lower(...).compile()` so that compilation is timed apart from the steps, each step timed
  to completion.
- The schedule rule for short runs, output paths, machine description and table printing.

Spec syntax (both scripts):

    --scene lego                               preset (lego: configs/blender4.toml, fern: configs/llff3.toml)
    --scene NAME=CONFIG[:key=value,...]        a scene of your own: CONFIG's [data] section and settings
    --variant NAME=scene[:key=value,...]       the scene's own config (the paper settings of its dataset)
    --variant NAME=FILE.toml[:key=value,...]   a config file used for every scene it fits (see below)

Override lists are comma-separated `section.key=value` items, parsed like the overrides of
`load_config`; the macros `@baseline` (the three NLL weights at zero: the mip-NeRF baseline)
and `@fast` (32 + 32 samples, bfloat16 matrix products) expand in place.

A variant that names a file takes everything but the data from that file and the `[data]`
section from the scene, so a scene-independent file (one that names no dataset, like
`configs/paper_base.toml`) serves every scene. A file that names a dataset (`blender4.toml`
names blender) is scene-specific: it runs on the scenes of that dataset only (with their
`data.scene`), and is skipped, with a message, on the others, rather than training fern with
Blender's learning rate and loss weights.

Order of the overrides, later ones winning: the scene's or file's settings, then `--set`
(for every variant), then the variant's own overrides, then what the script itself sets
(data root, test-view subset, schedule length).
"""

import argparse
import contextlib
import dataclasses
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np

from mixnerf_eqx import Config, build_model, load_config
from mixnerf_eqx._config import init_key
from mixnerf_eqx._occupancy import refresh_occupancy, update_occupancy
from mixnerf_eqx._skipping import Skipping
from mixnerf_eqx._train import (
    make_occupancy_grid,
    make_optimizer,
    make_skipping,
    make_train_step,
    training_rays,
)
from mixnerf_eqx.data import Dataset, Views, load_dataset

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"

SCENE_PRESETS = {
    "lego": str(REPO / "configs" / "blender4.toml"),
    "fern": str(REPO / "configs" / "llff3.toml"),
}

MACROS = {
    "@baseline": (
        "loss.lambda_colour_start=0.0",
        "loss.lambda_colour_end=0.0",
        "loss.lambda_depth=0.0",
        "loss.lambda_regen=0.0",
    ),
    "@fast": (
        "model.num_coarse_samples=32",
        "model.num_fine_samples=32",
        'model.matmul_dtype="bfloat16"',
    ),
}


# ----------------------------------------------------------------------------- specs


@dataclasses.dataclass(frozen=True)
class Spec:
    """A named config: `base` is a TOML file or, for variants, the word `scene`."""

    name: str
    base: str
    overrides: tuple[str, ...] = ()

    def describe(self) -> str:
        return self.base + (":" + ",".join(self.overrides) if self.overrides else "")


def expand_overrides(items: Sequence[str]) -> tuple[str, ...]:
    """Expands the macros of an override list and checks the `key=value` form."""
    expanded: list[str] = []
    for item in items:
        item = item.strip()
        if not item:
            continue
        if item.startswith("@"):
            if item not in MACROS:
                raise argparse.ArgumentTypeError(f"unknown macro {item!r} (known: {', '.join(MACROS)})")
            expanded.extend(MACROS[item])
        elif "=" not in item:
            raise argparse.ArgumentTypeError(f"override {item!r} is not of the form section.key=value")
        else:
            expanded.append(item)
    return tuple(expanded)


def _split_spec(text: str, what: str) -> tuple[str, str, tuple[str, ...]]:
    name, sep, rest = text.partition("=")
    if not sep or not name.strip() or not rest.strip():
        raise argparse.ArgumentTypeError(f"{what} {text!r} is not of the form NAME=CONFIG[:key=value,...]")
    base, _, tail = rest.partition(":")
    return name.strip(), base.strip(), expand_overrides(tail.split(","))


def scene_spec(text: str) -> Spec:
    """`lego`, `fern` or `NAME=CONFIG[:overrides]` (argparse type)."""
    if "=" not in text:
        if text not in SCENE_PRESETS:
            raise argparse.ArgumentTypeError(
                f"unknown scene preset {text!r} (presets: {', '.join(SCENE_PRESETS)}); "
                "or give NAME=CONFIG[:key=value,...]"
            )
        return Spec(text, SCENE_PRESETS[text])
    name, base, overrides = _split_spec(text, "scene")
    if base == "scene":
        raise argparse.ArgumentTypeError(f"scene {name!r}: give a config file, not 'scene'")
    return Spec(name, base, overrides)


def variant_spec(text: str) -> Spec:
    """`NAME=scene[:overrides]` or `NAME=FILE[:overrides]` (argparse type)."""
    return Spec(*_split_spec(text, "variant"))


def override_keys(overrides: Sequence[str]) -> set[str]:
    """The `section.key` names an override list sets."""
    return {item.partition("=")[0].strip() for item in overrides}


def toml_value(value: Any) -> str:
    """A config value written as TOML, for an override string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string
    return repr(value)


def data_overrides(config: Config) -> list[str]:
    """The whole `[data]` section of `config` as override strings."""
    return [f"data.{key}={toml_value(value)}" for key, value in dataclasses.asdict(config.data).items()]


@dataclasses.dataclass(frozen=True)
class Resolved:
    """A variant on a scene: the config file and override list to load, or why it is skipped."""

    path: str
    overrides: tuple[str, ...]
    skip_reason: str | None = None


def resolve(scene: Spec, variant: Spec, common: Sequence[str]) -> Resolved:
    """The file and overrides of `variant` on `scene`, before the script's own overrides."""
    if variant.base == "scene":
        return Resolved(scene.base, (*scene.overrides, *common, *variant.overrides))
    scene_config = load_config(scene.base, scene.overrides)
    file_config = load_config(variant.base)
    if file_config.data.dataset not in ("builtin", scene_config.data.dataset):
        return Resolved(
            variant.base,
            (),
            f"{variant.base} is a {file_config.data.dataset} config and scene {scene.name!r} is "
            f"{scene_config.data.dataset}; use a scene-independent file or 'scene'",
        )
    return Resolved(variant.base, (*data_overrides(scene_config), *common, *variant.overrides))


def load(resolved: Resolved, extra: Sequence[str] = ()) -> Config:
    return load_config(resolved.path, [*resolved.overrides, *extra])


def data_dir_override(data_dir: str | None) -> list[str]:
    return [] if not data_dir else [f"data.data_dir={json.dumps(str(Path(data_dir).expanduser()))}"]


# ----------------------------------------------------------------------------- schedule


# Schedule lengths that the paper gives in steps, and the share of a short run they may take.
_SCHEDULE_CAPS = {
    "optim.warmup_steps": 10,
    "loss.lambda_colour_steps": 10,
    "train.anneal_steps": 5,
}


def schedule_overrides(config: Config, max_steps: int, explicit: set[str]) -> list[str]:
    """`train.max_steps` and, for runs too short for them, shortened warm-up and ramps.

    The paper's learning-rate warm-up (512 steps), lambda_C ramp (512) and sample-space
    annealing (256 or 512) are kept unless they would exceed a tenth (warm-up, ramp) or a
    fifth (annealing) of `max_steps`, the shares that `short_real_runs.py` uses; then they
    are cut to that share. Keys set on the command line (`explicit`) are left alone.
    """
    overrides = [f"train.max_steps={max_steps}"]
    for key, share in _SCHEDULE_CAPS.items():
        if key in explicit:
            continue
        section, name = key.split(".")
        current = getattr(getattr(config, section), name)
        cap = max(1, max_steps // share)
        if current > cap:
            overrides.append(f"{key}={cap}")
    return overrides


# ----------------------------------------------------------------------------- data


def downscale_views(views: Views, factor: int) -> tuple[Views, int]:
    """Area-downsamples the views by `factor` (or the largest factor <= it that divides both
    image sides); focal length and intrinsics are divided by it.

    Pixel centres sit at `col + 0.5` (see `mixnerf_eqx._rays`), so a box average over
    `f x f` blocks is exactly the camera with every intrinsic divided by `f`; NDC rays stay
    in the same NDC space, because it depends on focal / width and focal / height only.
    Object masks are kept by majority; true depths are dropped (not reported here).

    **Returns:**

    `(views, factor used)`.
    """
    if factor <= 1:
        return views, 1
    common = math.gcd(views.height, views.width)
    used = max(d for d in range(1, factor + 1) if common % d == 0)
    if used == 1:
        return views, 1
    n, h, w = views.images.shape[:3]

    def blocks(array: np.ndarray) -> np.ndarray:
        return array.reshape(n, h // used, used, w // used, used, *array.shape[3:])

    images = blocks(views.images).mean(axis=(2, 4), dtype=np.float64).astype(np.float32)
    intrinsics = None
    if views.intrinsics is not None:
        intrinsics = np.array(views.intrinsics, np.float64, copy=True)
        intrinsics[:, :2, :] /= used
        intrinsics = intrinsics.astype(views.intrinsics.dtype)
    masks = None
    if views.masks is not None:
        masks = blocks(views.masks.astype(np.float32)).mean(axis=(2, 4)) >= 0.5
    return (
        dataclasses.replace(
            views, images=images, focal=views.focal / used, intrinsics=intrinsics, masks=masks, depths=None
        ),
        used,
    )


class DatasetCache:
    """Loads each scene once (per distinct `[data]` section) and prepares its test views."""

    def __init__(self, eval_downscale: int):
        self.eval_downscale = eval_downscale
        self._cache: dict[Any, tuple[Dataset, dict[str, Any]]] = {}

    def get(self, config: Config) -> tuple[Dataset, dict[str, Any]]:
        if config.data not in self._cache:
            started = time.perf_counter()
            dataset = load_dataset(config.data)
            load_s = time.perf_counter() - started
            test, used = downscale_views(dataset.test, self.eval_downscale)
            info = {
                "load_s": load_s,
                "train_views": dataset.train.num_views,
                "train_size": [dataset.train.width, dataset.train.height],
                "test_view_ids": list(test.ids),
                "test_size": [test.width, test.height],
                "eval_downscale": used,
            }
            if used != self.eval_downscale:
                print(
                    f"note: {dataset.name}: test views of {dataset.test.width}x{dataset.test.height} "
                    f"cannot be downsampled by {self.eval_downscale}; using {used}"
                )
            self._cache[config.data] = (dataclasses.replace(dataset, test=test), info)
        return self._cache[config.data]


# ----------------------------------------------------------------------------- training


@contextlib.contextmanager
def typechecking(enabled: bool) -> Iterator[None]:
    """Runtime shape checks on or off (they act while JAX traces), as `fit` sets them."""
    previous = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", not enabled)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", previous)


class TrainingDiverged(RuntimeError):
    pass


_update_occupancy = eqx.filter_jit(update_occupancy)
_refresh_occupancy = eqx.filter_jit(refresh_occupancy)


class TrainingRun:
    """A model, its optimiser state and its compiled training step (the library's own).

    The model and key come from the config's seed exactly as in `fit`. `compile()` lowers
    and compiles the step ahead of time without running it (the model is not changed);
    `advance()` runs one step to completion and returns its wall time.

    With `occupancy.enabled`, the occupancy grid is kept up to date as `fit` keeps it (a
    share of the cells every `occupancy.update_every` steps, compiled ahead too) and those
    updates count as training time; `skipping()` gives the renderer options for evaluation,
    with the grid refreshed in every cell as `fit` does before its final evaluation.
    """

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config
        model_key, self.key = jax.random.split(init_key(config))
        self.model = build_model(
            config, key=model_key, frustum=dataset.frustum, white_background=dataset.white_background
        )
        optimizer = make_optimizer(config)
        self.opt_state = optimizer.init(eqx.filter(self.model, eqx.is_array))
        self.data = training_rays(dataset)
        self._step_fn = make_train_step(config, optimizer)
        self._compiled = None
        self.grid = make_occupancy_grid(config, dataset) if config.occupancy.enabled else None
        self._grid_key = jax.random.fold_in(self.key, 0x0CC)  # as in fit
        self._compiled_update = None
        self.step = 0
        self.skipped = 0
        self._streak = 0

    def _update_arguments(self, done: int) -> tuple[tuple, dict[str, Any]]:
        occupancy = self.config.occupancy
        return (self.grid, self.model.field), {
            "key": jax.random.fold_in(self._grid_key, done),
            "decay": occupancy.decay,
            "fraction": occupancy.update_fraction,
            "offset": jnp.asarray(done // occupancy.update_every, jnp.int32),
        }

    def compile(self) -> float:
        """Traces, lowers and compiles the step (and grid update); returns the seconds taken."""
        started = time.perf_counter()
        with typechecking(self.config.train.typecheck):
            lowered = self._step_fn.lower(
                self.model, self.opt_state, self.data, jnp.asarray(0, jnp.int32), self.key
            )
            self._compiled = lowered.compile()
            if self.grid is not None:
                args, kwargs = self._update_arguments(0)
                self._compiled_update = _update_occupancy.lower(*args, **kwargs).compile()
        return time.perf_counter() - started

    def advance(self) -> float:
        """One training step (and grid update when due), waited for; returns its wall time."""
        if self._compiled is None:
            raise RuntimeError("compile() first")
        step = jnp.asarray(self.step, jnp.int32)
        started = time.perf_counter()
        model, opt_state, metrics = self._compiled(self.model, self.opt_state, self.data, step, self.key)
        self.model, self.opt_state = model, opt_state
        self.step += 1
        if self._compiled_update is not None and self.step % self.config.occupancy.update_every == 0:
            args, kwargs = self._update_arguments(self.step)
            self.grid = self._compiled_update(*args, **kwargs)
        jax.block_until_ready((model, opt_state, metrics, self.grid))
        seconds = time.perf_counter() - started
        if bool(metrics.skipped):
            self.skipped += 1
            self._streak += 1
            if self._streak >= self.config.train.max_nonfinite_steps:
                raise TrainingDiverged(f"{self._streak} consecutive non-finite steps at step {self.step}")
        else:
            self._streak = 0
        return seconds

    def skipping(self) -> Skipping | None:
        """Renderer options for evaluating now (`None`: dense), not counted as training."""
        if self.grid is None:
            return None
        key = jax.random.fold_in(self._grid_key, self.step + 1)
        with typechecking(self.config.train.typecheck):
            grid = _refresh_occupancy(self.grid, self.model.field, key=key)
        return make_skipping(self.config, grid)

    def render_chunk(self, chunk: int | None = None) -> int:
        """`chunk`, or the config's: `occupancy.chunk` with skipping, else `train.render_chunk`."""
        if chunk:
            return chunk
        return self.config.occupancy.chunk if self.grid is not None else self.config.train.render_chunk


def calibrate_steps(config: Config, dataset: Dataset, budget_s: float, repeats: int) -> dict[str, Any]:
    """Estimates how many steps fit `budget_s` from `repeats` timed steps of a throwaway run.

    The step depends on `train.max_steps` (the learning-rate schedule is compiled in), so
    the real run compiles again once the estimate is known; this run is then discarded.
    """
    run = TrainingRun(config, dataset)
    compile_s = run.compile()
    times = [run.advance() for _ in range(max(1, repeats))]
    # The first steps after compiling can be slower (allocation); the median ignores that.
    per_step = statistics.median(times[1:] if len(times) > 2 else times)
    return {
        "calibrate_compile_s": compile_s,
        "calibrate_steps": len(times),
        "calibrate_step_s": per_step,
        "estimated_steps": max(1, int(budget_s / per_step)),
    }


# ----------------------------------------------------------------------------- output


def platform_tag() -> str:
    """`cpu`, `gpu` or `tpu`: the JAX backend in use (the suffix of the result files)."""
    return jax.default_backend()


def machine_info() -> dict[str, Any]:
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "device_kind": jax.devices()[0].device_kind,
    }
    with contextlib.suppress(OSError):
        info["load_average_at_start"] = list(os.getloadavg())
    return info


def model_summary(config: Config) -> dict[str, Any]:
    model = config.model
    return {
        "mlp": f"{model.depth}x{model.width}",
        "samples": [model.num_coarse_samples, model.num_fine_samples],
        "matmul_dtype": model.matmul_dtype,
        "batch_size": config.train.batch_size,
        "baseline": config.loss.is_baseline,
        "occupancy": config.occupancy.enabled,
        "max_steps": config.train.max_steps,
    }


def print_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """A markdown table; floats with 4 significant digits."""

    def cell(value: Any) -> str:
        if value is None:
            return "n/a"
        if isinstance(value, float):
            return f"{value:.4g}"
        return str(value)

    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(cell(value) for value in row) + " |")


def relative_paths(value: Any) -> Any:
    """`value` with every string that names a path inside the repository made relative to it."""
    if isinstance(value, dict):
        return {key: relative_paths(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [relative_paths(item) for item in value]
    if isinstance(value, str) and value.startswith(str(REPO) + "/"):
        return value[len(str(REPO)) + 1 :]
    return value


def write_json(path: Path, payload: Any) -> None:
    """Writes `payload` as JSON, with paths inside the repository relative to it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(relative_paths(payload), indent=2))
    print(f"written to {path}")
