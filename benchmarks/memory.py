"""Peak memory of one training step (remat off and on) and of rendering whole frames in chunks.

    python benchmarks/memory.py      # paper batch; frames 100 to 1600 px square; chunks 1024 to 16384
    # the CPU run of results/memory_cpu.json (about 6 minutes on two cores):
    python benchmarks/memory.py --sizes 32 64 128 400 800 1600 --frame-chunk 1024 --chunk-frame 64 \
        --max-execute-rays 16384

(a) One training step at the config's batch (default: the paper's, 4096 rays, 128 + 128
samples, 8 x 256 MLP, as in `step_time.py`) with `model.remat` false and true: the step that
`mixnerf_eqx._train.make_train_step` builds, lowered and compiled ahead of time through its
`eqx.filter_jit`; its ray table is synthetic (`--train-views` views of `--train-image-size`
pixels square). (b) One frame rendered with `mixnerf_eqx._evaluate.render_rays`, for several
square frame sizes at one chunk (`--frame-chunk`, default the config's `train.render_chunk`)
and for several chunks at one frame size (`--chunk-frame`); the rays are `camera_rays` of a
synthetic pose, the model is freshly initialised (its values do not change the memory).

Three kinds of figure, each labelled in the table and the JSON:

- compiled (XLA): `memory_analysis()` of the compiled step or render chunk, known before
  anything runs: arguments + outputs + temporaries - aliases (the "total"; nothing is donated,
  so the outputs do not reuse the inputs). A frame's compiled estimate is the chunk's total
  plus the frame's ray table twice: the rays as built, and the flattened copy that
  `render_rays` makes of them.
- device peak (GPU only): `memory_stats()["peak_bytes_in_use"]` after the measured work. The
  peak cannot be reset, so every measurement runs in a fresh subprocess (`--one`), and the
  peak also covers that process's setup (model, rays, compilation).
- host RSS: the subprocess's resident memory on the host: its peak during the measured work
  (Linux: VmHWM, reset after setup and compilation) and over its whole life (wait4). On the
  CPU, device buffers live in host memory, so this is the only measured figure there; it is
  host memory with the Python interpreter and the JAX runtime in it, not device memory.

The training step runs on a GPU and is only compiled on the CPU (`--execute-train`); a frame is
rendered when it has at most `--max-execute-rays` rays (default: every frame on a GPU, 16384
rays on the CPU, where the paper model renders about 200 rays/s on two cores) and otherwise has
its compiled estimate alone. The main process never touches the accelerator itself (a first
subprocess reports the machine), so that none of its memory is held while others measure.
Prints the tables (markdown) and writes `benchmarks/results/memory_<cpu|gpu>.json`.
"""

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

MARKER = "MEMORY-RESULT "
MIB = 2**20
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


# --- host and device memory probes (run inside the measuring subprocess) ---


def _proc_status_bytes(field: str) -> int | None:
    """A `kB` line of /proc/self/status (Linux) in bytes, or None elsewhere."""
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return None


def _ru_maxrss_bytes(usage) -> int:
    # ru_maxrss is in kilobytes on Linux and in bytes on macOS.
    return usage.ru_maxrss if sys.platform == "darwin" else usage.ru_maxrss * 1024


def host_peak_bytes() -> int | None:
    """This process' resident-set high-water mark (reset by `reset_host_peak`, where it works)."""
    peak = _proc_status_bytes("VmHWM")
    if peak is not None:
        return peak
    try:
        import resource
    except ImportError:
        return None
    return _ru_maxrss_bytes(resource.getrusage(resource.RUSAGE_SELF))


def reset_host_peak() -> bool:
    """Resets the resident-set high-water mark to the current RSS (Linux 4.0+); False if not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def device_memory() -> dict | None:
    """The first device's allocator statistics; None where the backend keeps none (the CPU)."""
    import jax

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
    import equinox as eqx
    import jax

    return int(sum(leaf.nbytes for leaf in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))))


def measured(work) -> dict:
    """Runs `work()` and reports the device and host memory around it."""
    before = device_memory()
    rss_start = _proc_status_bytes("VmRSS")
    reset = reset_host_peak()
    start = time.perf_counter()
    work()
    seconds = time.perf_counter() - start
    return {
        "seconds": seconds,
        "device_before": before,
        "device_after": device_memory(),
        "host_rss_start_bytes": rss_start,
        "host_rss_peak_bytes": host_peak_bytes() if reset else None,
    }


# --- synthetic cameras ---


def synthetic_poses(count: int):
    """`count` camera-to-world matrices (3 x 4) on a circle 30 degrees above the origin, facing it."""
    import numpy as np

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
    return np.stack(poses)


def frame_rays(size: int, views: int = 1):
    from mixnerf_eqx import camera_rays

    return camera_rays(synthetic_poses(views), FOCAL_PER_PIXEL * size, size, size, NEAR, FAR)


# --- the measurements, one per subprocess ---


def measure_machine(config) -> dict:
    import equinox as eqx
    import jax
    import jaxlib

    cpu_model = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        host_memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        host_memory = None
    device = jax.devices()[0]
    stats = device_memory() or {}
    m = config.model
    return {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_model": cpu_model,
            "cpu_count": os.cpu_count(),
            "host_memory_bytes": host_memory,
            "python": platform.python_version(),
            "jax": jax.__version__,
            "jaxlib": jaxlib.__version__,
            "equinox": eqx.__version__,
            "backend": jax.default_backend(),
            "devices": [str(d) for d in jax.devices()],
            "device_kind": device.device_kind,
            "device_bytes_limit": stats.get("bytes_limit"),
            "xla_env": {k: v for k, v in os.environ.items() if k.startswith(("XLA_", "JAX_"))},
        },
        "config": {
            "batch_size": config.train.batch_size,
            "num_coarse_samples": m.num_coarse_samples,
            "num_fine_samples": m.num_fine_samples,
            "depth": m.depth,
            "width": m.width,
            "view_width": m.view_width,
            "matmul_dtype": m.matmul_dtype,
            "remat": m.remat,
            "render_chunk": config.train.render_chunk,
            "baseline": config.loss.is_baseline,
        },
    }


def measure_train(config, views: int, image_size: int, execute: bool) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from mixnerf_eqx import build_model
    from mixnerf_eqx._train import TrainingRays, make_optimizer, make_train_step

    model = build_model(config, key=jax.random.key(0))
    optimizer = make_optimizer(config)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_array))
    pixels = image_size * image_size
    data = TrainingRays(
        rays=frame_rays(image_size, views).reshape(views, pixels),
        rgb=jax.random.uniform(jax.random.key(2), (views, pixels, 3)),
    )
    step, key = jnp.asarray(0, jnp.int32), jax.random.key(1)
    step_fn = make_train_step(config, optimizer)
    start = time.perf_counter()
    compiled = step_fn.lower(model, opt_state, data, step, key).compile()
    row = {
        "compile_s": time.perf_counter() - start,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(model),
        "opt_state_bytes": tree_bytes(opt_state),
        "data_bytes": tree_bytes(data),
        "executed": execute,
    }
    if execute:
        row["measured"] = measured(lambda: jax.block_until_ready(compiled(model, opt_state, data, step, key)))
    return row


def _pad_to(rays, count: int):
    """The first `count` rays, the last one repeated where there are fewer (as `render_rays` pads)."""
    import jax
    import jax.numpy as jnp

    piece = rays[:count]
    missing = count - piece.origins.shape[0]
    if missing > 0:
        piece = jax.tree_util.tree_map(
            lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], missing, axis=0)]), piece
        )
    return piece


def measure_render(config, size: int, chunk: int, execute: bool) -> dict:
    import jax

    from mixnerf_eqx import build_model
    from mixnerf_eqx._evaluate import _render_chunk, render_rays

    model = build_model(config, key=jax.random.key(0))
    # Without rendering, only one chunk's rays are needed for the compiled figures.
    rays = frame_rays(size if execute else math.isqrt(chunk - 1) + 1)
    piece = _pad_to(rays.reshape(-1), chunk)
    start = time.perf_counter()
    # Compiling ahead of time fills the cache that `render_rays`' calls use, so the measured
    # render below compiles nothing.
    compiled = _render_chunk.lower(model, piece).compile()
    row = {
        "compile_s": time.perf_counter() - start,
        "compiled": compiled_memory(compiled),
        "model_bytes": tree_bytes(model),
        "executed": execute,
    }
    del piece, compiled
    if execute:
        row["ray_table_bytes"] = tree_bytes(rays)
        row["measured"] = measured(lambda: render_rays(model, rays, chunk))
    return row


def run_one(spec: dict, config_path: str | None, overrides: list[str]) -> dict:
    from mixnerf_eqx import load_config

    kind = spec["kind"]
    if kind == "train":
        config = load_config(config_path, [*overrides, f"model.remat={str(spec['remat']).lower()}"])
        return measure_train(config, spec["views"], spec["image_size"], spec["execute"])
    config = load_config(config_path, overrides)
    if kind == "machine":
        return measure_machine(config)
    if kind == "render":
        return measure_render(config, spec["size"], spec["chunk"], spec["execute"])
    raise ValueError(f"unknown measurement {kind!r}")


# --- the main process: one subprocess per measurement ---


def spawn(spec: dict, args) -> dict:
    """Runs one measurement in a fresh Python process; adds its lifetime peak RSS (wait4)."""
    command = [sys.executable, str(Path(__file__).resolve()), "--one", json.dumps(spec)]
    if args.config:
        command += ["--config", args.config]
    command += args.overrides
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)  # stderr passes through
    output = process.stdout.read()
    process.stdout.close()
    process_peak = None
    if hasattr(os, "wait4"):  # this child's own rusage, not the running maximum over all children
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        process_peak = _ru_maxrss_bytes(usage)
    else:
        process.wait()
    lines = [line for line in output.splitlines() if line.startswith(MARKER)]
    if process.returncode != 0 or not lines:
        return {
            **spec,
            "error": f"subprocess exited with {process.returncode}",
            "wall_s": time.perf_counter() - start,
        }
    result = json.loads(lines[-1][len(MARKER) :])
    return {
        **spec,
        **result,
        "host_rss_process_peak_bytes": process_peak,
        "wall_s": time.perf_counter() - start,
    }


def _mib(value) -> str:
    return "n/a" if value is None else f"{value / MIB:,.0f}"


def _get(row: dict, *path):
    for key in path:
        if not isinstance(row, dict) or row.get(key) is None:
            return None
        row = row[key]
    return row


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cells) + " |" for cells in rows]
    return "\n".join(lines)


def train_table(rows: list[dict]) -> str:
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
        seconds = _get(row, "measured", "seconds")
        cells.append(
            [
                str(row["remat"]).lower(),
                "executed" if row["executed"] else "compiled only",
                _mib(_get(row, "compiled", "argument_size_in_bytes")),
                _mib(_get(row, "compiled", "output_size_in_bytes")),
                _mib(_get(row, "compiled", "temp_size_in_bytes")),
                _mib(_get(row, "compiled", "xla_total_bytes")),
                _mib(_get(row, "measured", "device_after", "peak_bytes_in_use")),
                _mib(_get(row, "measured", "host_rss_peak_bytes")),
                _mib(row["host_rss_process_peak_bytes"]),
                f"{row['compile_s']:.1f}",
                "n/a" if seconds is None else f"{seconds:.1f}",
            ]
        )
    return _table(header, cells)


def render_table(rows: list[dict]) -> str:
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
        measured_row = row.get("measured") or {}
        seconds = measured_row.get("seconds")
        if "error" in row:
            seconds = None
            measured_row = {"host_rss_start_bytes": None}
        cells.append(
            [
                row["sweep"],
                f"{row['size']}x{row['size']}",
                f"{row['rays']:,}",
                str(row["chunk"]),
                str(row["calls"]),
                _mib(_get(row, "compiled", "xla_total_bytes")),
                f"{row['ray_table_bytes'] / MIB:,.1f}",
                _mib(row.get("estimate_bytes")),
                _mib(_get(measured_row, "device_after", "peak_bytes_in_use")),
                _mib(measured_row.get("host_rss_start_bytes")),
                _mib(measured_row.get("host_rss_peak_bytes")),
                _mib(row.get("host_rss_process_peak_bytes")) if row["executed"] else "n/a",
                row["error"] if "error" in row else ("n/a" if seconds is None else f"{seconds:.1f}"),
            ]
        )
    return _table(header, cells)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=None, help="TOML config (default: the paper's settings)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 400, 800, 1600], help="square frames")
    parser.add_argument("--frame-chunk", type=int, default=None, help="chunk of the size sweep")
    parser.add_argument("--chunks", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--chunk-frame", type=int, default=400, help="frame size of the chunk sweep")
    parser.add_argument("--max-execute-rays", type=int, default=None, help="larger frames: compiled only")
    parser.add_argument("--execute-train", choices=["auto", "yes", "no"], default="auto")
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--train-views", type=int, default=4, help="synthetic training views")
    parser.add_argument("--train-image-size", type=int, default=400, help="their size in pixels, square")
    parser.add_argument("--out", default=None, help="default: benchmarks/results/memory_<platform>.json")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: one measurement
    parser.add_argument("overrides", nargs="*", help="config overrides, section.key=value")
    args = parser.parse_args()
    if args.one is not None:
        result = run_one(json.loads(args.one), args.config, args.overrides)
        print(MARKER + json.dumps(result), flush=True)
        return

    probe = spawn({"kind": "machine"}, args)
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
            row = spawn(spec, args)
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
        row = spawn({"kind": "render", "size": size, "chunk": chunk, "execute": execute}, args)
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

    m = config
    where = f"{machine['device_kind']} ({machine['backend']})"
    print(f"\n{where}, {machine['cpu_count']} CPUs, jax {machine['jax']}")
    print(
        f"MLP {m['depth']}x{m['width']}, {m['num_coarse_samples']}+{m['num_fine_samples']} samples; "
        f"MiB = 2^20 bytes; 'n/a': not measured (compiled only) or not available on this platform"
    )
    if train_rows:
        print(
            f"\n(a) one training step, {m['batch_size']} rays, ray table of {args.train_views} synthetic "
            f"{args.train_image_size}x{args.train_image_size} views\n"
        )
        print(train_table(train_rows))
    print(
        "\n(b) one frame with render_rays; frame estimate = XLA chunk total + 2 x ray table; "
        f"frames over {max_rays:,} rays compiled only\n"
        if max_rays < sys.maxsize
        else "\n(b) one frame with render_rays; frame estimate = XLA chunk total + 2 x ray table\n"
    )
    print(render_table(render_rows))

    out = Path(args.out or f"benchmarks/results/memory_{'gpu' if on_gpu else machine['backend']}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "command": " ".join(["python", *sys.argv]),
        "args": vars(args),
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
    out.write_text(json.dumps(report, indent=2))
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
