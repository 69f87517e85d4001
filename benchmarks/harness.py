"""The benchmarks' shared harness (not a benchmark itself). It uses the public API only.

- Scene and variant specs from the command line, and the configs they resolve to.
- Cheap evaluation views: a fixed subset of the test views, optionally area-downsampled.
- `TrainingRun`: one run of the library's `TrainState` and jitted step, compiled ahead of time
  with `.lower(...).compile()` so that compilation is timed apart from the steps, each step
  timed to completion.
- The schedule rule for short runs, output paths, machine description, table printing and
  result writing (every result file records the command that made it).
- For the timing scripts (`step_time.py`, `profile_step.py`, `typecheck_overhead.py`,
  `memory.py`, `quickstart.py`): their common arguments and default result path, the random
  points a training step's field evaluates, and the marked line through which a measurement
  run in a fresh process reports its result.

Spec syntax (`error_vs_time.py`, `sample_count.py`):

    --scene lego                               preset (lego: configs/blender4.toml, fern: configs/llff3.toml)
    --scene NAME=CONFIG[:key=value,...]        a scene of your own: CONFIG's [data] section and settings
    --variant NAME=scene[:key=value,...]       the scene's own config (the paper settings of its dataset)
    --variant NAME=FILE.toml[:key=value,...]   a config file used for every scene it fits (see below)

Override lists are comma-separated `section.key=value` items, parsed like the overrides of
`load_config`; the macros `@baseline` (`method = "mipnerf"` and no distortion loss: the
mip-NeRF baseline, as the `mipnerf_*.toml` configs)
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
import shlex
import statistics
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx import Config, load_config
from mixnerf_eqx.data import Dataset, Views, load_dataset

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"

# A benchmark times what a user of the commands gets: the script starts again with the
# allocator they preload (mimalloc on Linux; `MIXNERF_ALLOCATOR=system` times without it).
# Only a script of this folder run as a program does; a test importing the harness does not.
if Path(sys.argv[0]).resolve().parent == Path(__file__).resolve().parent:
    mx.runtime.preload_allocator()

SCENE_PRESETS = {
    "lego": str(REPO / "configs" / "blender4.toml"),
    "fern": str(REPO / "configs" / "llff3.toml"),
}

MACROS = {
    # As the mipnerf_*.toml baselines: without the mixture and without the distortion loss
    # (the LLFF family's recommended configs add it for MixNeRF only).
    "@baseline": ("method=mipnerf", "loss.distortion_weight=0"),
    "@fast": (
        "model.num_coarse_samples=32",
        "model.num_fine_samples=32",
        'mlp.matmul_dtype="bfloat16"',
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
    fifth (annealing) of `max_steps`, the shares that `experiments/short_real_runs.py` uses; then they
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

    Pixel centres sit at `col + 0.5` (see `mixnerf_eqx.nn.camera_rays`), so a box average over
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
    """Runtime shape checks on or off for a block (they act while JAX traces)."""
    previous = mx.runtime.typecheck_enabled()
    mx.set_typecheck(enabled)
    try:
        yield
    finally:
        mx.set_typecheck(previous)


class TrainingRun:
    """A `TrainState` and the library's compiled step, timed step by step.

    The state comes from `mx.training.init_train_state` (the config's seed, as in `fit`). `compile()`
    lowers and compiles the batch draw and the step ahead of time without running them;
    `advance()` runs one step to completion and returns its wall time.

    With `occupancy.enabled`, the grid is kept up to date as `fit` keeps it (`mx.training.update_grid`
    every `occupancy.update_every` steps, compiled ahead too) and those updates count as
    training time; `skipping()` gives the rendering options for evaluation where the config's
    renders skip (`occupancy.enabled` or `occupancy.render_skipping`), with the grid (the kept
    one, or a new one) refreshed in every cell as `fit` does before its final evaluation, its
    threshold the config's (none chosen).
    """

    def __init__(self, config: Config, dataset: Dataset):
        self.config = config
        self.dataset = dataset
        self.state = mx.training.init_train_state(config, dataset)
        self.data = mx.training.training_rays(dataset, config.loss)
        self._step_fn = mx.training.make_train_step(config)
        self._draw = eqx.filter_jit(mx.training.draw_batch)
        self._compiled = None
        self.skipped = 0
        self._streak = 0

    @property
    def model(self) -> mx.MixNeRF:
        return self.state.model

    @property
    def step(self) -> int:
        return int(self.state.step)

    def compile(self) -> float:
        """Traces, lowers and compiles the batch draw, the step (and grid update); returns the
        seconds taken."""
        started = time.perf_counter()
        batch_size = self.config.train.batch_size
        draw = self._draw.lower(self.data, self.state, batch_size).compile()
        # A batch to lower the step with; drawing is pure, so the run is not changed.
        step = self._step_fn.lower(self.state, draw(self.data, self.state, batch_size)).compile()
        update = None
        if self.state.grid is not None:
            update = mx.training.update_grid.lower(self.state, self.config.occupancy).compile()
        self._compiled = (draw, step, update)
        return time.perf_counter() - started

    def advance(self) -> float:
        """One training step (and grid update when due), waited for; returns its wall time."""
        if self._compiled is None:
            raise RuntimeError("compile() first")
        draw, step, update = self._compiled
        started = time.perf_counter()
        state, metrics = step(self.state, draw(self.data, self.state, self.config.train.batch_size))
        if update is not None and (self.step + 1) % self.config.occupancy.update_every == 0:
            state = update(state, self.config.occupancy)
        jax.block_until_ready((state, metrics))
        seconds = time.perf_counter() - started
        self.state = state
        if bool(metrics.skipped):
            self.skipped += 1
            self._streak += 1
            if self._streak >= self.config.train.max_nonfinite_steps:
                raise mx.training.TrainingDiverged(f"{self._streak} consecutive non-finite steps at step {self.step}")
        else:
            self._streak = 0
        return seconds

    def skipping(self) -> mx.inference.Skipping | None:
        """Rendering options for evaluating now (`None`: dense), not counted as training."""
        if not self.config.occupancy.renders_skip:
            return None
        key = mx.training.occupancy_key(self.state.key, self.step + 1)
        occupancy = dataclasses.replace(self.config.occupancy, choose_threshold=False)
        grid, _ = mx.runs.grid_for_rendering(
            occupancy, self.dataset, self.model, key=key, grid=self.state.grid
        )
        return mx.runs.make_skipping(self.config.occupancy, grid)

    def render_chunk(self, chunk: int | None = None) -> int:
        """`chunk`, or the config's: `occupancy.chunk` with skipping, else `train.render_chunk`."""
        if chunk:
            return chunk
        return self.config.occupancy.chunk if self.state.grid is not None else self.config.train.render_chunk


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


# ----------------------------------------------------------------------------- the field alone


def field_points(config: Config, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Random Gaussians, unit view directions and noise keys, as many as a training step
    evaluates (batch x (coarse + fine))."""
    count = config.train.batch_size * (config.model.num_coarse_samples + config.model.num_fine_samples)
    keys = jax.random.split(key, 4)
    means = jax.random.normal(keys[0], (count, 3))
    covs = 1e-4 * jnp.abs(jax.random.normal(keys[1], (count, 3)))
    viewdirs = jax.random.normal(keys[2], (count, 3))
    viewdirs = viewdirs / jnp.linalg.norm(viewdirs, axis=-1, keepdims=True)
    return means, covs, viewdirs, jax.random.split(keys[3], count)


def summed_field(model: mx.MixNeRF, means, covs, viewdirs, keys=None) -> jax.Array:
    """The field (as the model calls it: flat points, remat if configured), outputs summed."""
    outputs = model.query_points(means, covs, viewdirs, keys)
    return sum(jnp.sum(leaf) for leaf in jax.tree_util.tree_leaves(outputs))


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
        "allocator": Path(mx.runtime.allocator_in_use()).name,
    }
    with contextlib.suppress(OSError):
        info["load_average_at_start"] = list(os.getloadavg())
    return info


def grid_threshold(grid: mx.inference.OccupancyGrid) -> float:
    """A grid's density threshold (a float32 array leaf) as the shortest decimal that reads back
    as the same float32: 0.01, not 0.009999999776482582."""
    return float(np.format_float_positional(np.float32(grid.threshold), unique=True))


def model_summary(config: Config) -> dict[str, Any]:
    model, mlp = config.model, config.mlp
    return {
        "mlp": f"{mlp.depth}x{mlp.width}",
        "samples": [model.num_coarse_samples, model.num_fine_samples],
        "matmul_dtype": mlp.matmul_dtype,
        "batch_size": config.train.batch_size,
        "method": config.method,
        "occupancy": config.occupancy.enabled,
        "render_skipping": config.occupancy.render_skipping,
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


def command_line() -> str:
    """The command that is running, as a user would type it from the repository root."""
    script = Path(sys.argv[0]).resolve()
    shown = str(script.relative_to(REPO)) if script.is_relative_to(REPO) else script.name
    return shlex.join(["python", shown, *sys.argv[1:]])


def write_json(path: Path, payload: Any) -> None:
    """Writes `payload` as JSON, with paths inside the repository relative to it, and the
    command that made it (`"command"`) and the machine (`"machine"`) unless it has them."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(payload, dict):
        payload = {"command": command_line(), "machine": machine_info(), **payload}
    path.write_text(json.dumps(relative_paths(payload), indent=2))
    print(f"written to {path}")


def append_jsonl(path: Path, record: dict[str, Any]) -> None:
    """Appends one record (with the command that made it) to a JSON-lines file, flushed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        handle.write(json.dumps(relative_paths({"command": command_line(), **record})) + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def write_markdown(path: Path, text: str) -> None:
    """Writes a markdown result with a first line that names the command that made it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"<!-- made by: {command_line()} -->\n\n{text}")
    print(f"written to {path}")


def pyplot(what: str) -> Any:
    """`matplotlib.pyplot` on the file-only Agg backend for a benchmark's plots, or `None`
    where matplotlib is not installed, after printing that there are no `what` (e.g. "plots").
    (The package's run curves have their own twin of this: benchmarks use the public API only.)"""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"no {what}: matplotlib is not installed (pip install 'mixnerf_eqx[plots]')")
        return None
    return plt


def save_figure(figure: Any, path: Path, dpi: int = 120) -> None:
    """Saves a matplotlib figure as PNG with the command that made it in its metadata
    (the `Comment` text chunk) and closes it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=dpi, metadata={"Comment": f"made by: {command_line()}"})
    plt.close(figure)
    print(f"plot written to {path}")


# ----------------------------------------------------------------------------- timing scripts


def default_out(out: str | None, name: str, backend: str | None = None) -> Path:
    """`out`, or `benchmarks/results/<name>_<backend>.json` (backend: the one in use)."""
    return Path(out) if out else RESULTS / f"{name}_{backend or platform_tag()}.json"


def add_common(parser: argparse.ArgumentParser, default_config: str | None, out_name: str) -> None:
    """`--config FILE`, `--out PATH` and the `section.key=value` overrides of a timing script."""
    parser.add_argument(
        "--config", default=default_config, help=f"TOML config (default: {default_config or 'the paper'})"
    )
    parser.add_argument("--out", default=None, help=f"JSON path (default: results/{out_name}_<backend>.json)")
    parser.add_argument("overrides", nargs="*", help="config overrides, section.key=value")


def marked_result(output: str, marker: str) -> dict[str, Any] | None:
    """The JSON object on the last line of `output` that starts with `marker` (the line a
    measurement run in a fresh process prints its result on), or None if there is none."""
    lines = [line for line in output.splitlines() if line.startswith(marker)]
    return json.loads(lines[-1][len(marker) :]) if lines else None
