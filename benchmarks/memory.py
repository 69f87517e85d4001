"""Peak memory of one training step (remat off and on) and of rendering whole frames in chunks.

    python benchmarks/memory.py   # peak memory of a step and of rendering frames

(a) One training step at the config's batch with `model.remat` false and true: the batch
draw and `mx.training.make_train_step`'s step compiled as one function over the ray table, on a
synthetic scene (`--train-views` views of `--train-image-size` pixels square). (b) One
frame rendered with `mx.inference.render_rays`, for several square frame sizes at one chunk
(`--frame-chunk`, default the config's `train.render_chunk`) and for several chunks at one
frame size (`--chunk-frame`); the rays come from a synthetic camera, the model is freshly
initialised (its values do not change the memory).

Three kinds of figure, each labelled in the table and the JSON:

- compiled (XLA): `memory_analysis()` of the compiled step or render chunk (the dense
  render `model(rays).fine` that `render_rays` runs per chunk), known before anything
  runs: arguments + outputs + temporaries - aliases (the "total"; nothing is donated).
  A frame's compiled estimate is the chunk's total plus the frame's ray table twice: the
  rays as built, and the padded copy that `render_rays` makes of them.
- device peak (GPU only): `memory_stats()["peak_bytes_in_use"]` after the measured work.
  The peak cannot be reset, so every measurement runs in a fresh subprocess (`--one`),
  and the peak also covers that process's setup (model, rays, compilation).
- host RSS: the subprocess's resident memory on the host: its peak during the measured
  work (Linux: VmHWM, reset after setup and compilation) and over its whole life (wait4).
  On the CPU, device buffers live in host memory, so this is the only measured figure
  there; it is host memory with the interpreter and the JAX runtime in it.

The training step runs on a GPU and is only compiled on the CPU (`--execute-train`); a
frame is rendered when it has at most `--max-execute-rays` rays (default: every frame on a
GPU, 16384 rays on the CPU) and otherwise has its compiled estimate alone. The main
process never touches the accelerator while the measurements run (a first subprocess
reports the machine).

Takes `--config FILE` (default: the paper's settings, 4096 rays, 128 + 128 samples, 8 x 256
MLP), `section.key=value` overrides and `--out PATH` (default
`benchmarks/results/memory_<backend>.json`). The JSON records the command and the machine
(`harness.write_json`); the tables are printed as markdown.
"""

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import harness
import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, Views

SCRIPT = str(Path(__file__).resolve())
MIB = 2**20

MEMORY_MARKER = "MEMORY-RESULT "
NEAR, FAR = 2.0, 6.0  # Blender-like bounds around a scene at the origin
CAMERA_DISTANCE = 4.0
FOCAL_PER_PIXEL = 1.3888  # Blender's 555.6 px focal length at 400 px: a 39.6 degree field of view
MEMORY_FIELDS = (
    "argument_size_in_bytes",
    "output_size_in_bytes",
    "alias_size_in_bytes",
    "temp_size_in_bytes",
    "generated_code_size_in_bytes",
    "peak_memory_in_bytes",
    "host_argument_size_in_bytes",
    "host_output_size_in_bytes",
    "host_alias_size_in_bytes",
    "host_temp_size_in_bytes",
)


def proc_status_bytes(field: str) -> int | None:
    """A `kB` line of /proc/self/status (Linux) in bytes, or None elsewhere."""
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return None


def ru_maxrss_bytes(usage) -> int:
    # ru_maxrss is in kilobytes on Linux and in bytes on macOS.
    return usage.ru_maxrss if sys.platform == "darwin" else usage.ru_maxrss * 1024


def host_peak_bytes() -> int | None:
    """This process' resident-set high-water mark (reset by `reset_host_peak`, where it works)."""
    peak = proc_status_bytes("VmHWM")
    if peak is not None:
        return peak
    try:
        import resource
    except ImportError:
        return None
    return ru_maxrss_bytes(resource.getrusage(resource.RUSAGE_SELF))


def reset_host_peak() -> bool:
    """Resets the resident-set high-water mark to the current RSS (Linux 4.0+); False if not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def device_memory() -> dict | None:
    """The first device's allocator statistics; None where the backend keeps none (the CPU)."""
    stats = jax.devices()[0].memory_stats()
    if not stats:
        return None
    return {k: int(stats[k]) for k in ("bytes_in_use", "peak_bytes_in_use", "bytes_limit") if k in stats}


def compiled_memory(compiled) -> dict | None:
    """XLA's memory analysis of a compiled function (jax's or equinox's `Compiled`), or None."""
    inner = getattr(compiled, "compiled", compiled)  # equinox's Compiled wraps jax's
    try:
        stats = inner.memory_analysis()
    except (NotImplementedError, RuntimeError):
        return None
    if isinstance(stats, list | tuple):  # some versions answer one entry per device
        stats = stats[0] if stats else None
    if stats is None:
        return None
    fields = {name: int(getattr(stats, name)) for name in MEMORY_FIELDS if hasattr(stats, name)}
    total = sum(fields.get(f"{part}_size_in_bytes", 0) for part in ("argument", "output", "temp"))
    # Everything the executable holds while it runs: its arguments and outputs (no donation here)
    # and its one temporary allocation, whose size XLA's buffer assignment has already packed.
    # (XLA's own `peak_memory_in_bytes` is kept as reported; on the CPU it leaves temporaries out.)
    fields["xla_total_bytes"] = total - fields.get("alias_size_in_bytes", 0)
    return fields


def tree_bytes(tree) -> int:
    return int(sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))))


def measured(work: Callable[[], Any]) -> dict[str, Any]:
    """Runs `work()` and reports the device and host memory around it."""
    before = device_memory()
    rss_start = proc_status_bytes("VmRSS")
    reset = reset_host_peak()
    started = time.perf_counter()
    work()
    return {
        "seconds": time.perf_counter() - started,
        "device_before": before,
        "device_after": device_memory(),
        "host_rss_start_bytes": rss_start,
        "host_rss_peak_bytes": host_peak_bytes() if reset else None,
    }


def synthetic_poses(count: int) -> np.ndarray:
    """`count` camera-to-world matrices (3 x 4) on a circle 30 degrees above the origin, facing it."""
    poses = []
    elevation = math.radians(30.0)
    for index in range(count):
        azimuth = 2 * math.pi * index / count
        centre = CAMERA_DISTANCE * np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        back = centre / np.linalg.norm(centre)  # the camera looks along its -z axis
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        poses.append(np.stack([right, up, back, centre], axis=1))
    return np.stack(poses).astype(np.float32)


def synthetic_dataset(views: int, size: int) -> Dataset:
    """Random images from synthetic cameras: the memory does not depend on the pixels' values."""
    rng = np.random.default_rng(0)

    def split(count: int) -> Views:
        images = rng.uniform(0.0, 1.0, (count, size, size, 3)).astype(np.float32)
        return Views(images=images, camtoworlds=synthetic_poses(count), focal=FOCAL_PER_PIXEL * size)

    return Dataset(name="synthetic", train=split(views), test=split(1), near=NEAR, far=FAR)


def frame_rays(size: int) -> mx.nn.RayBundle:
    return mx.nn.camera_rays(synthetic_poses(1), FOCAL_PER_PIXEL * size, size, size, NEAR, FAR)


def measure_machine(config: mx.Config) -> dict[str, Any]:
    cpu_model = None
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    try:
        host_memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        host_memory = None
    stats = device_memory() or {}
    return {
        "machine": {
            **harness.machine_info(),
            "cpu_model": cpu_model,
            "host_memory_bytes": host_memory,
            "device_bytes_limit": stats.get("bytes_limit"),
            "xla_env": {k: v for k, v in os.environ.items() if k.startswith(("XLA_", "JAX_"))},
        },
        "config": {
            **harness.model_summary(config),
            "view_width": config.mlp.view_width,
            "remat": config.model.remat,
            "render_chunk": config.train.render_chunk,
        },
    }


def measure_train(config: mx.Config, views: int, image_size: int, execute: bool) -> dict[str, Any]:
    """The batch draw and the training step compiled as one function over the ray table (so
    that the table counts, as it is held while training), on a synthetic scene."""
    dataset = synthetic_dataset(views, image_size)
    state = mx.training.init_train_state(config, dataset)
    data = mx.training.training_rays(dataset)
    step_fn, batch_size = mx.training.make_train_step(config), config.train.batch_size

    @eqx.filter_jit
    def draw_and_step(data, state):
        return step_fn(state, mx.training.draw_batch(data, state, batch_size))

    started = time.perf_counter()
    compiled = draw_and_step.lower(data, state).compile()
    row = {
        "compile_s": time.perf_counter() - started,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(state.model),
        "opt_state_bytes": tree_bytes(state.opt_state),
        "data_bytes": tree_bytes(data),
        "executed": execute,
    }
    if execute:
        row["measured"] = measured(lambda: jax.block_until_ready(compiled(data, state)))
    return row


def pad_to(rays: mx.nn.RayBundle, count: int) -> mx.nn.RayBundle:
    """The first `count` rays, the last one repeated where there are fewer (as `render_rays` pads)."""
    piece = rays[:count]
    missing = count - piece.origins.shape[0]
    if missing > 0:
        piece = jax.tree_util.tree_map(
            lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], missing, axis=0)]), piece
        )
    return piece


def measure_render(config: mx.Config, size: int, chunk: int, execute: bool) -> dict[str, Any]:
    """One chunk's compiled figures (the dense render `model(rays).fine` of `chunk` rays, the
    program `mx.inference.render_rays` runs per chunk) and, when executed, a whole frame through
    `mx.inference.render_rays`."""
    model = mx.build_model(config, key=jax.random.key(0))
    # Without rendering, only one chunk's rays are needed for the compiled figures.
    rays = frame_rays(size if execute else math.isqrt(chunk - 1) + 1)
    piece = pad_to(rays.reshape(-1), chunk)
    started = time.perf_counter()
    compiled = eqx.filter_jit(lambda model, rays: model(rays).fine).lower(model, piece).compile()
    row = {
        "compile_s": time.perf_counter() - started,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(model),
        "executed": execute,
    }
    del compiled
    if execute:
        # One chunk through `render_rays` first, so that the measured frame compiles nothing.
        mx.inference.render_rays(model, piece, chunk)
        del piece
        row["ray_table_bytes"] = tree_bytes(rays)
        row["measured"] = measured(lambda: mx.inference.render_rays(model, rays, chunk))
    return row


def run_memory_one(spec: dict, args: argparse.Namespace) -> dict[str, Any]:
    kind = spec["kind"]
    if kind == "train":
        remat = str(spec["remat"]).lower()
        config = mx.load_config(args.config, [*args.overrides, f"model.remat={remat}"])
        return measure_train(config, spec["views"], spec["image_size"], spec["execute"])
    config = mx.load_config(args.config, args.overrides)
    if kind == "machine":
        return measure_machine(config)
    if kind == "render":
        return measure_render(config, spec["size"], spec["chunk"], spec["execute"])
    raise ValueError(f"unknown measurement {kind!r}")


def spawn_memory(spec: dict, args: argparse.Namespace) -> dict[str, Any]:
    """Runs one measurement in a fresh Python process; adds its lifetime peak RSS (wait4)."""
    command = [sys.executable, SCRIPT, "--one", json.dumps(spec)]
    if args.config:
        command += ["--config", args.config]
    command += args.overrides
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)  # stderr passes through
    output = process.stdout.read()
    process.stdout.close()
    process_peak = None
    if hasattr(os, "wait4"):  # this child's own rusage, not the running maximum over all children
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        process_peak = ru_maxrss_bytes(usage)
    else:
        process.wait()
    result = harness.marked_result(output, MEMORY_MARKER)
    wall_s = time.perf_counter() - started
    if process.returncode != 0 or result is None:
        return {**spec, "error": f"subprocess exited with {process.returncode}", "wall_s": wall_s}
    return {**spec, **result, "host_rss_process_peak_bytes": process_peak, "wall_s": wall_s}


def mib(value: int | None) -> str:
    return "n/a" if value is None else f"{value / MIB:,.0f}"


def nested(row: dict, *path: str) -> Any:
    for key in path:
        if not isinstance(row, dict) or row.get(key) is None:
            return None
        row = row[key]
    return row


def train_table(rows: list[dict]) -> None:
    header = [
        "remat",
        "run",
        "XLA arguments MiB",
        "XLA outputs MiB",
        "XLA temporaries MiB",
        "XLA total MiB (compiled)",
        "device peak MiB (measured)",
        "host RSS peak MiB, step",
        "host RSS peak MiB, process",
        "compile s",
        "step s",
    ]
    cells = []
    for row in rows:
        if "error" in row:
            cells.append([str(row["remat"]).lower(), row["error"]] + ["n/a"] * (len(header) - 2))
            continue
        seconds = nested(row, "measured", "seconds")
        cells.append(
            [
                str(row["remat"]).lower(),
                "executed" if row["executed"] else "compiled only",
                mib(nested(row, "compiled", "argument_size_in_bytes")),
                mib(nested(row, "compiled", "output_size_in_bytes")),
                mib(nested(row, "compiled", "temp_size_in_bytes")),
                mib(nested(row, "compiled", "xla_total_bytes")),
                mib(nested(row, "measured", "device_after", "peak_bytes_in_use")),
                mib(nested(row, "measured", "host_rss_peak_bytes")),
                mib(row["host_rss_process_peak_bytes"]),
                f"{row['compile_s']:.1f}",
                "n/a" if seconds is None else f"{seconds:.1f}",
            ]
        )
    harness.print_table(header, cells)


def render_table(rows: list[dict]) -> None:
    header = [
        "sweep",
        "frame",
        "rays",
        "chunk",
        "calls",
        "XLA chunk total MiB (compiled)",
        "ray table MiB",
        "frame estimate MiB (compiled)",
        "device peak MiB (measured)",
        "host RSS MiB before",
        "host RSS peak MiB, render",
        "host RSS peak MiB, process",
        "render s",
    ]
    cells = []
    for row in rows:
        measured_row = {} if "error" in row else row.get("measured") or {}
        seconds = measured_row.get("seconds")
        cells.append(
            [
                row["sweep"],
                f"{row['size']}x{row['size']}",
                f"{row['rays']:,}",
                str(row["chunk"]),
                str(row["calls"]),
                mib(nested(row, "compiled", "xla_total_bytes")),
                f"{row['ray_table_bytes'] / MIB:,.1f}",
                mib(row.get("estimate_bytes")),
                mib(nested(measured_row, "device_after", "peak_bytes_in_use")),
                mib(measured_row.get("host_rss_start_bytes")),
                mib(measured_row.get("host_rss_peak_bytes")),
                mib(row.get("host_rss_process_peak_bytes")) if row["executed"] else "n/a",
                row["error"] if "error" in row else ("n/a" if seconds is None else f"{seconds:.1f}"),
            ]
        )
    harness.print_table(header, cells)


def run(args: argparse.Namespace) -> None:
    """Runs every measurement in its own process and writes the result (see the module docstring)."""
    if args.one is not None:
        result = run_memory_one(json.loads(args.one), args)
        print(MEMORY_MARKER + json.dumps(result), flush=True)
        return

    probe = spawn_memory({"kind": "machine"}, args)
    if "error" in probe:
        raise SystemExit(f"the machine probe failed: {probe['error']}")
    machine, config = probe["machine"], probe["config"]
    on_gpu = machine["backend"] != "cpu"
    execute_train = args.execute_train == "yes" or (args.execute_train == "auto" and on_gpu)
    max_rays = args.max_execute_rays
    if max_rays is None:
        max_rays = sys.maxsize if on_gpu else 16384
    frame_chunk = args.frame_chunk or config["render_chunk"]

    train_rows = []
    if not args.skip_train:
        for remat in (False, True):
            spec = {
                "kind": "train",
                "remat": remat,
                "views": args.train_views,
                "image_size": args.train_image_size,
                "execute": execute_train,
            }
            row = spawn_memory(spec, args)
            train_rows.append(row)
            print(json.dumps(row), flush=True)

    # The (sweep, size, chunk) cells; a frame in both sweeps is measured once.
    cells = [("size", size, frame_chunk) for size in args.sizes]
    cells += [("chunk", args.chunk_frame, chunk) for chunk in args.chunks]
    results: dict[tuple[int, int], dict] = {}
    chunk_figures: dict[int, dict | None] = {}
    for _, size, chunk in cells:
        execute = size * size <= max_rays
        if (size, chunk) in results or (not execute and chunk in chunk_figures):
            continue
        row = spawn_memory({"kind": "render", "size": size, "chunk": chunk, "execute": execute}, args)
        print(json.dumps(row), flush=True)
        chunk_figures.setdefault(chunk, row.get("compiled"))
        if execute:
            results[(size, chunk)] = row
    render_rows = []
    for sweep, size, chunk in cells:
        rays = size * size
        row = dict(results.get((size, chunk), {"executed": False}))
        compiled = row.get("compiled") or chunk_figures.get(chunk)
        ray_table = rays * 12 * 4  # origins, directions, viewdirs (3 each), radii, near, far: float32
        row.update(
            sweep=sweep,
            size=size,
            chunk=chunk,
            rays=rays,
            calls=-(-rays // chunk),
            compiled=compiled,
            ray_table_bytes=row.get("ray_table_bytes", ray_table),
        )
        if compiled is not None:
            row["estimate_bytes"] = compiled["xla_total_bytes"] + 2 * row["ray_table_bytes"]
        render_rows.append(row)

    where = f"{machine['device_kind']} ({machine['backend']})"
    print(f"\n{where}, {machine['cpu_count']} CPUs, jax {machine['jax']}")
    print(
        f"MLP {config['mlp']}, {'+'.join(map(str, config['samples']))} samples; MiB = 2^20 bytes; "
        "'n/a': not measured (compiled only) or not available on this platform"
    )
    if train_rows:
        print(
            f"\n(a) one training step, {config['batch_size']} rays, ray table of {args.train_views} "
            f"synthetic {args.train_image_size}x{args.train_image_size} views\n"
        )
        train_table(train_rows)
    print("\n(b) one frame with render_rays; frame estimate = XLA chunk total + 2 x ray table")
    if max_rays < sys.maxsize:
        print(f"frames over {max_rays:,} rays compiled only")
    print()
    render_table(render_rows)
    print()

    payload = {
        "args": {k: v for k, v in vars(args).items() if k != "one"},
        "machine": machine,
        "config": config,
        "max_execute_rays": None if max_rays == sys.maxsize else max_rays,
        "figures": {
            "compiled": "XLA memory_analysis() of the compiled function; an estimate, nothing run",
            "compiled.xla_total_bytes": "arguments + outputs + temporaries - aliases, from memory_analysis()",
            "estimate_bytes": "a frame: the render chunk's XLA total + 2 x the frame's ray table",
            "measured.device_after.peak_bytes_in_use": "device allocator peak over the subprocess' life",
            "measured.host_rss_peak_bytes": "host RSS high-water mark during the measured work (Linux)",
            "host_rss_process_peak_bytes": "host RSS high-water mark over the subprocess' life (wait4)",
        },
        "train": train_rows,
        "render": render_rows,
    }
    harness.write_json(
        harness.default_out(args.out, "memory", "gpu" if on_gpu else machine["backend"]), payload
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    harness.add_common(parser, None, "memory")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 400, 800, 1600], help="square frames")
    parser.add_argument("--frame-chunk", type=int, default=None, help="chunk of the size sweep")
    parser.add_argument("--chunks", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--chunk-frame", type=int, default=400, help="frame size of the chunk sweep")
    parser.add_argument("--max-execute-rays", type=int, default=None, help="larger frames: compiled only")
    parser.add_argument("--execute-train", choices=["auto", "yes", "no"], default="auto")
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--train-views", type=int, default=4, help="synthetic training views")
    parser.add_argument("--train-image-size", type=int, default=400, help="their size in pixels, square")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # one measurement, in a subprocess
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    run(parse_args(argv))


if __name__ == "__main__":
    main()
