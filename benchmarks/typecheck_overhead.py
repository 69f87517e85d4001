"""What the runtime shape checks cost: the tracing first step and the compiled step, on and off.

    python benchmarks/typecheck_overhead.py   # what the runtime shape checks cost (configs/builtin.toml)

The checks are jaxtyping's with beartype, installed for the package's modules as it is
imported and switched with `mx.set_typecheck`, which every checked call reads when it
runs. Each setting runs in a fresh Python process (`--one on|off`), so that neither
inherits the other's caches; each process

- sets the switch, calls a public annotated function wrongly (`mx.nn.blend_weights` with one
  density and five interval edges; it needs two) and records what happens: with the
  checks on it must raise jaxtyping's `TypeCheckError`, with them off it returns a
  wrongly shaped result; then calls it again with the switch flipped, which must do the
  opposite;
- times the setup (scene, ray table, `mx.training.init_train_state`);
- times the first batch draw and step of `mx.training.make_train_step` (trace, lower, compile and
  one run: the checks act in the trace alone), split into its phases by JAX's own
  monitoring events, then `--steps` further steps one by one, each waited for, and
  reports their median: the compiled step;
- traces and lowers fresh step functions five times ("re-trace", the median) and hashes
  the StableHLO text: equal hashes on and off mean that XLA is given the same program.
  The loss after the last timed step is recorded too;
- lowers the step once more with the batch's colours as uint8: `loss_fn`'s `target_rgb`
  is annotated `Float`, so with the checks on the trace must stop with `TypeCheckError`,
  while without them it lowers silently.

The processes run one after another, `--rounds` of each setting (on first in even rounds,
off first in odd ones); the ratios on / off are medians over the on processes divided by
medians over the off ones. A fresh interpreter per round also times `import mixnerf_eqx`
(the same with the checks on or off: the switch acts at call time). Exits with status 1
when the checks were not active as expected.

Takes `--config FILE` (default: configs/builtin.toml), `section.key=value` overrides and
`--out PATH` (default `benchmarks/results/typecheck_overhead_<backend>.json`). The JSON records
the command and the machine (`harness.write_json`); the table is printed as markdown.
"""

import argparse
import hashlib
import json
import os
import statistics
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

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset

SCRIPT = str(Path(__file__).resolve())

TYPECHECK_MARKER = "TYPECHECK-OVERHEAD-RESULT "
RETRACES = 5
# A fresh interpreter with JAX, Equinox and jaxtyping already loaded times `import mixnerf_eqx`
# (which installs jaxtyping's import hook and loads its names on first use) and the first use
# of `fit`, and lists the package's modules loaded before the hook (the commands' start-up and
# the table of moved names, unchecked) and those loaded through it.
IMPORT_PROBE = """
import json, sys, time
import equinox, jax, jaxtyping
before = set(sys.modules)
started = time.perf_counter()
import mixnerf_eqx
import_s = time.perf_counter() - started
unhooked = sorted(m for m in set(sys.modules) - before if m.startswith("mixnerf_eqx"))
started = time.perf_counter()
mixnerf_eqx.fit
import mixnerf_eqx.eval, mixnerf_eqx.train
first_use_s = time.perf_counter() - started
hooked = sorted(m for m in set(sys.modules) - before if m.startswith("mixnerf_eqx") and m not in unhooked)
print(json.dumps({"import_s": import_s, "first_use_s": first_use_s, "hooked_modules": hooked,
                  "modules_before_the_hook": unhooked}))
"""


def probe_call(call: Callable[[], Any]) -> dict[str, Any]:
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


def compile_phases(events: list[tuple[str, float]]) -> dict[str, float | None]:
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


def measure_typecheck(setting: str, config_path: str, overrides: list[str], steps: int) -> dict[str, Any]:
    """One setting's measurements, in a fresh process (`--one on|off`)."""
    on = setting == "on"
    mx.set_typecheck(on)

    # One density but five edges: the annotations tie the edges to `num_samples+1` = 2.
    # Unchecked, the arithmetic broadcasts and returns four weights where one is due.
    def wrong_call():
        return mx.nn.blend_weights(jnp.ones((1,)), jnp.linspace(2.0, 6.0, 5), jnp.asarray(1.0))

    probe = probe_call(wrong_call)
    # The switch acts on the next call: flipped, the same call must do the opposite.
    with harness.typechecking(not on):
        probe_flipped = probe_call(wrong_call)

    config = mx.load_config(config_path, overrides)
    batch_size = config.train.batch_size
    started = time.perf_counter()
    dataset = load_dataset(config.data)
    data = mx.training.training_rays(dataset)
    state = mx.training.init_train_state(config, dataset)
    jax.block_until_ready((data, state))
    setup_s = time.perf_counter() - started

    # JAX reports how long each phase of a jit's first call took: tracing to a jaxpr (where
    # the checks run), lowering to StableHLO, and XLA's compilation.
    events: list[tuple[str, float]] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: events.append((event, seconds))
    )
    initial = state
    step_fn, draw = mx.training.make_train_step(config), eqx.filter_jit(mx.training.draw_batch)
    # The first step: the batch draw and the step, each traced, lowered, compiled and run.
    events.clear()
    started = time.perf_counter()
    state, metrics = jax.block_until_ready(step_fn(state, draw(data, state, batch_size)))
    first_step_s = time.perf_counter() - started
    first_phases = compile_phases(events)
    step_times = []
    for _ in range(steps):
        started = time.perf_counter()
        state, metrics = jax.block_until_ready(step_fn(state, draw(data, state, batch_size)))
        step_times.append(time.perf_counter() - started)
    final_loss = float(metrics.terms.total)

    # Fresh step functions (new closures, so nothing of the first is reused) are traced and
    # lowered again, `RETRACES` times (one alone swings with the garbage collector), and the
    # StableHLO of the last kept: the program XLA is given.
    batch = draw(data, initial, batch_size)
    retrace_times = []
    for _ in range(RETRACES):
        events.clear()
        lowered = mx.training.make_train_step(config).lower(initial, batch)
        retrace_times.append(compile_phases(events)["trace_s"])
    retrace_s = None if None in retrace_times else statistics.median(retrace_times)
    stablehlo = lowered.as_text()

    # The checks inside the step: colours as 8-bit integers (an easy mistake with images) reach
    # `loss_fn`, whose `target_rgb` is annotated `Float[...]`. Checked, tracing stops there;
    # unchecked, the integers are promoted and the step traces and lowers as if all were well.
    uint8_batch = eqx.tree_at(lambda b: b.rgb, batch, (255 * batch.rgb).astype(jnp.uint8))
    probe_step = probe_call(lambda: mx.training.make_train_step(config).lower(initial, uint8_batch))

    return {
        "typecheck_enabled": mx.runtime.typecheck_enabled(),
        "wrong_shape_call": probe,
        "wrong_shape_call_switch_flipped": probe_flipped,
        "uint8_colours_step_lowering": probe_step,
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
        "model": harness.model_summary(config),
        "machine": harness.machine_info(),
    }


def spawn_typecheck(setting: str, round_index: int, args: argparse.Namespace) -> dict[str, Any]:
    command = [sys.executable, SCRIPT, "--one", setting, "--steps", str(args.steps)]
    command += ["--config", args.config, *args.overrides]
    # Each process starts from the default (checks on) and sets its own setting.
    env = {k: v for k, v in os.environ.items() if k != "JAXTYPING_DISABLE"}
    started = time.perf_counter()
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, text=True)  # stderr passes through
    row = {"checks": setting, "round": round_index, "wall_s": time.perf_counter() - started}
    result = harness.marked_result(done.stdout, TYPECHECK_MARKER)
    if done.returncode != 0 or result is None:
        return {**row, "error": f"subprocess exited with {done.returncode}"}
    return {**row, **result}


def import_probe() -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if k != "JAXTYPING_DISABLE"}
    done = subprocess.run([sys.executable, "-c", IMPORT_PROBE], env=env, stdout=subprocess.PIPE, text=True)
    if done.returncode != 0:
        return {"error": f"subprocess exited with {done.returncode}"}
    return json.loads(done.stdout.splitlines()[-1])


def on_off_ratio(rows: list[dict], key: str) -> float | None:
    on = [row[key] for row in rows if row["checks"] == "on" and row.get(key) is not None]
    off = [row[key] for row in rows if row["checks"] == "off" and row.get(key) is not None]
    if not on or not off:
        return None
    return statistics.median(on) / statistics.median(off)


def outcome(probe: dict | None) -> str:
    if probe is None:
        return "n/a"
    if probe["raised"] is None:
        return f"returned {probe['returned']}"
    return f"raised {probe['raised'].rsplit('.', 1)[-1]}"


def checks_as_expected(row: dict) -> bool:
    """On: the wrong call raises TypeCheckError, and does not once the switch is flipped off;
    tracing the step with uint8 colours raises too. Off: the reverse."""
    if "error" in row:
        return False
    on = row["checks"] == "on"
    return (
        row["typecheck_enabled"] == on
        and row["wrong_shape_call"]["type_check_error"] == on
        and row["wrong_shape_call_switch_flipped"]["type_check_error"] != on
        and row["uint8_colours_step_lowering"]["type_check_error"] == on
    )


TYPECHECK_COLUMNS = (  # (header, key, scale)
    ("setup s", "setup_s", 1.0),
    ("first step s", "first_step_s", 1.0),
    ("of which trace s", "first_step_trace_s", 1.0),
    ("lower s", "first_step_lower_s", 1.0),
    ("XLA compile s", "first_step_compile_s", 1.0),
    ("re-trace s (median)", "retrace_s", 1.0),
    ("compiled step ms (median)", "step_s_median", 1e3),
    ("min ms", "step_s_min", 1e3),
)


def run(args: argparse.Namespace) -> None:
    """Runs the processes of both settings and writes the result (see the module docstring)."""
    if args.steps < 1 or args.rounds < 1:
        raise SystemExit("--steps and --rounds must be at least 1")
    if args.one is not None:
        result = measure_typecheck(args.one, args.config, args.overrides, args.steps)
        print(TYPECHECK_MARKER + json.dumps(result), flush=True)
        return

    rows, imports = [], []
    for round_index in range(args.rounds):
        imports.append(import_probe())
        order = ("on", "off") if round_index % 2 == 0 else ("off", "on")
        for setting in order:
            row = spawn_typecheck(setting, round_index, args)
            rows.append(row)
            brief = {k: row.get(k) for k in ("checks", "round", "error", "first_step_s", "step_s_median")}
            print(json.dumps({k: v for k, v in brief.items() if v is not None}), flush=True)

    good = [row for row in rows if "error" not in row]
    import_times = [probe["import_s"] for probe in imports if "import_s" in probe]
    summary = {
        "import_s_median": statistics.median(import_times) if import_times else None,
        "first_step_ratio_on_off": on_off_ratio(rows, "first_step_s"),
        "first_step_trace_ratio_on_off": on_off_ratio(rows, "first_step_trace_s"),
        "first_step_compile_ratio_on_off": on_off_ratio(rows, "first_step_compile_s"),
        "retrace_ratio_on_off": on_off_ratio(rows, "retrace_s"),
        "compiled_step_ratio_on_off": on_off_ratio(rows, "step_s_median"),
        "compiled_step_min_ratio_on_off": on_off_ratio(rows, "step_s_min"),
        "same_stablehlo_on_off": len({row["stablehlo_sha256"] for row in good}) == 1 if good else None,
        "same_final_loss_on_off": len({row["final_loss"] for row in good}) == 1 if good else None,
        "checks_as_expected": all(checks_as_expected(row) for row in rows),
    }

    model = good[0]["model"] if good else {}
    overrides = " ".join(args.overrides) or "none"
    print(f"\n{args.config} (overrides: {overrides}): batch {model.get('batch_size')} rays,")
    print(
        f"{'+'.join(map(str, model.get('samples', [])))} samples, MLP {model.get('mlp')}; "
        f"{args.steps} timed steps per process\n"
    )
    table = []
    for row in rows:
        if "error" in row:
            table.append((row["checks"], row["round"], row["error"]))
            continue
        cells = [None if row.get(key) is None else scale * row[key] for _, key, scale in TYPECHECK_COLUMNS]
        outcomes = (
            outcome(row["wrong_shape_call"]),
            outcome(row["wrong_shape_call_switch_flipped"]),
            outcome(row["uint8_colours_step_lowering"]),
        )
        table.append((row["checks"], row["round"], *cells, *outcomes))
    header = ["checks", "round", *(c[0] for c in TYPECHECK_COLUMNS)]
    header += ["wrong-shape call", "switch flipped", "step, uint8 colours"]
    harness.print_table(header, table)
    print()

    def show(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.2f}"

    lines = [
        ("import mixnerf_eqx, s", show(summary["import_s_median"])),
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
    hooked = next((probe for probe in imports if "hooked_modules" in probe), None)
    if hooked is not None:
        before = ", ".join(name.removeprefix("mixnerf_eqx.") for name in hooked["modules_before_the_hook"])
        print(
            f"modules under the hook: {len(hooked['hooked_modules'])}; loaded before it, so unchecked: "
            f"{len(hooked['modules_before_the_hook'])} ({before or 'none'})"
        )

    backend = good[0]["machine"]["backend"] if good else None
    payload = {
        "config": args.config,
        "overrides": args.overrides,
        "steps": args.steps,
        "rounds": args.rounds,
        "machine": good[0]["machine"] if good else None,
        "load_average_at_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "summary": summary,
        "imports": imports,
        "rows": rows,
    }
    if payload["machine"] is None:
        del payload["machine"]
    harness.write_json(harness.default_out(args.out, "typecheck_overhead", backend), payload)
    if not summary["checks_as_expected"]:
        print("the checks were not active as expected", file=sys.stderr)
        sys.exit(1)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    harness.add_common(parser, "configs/builtin.toml", "typecheck_overhead")
    parser.add_argument("--steps", type=int, default=20, help="timed steps after the first (default 20)")
    parser.add_argument("--rounds", type=int, default=2, help="processes per setting (default 2)")
    parser.add_argument("--one", choices=["on", "off"], help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    run(parse_args(argv))


if __name__ == "__main__":
    main()
