"""What the runtime shape checks cost: the tracing first step and the compiled step, checks on and off.

    python benchmarks/typecheck_overhead.py      # configs/builtin.toml, 20 timed steps, 2 rounds
    python benchmarks/typecheck_overhead.py --steps 5 --config configs/blender4.toml model.remat=true

`import mixnerf_eqx` puts the package's modules through `jaxtyping.install_import_hook(...,
"beartype.beartype")` unless `MIXNERF_EQX_TYPECHECK=0` is set before the import, so each
setting runs in a fresh Python process: `MIXNERF_EQX_TYPECHECK=1` (checks on) and `=0` (off),
with `JAXTYPING_DISABLE` removed from its environment. Each process

- times the import of `mixnerf_eqx` (the hook rewrites the modules it imports) and the setup
  (scene, ray table, model and optimiser state, as `mixnerf_eqx._train.fit` builds them);
- calls a public annotated function wrongly, `mixnerf_eqx.blend_weights` with one density and
  five interval edges (it needs two), and records what happens: with the checks on it must
  raise jaxtyping's `TypeCheckError`; with them off it returns, silently, a wrongly shaped
  result. It repeats the call with `jaxtyping.config.jaxtyping_disable` set, the switch that
  `fit` flips from `train.typecheck`;
- times the first call of the jitted training step of `make_train_step` (trace, lower,
  compile and one run: the checks act in the trace alone), split into its phases by JAX's own
  monitoring events, then `--steps` further calls one by one, each to completion
  (`block_until_ready`), and reports their median: the compiled step;
- afterwards traces and lowers fresh step functions five times (`.lower()`; "re-trace", the
  median, with JAX's caches of small helper functions already warm) and hashes the StableHLO
  text: equal hashes on and off mean that XLA is given the same program. The loss after the
  last timed step is recorded too: the same seeds give the same numbers when the programs are
  the same;
- lowers the step once more with the training colours as uint8: `loss_fn`'s `target_rgb` is
  annotated `Float`, so with the checks on the trace must stop with `TypeCheckError` (the
  checks act inside the training step), while without them it lowers silently.

The processes run one after another, `--rounds` of each setting (on first in even rounds, off
first in odd ones), and the ratios on / off summarise them, each the median over the on
processes divided by the median over the off ones. The printed table is markdown; the JSON,
with every step's time and the machine, goes to
`benchmarks/results/typecheck_overhead_<backend>.json` (`--out` to change it). The script
exits with status 1 when the checks were not active as expected.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

MARKER = "TYPECHECK-OVERHEAD-RESULT "
SETTINGS = {"on": "1", "off": "0"}
DEFAULT_CONFIG = "configs/builtin.toml"
RESULTS = Path(__file__).resolve().parent / "results"
RETRACES = 5


# --- one measurement, in a fresh process (`--one on|off`) ---


def _probe(call) -> dict[str, Any]:
    """What `call()` did: the exception it raised, or what it returned (dtype and shape of an array)."""
    import jaxtyping

    try:
        out = call()
    except Exception as error:  # whatever happens is recorded
        kind = type(error)
        return {
            "raised": f"{kind.__module__}.{kind.__qualname__}",
            "type_check_error": isinstance(error, jaxtyping.TypeCheckError),
            "message": str(error).splitlines()[:2],
        }
    returned = f"{out.dtype}{list(out.shape)}" if hasattr(out, "shape") else type(out).__name__
    return {"raised": None, "type_check_error": False, "returned": returned}


def _phases(events: list[tuple[str, float]]) -> dict[str, float | None]:
    """Seconds of tracing, lowering and compiling among JAX's monitoring events.

    Tracing takes the longest trace event (a jit traced inside another is part of it); the
    others are summed.
    """
    names = {
        "trace_s": "/jax/core/compile/jaxpr_trace_duration",
        "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
        "compile_s": "/jax/core/compile/backend_compile_duration",
    }
    phases: dict[str, float | None] = {}
    for key, name in names.items():
        seconds = [d for event, d in events if event == name]
        phases[key] = None if not seconds else (max(seconds) if key == "trace_s" else sum(seconds))
    return phases


def measure(setting: str, config_path: str, overrides: list[str], steps: int) -> dict[str, Any]:
    import hashlib

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import jaxlib
    import jaxtyping

    loaded_before = set(sys.modules)
    start = time.perf_counter()
    import mixnerf_eqx

    import_s = time.perf_counter() - start
    # The hook is active only while `mixnerf_eqx/__init__.py` imports; modules loaded later
    # (by the imports below, say) are not checked even with it on.
    hooked = sorted(m for m in set(sys.modules) - loaded_before if m.startswith("mixnerf_eqx"))
    from mixnerf_eqx import build_model, load_config
    from mixnerf_eqx._config import init_key
    from mixnerf_eqx._train import make_optimizer, make_train_step, training_rays
    from mixnerf_eqx.data import load_dataset

    later = sorted(
        m for m in set(sys.modules) - loaded_before if m.startswith("mixnerf_eqx") and m not in hooked
    )

    # One density but five edges: the annotations tie the edges to `num_samples+1` = 2.
    # Unchecked, the arithmetic broadcasts and returns four weights where one is due.
    def wrong_call():
        return mixnerf_eqx.blend_weights(jnp.ones((1,)), jnp.linspace(2.0, 6.0, 5), jnp.asarray(1.0))

    disable_before = bool(jaxtyping.config.jaxtyping_disable)
    probe = _probe(wrong_call)
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        probe_disabled = _probe(wrong_call)
    finally:
        jaxtyping.config.update("jaxtyping_disable", disable_before)

    config = load_config(config_path, overrides)
    start = time.perf_counter()
    dataset = load_dataset(config.data)
    data = training_rays(dataset)
    model_key, train_key = jax.random.split(init_key(config))
    model = build_model(
        config, key=model_key, frustum=dataset.frustum, white_background=dataset.white_background
    )
    optimizer = make_optimizer(config)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_array))
    jax.block_until_ready((data, model, opt_state))
    setup_s = time.perf_counter() - start

    # JAX reports how long each phase of a jit's first call took: tracing to a jaxpr (where
    # the checks run), lowering to StableHLO, and XLA's compilation.
    events: list[tuple[str, float]] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: events.append((event, seconds))
    )

    initial_model, initial_opt_state = model, opt_state
    step_fn = make_train_step(config, optimizer)
    step = jnp.asarray(0, jnp.int32)
    events.clear()
    start = time.perf_counter()
    model, opt_state, metrics = jax.block_until_ready(step_fn(model, opt_state, data, step, train_key))
    first_step_s = time.perf_counter() - start
    first_phases = _phases(events)

    step_times = []
    for index in range(1, steps + 1):
        step = jnp.asarray(index, jnp.int32)
        start = time.perf_counter()
        model, opt_state, metrics = jax.block_until_ready(step_fn(model, opt_state, data, step, train_key))
        step_times.append(time.perf_counter() - start)
    final_loss = float(metrics.terms.total)

    # Fresh step functions (new closures, so nothing of the first is reused) are traced and
    # lowered again, `RETRACES` times (one alone swings with the garbage collector), and the
    # StableHLO of the last kept: the program XLA is given.
    retrace_times = []
    for _ in range(RETRACES):
        fresh_fn = make_train_step(config, optimizer)
        events.clear()
        lowered = fresh_fn.lower(initial_model, initial_opt_state, data, jnp.asarray(0, jnp.int32), train_key)
        retrace_times.append(_phases(events)["trace_s"])
    retrace_s = None if None in retrace_times else statistics.median(retrace_times)
    stablehlo = lowered.as_text()

    # The checks inside the step: colours as 8-bit integers (an easy mistake with images) reach
    # `loss_fn`, whose `target_rgb` is annotated `Float[...]`. Checked, tracing stops there;
    # unchecked, the integers are promoted and the step traces and lowers as if all were well.
    uint8_data = eqx.tree_at(lambda d: d.rgb, data, (255 * data.rgb).astype(jnp.uint8))
    probe_step = _probe(
        lambda: make_train_step(config, optimizer).lower(
            initial_model, initial_opt_state, uint8_data, jnp.asarray(0, jnp.int32), train_key
        )
    )

    m = config.model
    return {
        "typecheck_on_import": mixnerf_eqx.TYPECHECK_ON_IMPORT,
        "jaxtyping_disable": disable_before,
        "hooked_modules": hooked if mixnerf_eqx.TYPECHECK_ON_IMPORT else [],
        "modules_imported_after_the_hook": later,
        "wrong_shape_call": probe,
        "wrong_shape_call_with_jaxtyping_disable": probe_disabled,
        "uint8_colours_step_lowering": probe_step,
        "import_s": import_s,
        "setup_s": setup_s,
        "first_step_s": first_step_s,
        "first_step_trace_s": first_phases["trace_s"],
        "first_step_lower_s": first_phases["lower_s"],
        "first_step_compile_s": first_phases["compile_s"],
        "retrace_s": retrace_s,
        "retrace_s_each": retrace_times,
        "step_s_median": statistics.median(step_times),
        "step_s_min": min(step_times),
        "step_s_mean": statistics.fmean(step_times),
        "step_s": step_times,
        "final_loss": final_loss,
        "stablehlo_sha256": hashlib.sha256(stablehlo.encode()).hexdigest(),
        "stablehlo_chars": len(stablehlo),
        "model": {
            "mlp": f"{m.depth}x{m.width}",
            "samples": [m.num_coarse_samples, m.num_fine_samples],
            "remat": m.remat,
            "matmul_dtype": m.matmul_dtype,
            "batch_size": config.train.batch_size,
        },
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "jaxlib": jaxlib.__version__,
            "jaxtyping": jaxtyping.__version__,
            "equinox": eqx.__version__,
            "backend": jax.default_backend(),
            "devices": [str(d) for d in jax.devices()],
            "device_kind": jax.devices()[0].device_kind,
        },
    }


# --- the main process: one subprocess per setting and round (it never imports JAX) ---


def spawn(setting: str, round_index: int, args) -> dict[str, Any]:
    command = [sys.executable, str(Path(__file__).resolve()), "--one", setting]
    command += ["--config", args.config, "--steps", str(args.steps), *args.overrides]
    env = {k: v for k, v in os.environ.items() if k != "JAXTYPING_DISABLE"}
    env["MIXNERF_EQX_TYPECHECK"] = SETTINGS[setting]
    start = time.perf_counter()
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, text=True)  # stderr passes through
    wall_s = time.perf_counter() - start
    lines = [line for line in done.stdout.splitlines() if line.startswith(MARKER)]
    row = {"checks": setting, "round": round_index, "wall_s": wall_s}
    if done.returncode != 0 or not lines:
        return {**row, "error": f"subprocess exited with {done.returncode}"}
    return {**row, **json.loads(lines[-1][len(MARKER) :])}


def _ratio(rows: list[dict], key: str) -> float | None:
    on = [row[key] for row in rows if row["checks"] == "on" and row.get(key) is not None]
    off = [row[key] for row in rows if row["checks"] == "off" and row.get(key) is not None]
    if not on or not off:
        return None
    return statistics.median(on) / statistics.median(off)


def _outcome(probe: dict | None) -> str:
    if probe is None:
        return "n/a"
    if probe["raised"] is None:
        return f"returned {probe['returned']}"
    return f"raised {probe['raised'].rsplit('.', 1)[-1]}"


def checks_as_expected(row: dict) -> bool:
    """On: imported with the hook; the wrong call raises TypeCheckError (but not once
    `jaxtyping_disable` is set) and so does tracing the step with uint8 colours.
    Off: no hook, and neither raises TypeCheckError."""
    if "error" in row:
        return False
    on = row["checks"] == "on"
    return (
        row["typecheck_on_import"] == on
        and row["wrong_shape_call"]["type_check_error"] == on
        and not row["wrong_shape_call_with_jaxtyping_disable"]["type_check_error"]
        and row["uint8_colours_step_lowering"]["type_check_error"] == on
    )


COLUMNS = (  # (header, key, scale, format)
    ("import s", "import_s", 1.0, ".2f"),
    ("setup s", "setup_s", 1.0, ".2f"),
    ("first step s", "first_step_s", 1.0, ".2f"),
    ("of which trace s", "first_step_trace_s", 1.0, ".2f"),
    ("lower s", "first_step_lower_s", 1.0, ".2f"),
    ("XLA compile s", "first_step_compile_s", 1.0, ".2f"),
    ("re-trace s (median)", "retrace_s", 1.0, ".2f"),
    ("compiled step ms (median)", "step_s_median", 1e3, ".1f"),
    ("min ms", "step_s_min", 1e3, ".1f"),
)


def print_table(rows: list[dict]) -> None:
    header = ["checks", "round", *(c[0] for c in COLUMNS)]
    header += ["wrong-shape call", "with jaxtyping_disable", "step, uint8 colours"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        cells = [row["checks"], str(row["round"])]
        if "error" in row:
            cells += [row["error"]] + ["n/a"] * (len(header) - 3)
        else:
            for _, key, scale, spec in COLUMNS:
                cells.append("n/a" if row.get(key) is None else format(scale * row[key], spec))
            cells += [
                _outcome(row["wrong_shape_call"]),
                _outcome(row["wrong_shape_call_with_jaxtyping_disable"]),
                _outcome(row["uint8_colours_step_lowering"]),
            ]
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default=DEFAULT_CONFIG, help=f"TOML config (default {DEFAULT_CONFIG})")
    parser.add_argument("--steps", type=int, default=20, help="timed steps after the first (default 20)")
    parser.add_argument("--rounds", type=int, default=2, help="processes per setting (default 2)")
    parser.add_argument("--out", default=None, help="JSON path (default: see above)")
    parser.add_argument("--one", choices=sorted(SETTINGS), help=argparse.SUPPRESS)
    parser.add_argument("overrides", nargs="*", help="section.key=value")
    args = parser.parse_args()
    if args.steps < 1 or args.rounds < 1:
        parser.error("--steps and --rounds must be at least 1")

    if args.one is not None:
        result = measure(args.one, args.config, args.overrides, args.steps)
        print(MARKER + json.dumps(result), flush=True)
        return

    load_at_start = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    rows = []
    for round_index in range(args.rounds):
        order = ("on", "off") if round_index % 2 == 0 else ("off", "on")
        for setting in order:
            row = spawn(setting, round_index, args)
            rows.append(row)
            brief = {k: row.get(k) for k in ("checks", "round", "error", "first_step_s", "step_s_median")}
            print(json.dumps({k: v for k, v in brief.items() if v is not None}), flush=True)

    good = [row for row in rows if "error" not in row]
    machine = good[0]["machine"] if good else {"cpu_count": os.cpu_count()}
    hashes = {row["stablehlo_sha256"] for row in good}
    losses = {row["final_loss"] for row in good}
    summary = {
        "first_step_ratio_on_off": _ratio(rows, "first_step_s"),
        "first_step_trace_ratio_on_off": _ratio(rows, "first_step_trace_s"),
        "first_step_compile_ratio_on_off": _ratio(rows, "first_step_compile_s"),
        "retrace_ratio_on_off": _ratio(rows, "retrace_s"),
        "compiled_step_ratio_on_off": _ratio(rows, "step_s_median"),
        "compiled_step_min_ratio_on_off": _ratio(rows, "step_s_min"),
        "import_ratio_on_off": _ratio(rows, "import_s"),
        "same_stablehlo_on_off": len(hashes) == 1 if good else None,
        "same_final_loss_on_off": len(losses) == 1 if good else None,
        "checks_as_expected": all(checks_as_expected(row) for row in rows),
    }

    print()
    model = good[0]["model"] if good else {}
    overrides = " ".join(args.overrides) or "none"
    print(f"{args.config} (overrides: {overrides}): batch {model.get('batch_size')} rays,")
    print(
        f"{'+'.join(map(str, model.get('samples', [])))} samples, MLP {model.get('mlp')}, "
        f"remat {model.get('remat')}; {machine.get('backend')}, jax {machine.get('jax')}, "
        f"{machine.get('cpu_count')} CPUs; {args.steps} timed steps per process"
    )
    print()
    print_table(rows)
    print()

    def show(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.2f}"

    lines = [
        ("import, on / off", show(summary["import_ratio_on_off"])),
        ("first step, on / off", show(summary["first_step_ratio_on_off"])),
        ("  its trace, on / off", show(summary["first_step_trace_ratio_on_off"])),
        ("  its XLA compile, on / off", show(summary["first_step_compile_ratio_on_off"])),
        ("re-trace, on / off", show(summary["retrace_ratio_on_off"])),
        ("compiled step, on / off", f"{show(summary['compiled_step_ratio_on_off'])}  (expected about 1.00)"),
        ("  its fastest, on / off", show(summary["compiled_step_min_ratio_on_off"])),
        ("same StableHLO on and off", summary["same_stablehlo_on_off"]),
        (f"same loss after {args.steps + 1} steps", summary["same_final_loss_on_off"]),
        ("checks active as expected", summary["checks_as_expected"]),
    ]
    for label, value in lines:
        print(f"{label + ':':<30s}{value}")
    hooked = next((row["hooked_modules"] for row in good if row["checks"] == "on"), None)
    later = next((row["modules_imported_after_the_hook"] for row in good if row["checks"] == "on"), [])
    if hooked is not None:
        names = ", ".join(name.removeprefix("mixnerf_eqx.") for name in later)
        print(f"modules under the hook: {len(hooked)}; imported after it, so unchecked: {len(later)}")
        print(f"  ({names})")

    backend = machine.get("backend", "unknown")
    out = Path(args.out) if args.out else RESULTS / f"typecheck_overhead_{backend}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "command": " ".join(["python", "benchmarks/typecheck_overhead.py", *sys.argv[1:]]),
        "config": args.config,
        "overrides": args.overrides,
        "steps": args.steps,
        "rounds": args.rounds,
        "machine": machine,
        "load_average_at_start": load_at_start,
        "load_average_at_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "summary": summary,
        "rows": rows,
    }
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"\nwrote {out}")
    if not summary["checks_as_expected"]:
        print("the checks were not active as expected", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
