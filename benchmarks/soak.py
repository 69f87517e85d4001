"""Soak test of resuming: train a tiny run, stop it at random moments (Ctrl-C or `kill -9`)
and start it again, many times, then check that it ended exactly where an uninterrupted run
ends.

    python benchmarks/soak.py                         # 50 stops, about 20 minutes on 2 CPU cores
    python benchmarks/soak.py --rounds 6 --steps 600  # a quick look

Every start is the README's command, `python -m mixnerf_eqx.train`, in a fresh process on the
same run folder (it resumes from the newest checkpoint). Each stop comes at a uniformly random
time after the start, so stops land in the imports, the scene's generation, compilation,
training steps, checkpoint writes, log writes and the final evaluation alike; the signal is
SIGINT or SIGKILL with equal odds. After `--rounds` stops the run is started once more and left
to finish. Checked against an uninterrupted run of the same config:

- every parameter of the final checkpoint equal bit for bit, and the optimiser state too;
- the test metrics equal;
- `train_log.jsonl` holds one entry per logged step, the same steps as the uninterrupted log,
  with the same losses;
- every stopped process ended with status 130 (Ctrl-C) or by the kill, never with a
  traceback, and no staging folder or partial file is left.

The figures (stops by signal and by what the run was doing, steps redone after kills, time)
go to `results/soak_cpu.json`, and `docs/reliability.md` quotes them.
"""

import argparse
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import harness
import jax
import numpy as np

import mixnerf_eqx as mx

CONFIG = "configs/builtin.toml"
# The tests' tiny model (tests/helpers.py, TINY_OVERRIDES), with a checkpoint every 10 steps and
# a periodic evaluation, so that stops also land in checkpoint writes and in renders.
TINY = [
    "data.resolution=32",
    "data.num_train_views=4",
    "data.num_test_views=3",
    "mlp.width=32",
    "mlp.depth=2",
    "mlp.skip_layer=1",
    "mlp.view_width=16",
    "mlp.max_deg=8",
    "model.num_coarse_samples=16",
    "model.num_fine_samples=16",
    "optim.lr_init=5e-3",
    "optim.lr_final=5e-4",
    "optim.warmup_steps=20",
    "loss.lambda_colour_steps=20",
    "train.batch_size=256",
    "train.anneal_steps=20",
    "train.checkpoint_every=10",
]


def train_command(run_dir: Path, steps: int, eval_every: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "mixnerf_eqx.train",
        "--no-progress",
        "--config",
        CONFIG,
        *TINY,
        f"train.max_steps={steps}",
        f"train.eval_every={eval_every}",
        f"train.run_dir={json.dumps(str(run_dir))}",
    ]


def environment(cache: Path) -> dict[str, str]:
    # One compilation cache for every start, so that a restart costs seconds, not a compile.
    return {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache), "PYTHONUNBUFFERED": "1"}


def log_steps(run_dir: Path) -> list[dict]:
    path = run_dir / "train_log.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def in_python_imports(status: int, stderr: str) -> bool:
    """A Ctrl-C that came while Python was still importing the package (the first seconds): no
    code of the run has started, and Python ends with its own KeyboardInterrupt traceback and
    the default SIGINT exit."""
    lines = stderr.strip().splitlines()
    return (
        status == -signal.SIGINT
        and bool(lines)
        and lines[-1] == "KeyboardInterrupt"
        and "importlib._bootstrap" in stderr
    )


def what_it_was_doing(before: list[dict], after: list[dict], status: int, stderr: str) -> str:
    """Where a start was stopped: `"imports"` (see `in_python_imports`), `"shutdown"` (after
    the run ended, as the interpreter shuts down), `"training"` if it
    logged a step (the log is read right after the stop, before the next start drops what a
    kill left unsaved), else `"start-up"` (the scene, compilation, the first steps)."""
    if in_python_imports(status, stderr):
        return "imports"
    if status == -signal.SIGINT and "Traceback" not in stderr:
        # Killed by SIGINT's default disposition, which Python restores only as it shuts down:
        # the run had ended, its work done.
        return "shutdown"
    return "training" if len(after) > len(before) else "start-up"


def state_leaves(run_dir: Path) -> list[np.ndarray]:
    """Every array of the run's final state (parameters, optimiser state, key, step)."""
    run = mx.runs.restore_run(run_dir)
    leaves = jax.tree_util.tree_leaves(eqx.filter(run.state, eqx.is_array))
    return [
        np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
        for x in leaves
    ]


def stop_window(start_s: float, steps_per_s: float, steps: int, rounds: int) -> float:
    """The latest stop, in seconds after a start, such that `rounds` stops at uniform times in
    `[0, start_s + window]` are expected to train about 70% of `steps` in all (a stop after
    the start-up of `start_s` keeps about `steps_per_s` steps per second past it): the run
    lasts through every round, and a third or so of the stops land in training."""
    per_round = 0.7 * steps / rounds / steps_per_s  # seconds of training expected per round
    # E[max(0, u - start_s)] for u ~ U(0, start_s + w) is w^2 / (2 (start_s + w)).
    return per_round + math.sqrt(per_round**2 + 2 * per_round * start_s)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=50, help="stops before the run is let finish")
    parser.add_argument("--steps", type=int, default=5000, help="train.max_steps of the run")
    parser.add_argument("--eval-every", type=int, default=500, help="train.eval_every of the run")
    parser.add_argument(
        "--max-wait", type=float, default=None, help="latest stop, s after a start (default: measured)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the stop times and signals")
    parser.add_argument("--out", default=None, help="result file (default results/soak_<backend>.json)")
    args = parser.parse_args()
    # A process started in the background of a shell ignores SIGINT, and so would every run it
    # starts: with a handler of its own here, the runs start with the default disposition, as
    # from a terminal.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    rng = random.Random(args.seed)
    scratch = Path(tempfile.mkdtemp(prefix="soak-"))
    env = environment(scratch / "xla-cache")

    reference = scratch / "uninterrupted"
    # A first start of the same run, stopped at its first log entry, only fills the compilation
    # cache, so that the reference's start-up is what every restart sees.
    warm_up = subprocess.Popen(
        train_command(scratch / "warm-up", args.steps, args.eval_every),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    while warm_up.poll() is None and not log_steps(scratch / "warm-up"):
        time.sleep(0.05)
    warm_up.kill()
    warm_up.wait()
    started = time.perf_counter()
    process = subprocess.Popen(
        train_command(reference, args.steps, args.eval_every),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    first_entry_s = None
    while process.poll() is None:
        if first_entry_s is None and log_steps(reference):
            first_entry_s = time.perf_counter() - started
        time.sleep(0.05)
    reference_s = time.perf_counter() - started
    _, stderr = process.communicate()
    if process.returncode != 0:
        raise SystemExit(f"the uninterrupted run failed:\n{stderr[-3000:]}")
    rates = [entry["steps_per_s"] for entry in log_steps(reference) if entry.get("steps_per_s")]
    steps_per_s = sorted(rates)[len(rates) // 2]
    start_s = first_entry_s - 10 / steps_per_s  # the first entry is logged at step 10
    max_wait = (
        args.max_wait
        if args.max_wait is not None
        else start_s + stop_window(start_s, steps_per_s, args.steps, args.rounds)
    )
    print(
        f"uninterrupted run: {reference_s:.1f} s, start-up {start_s:.1f} s, {steps_per_s:.0f} steps/s; "
        f"stops at uniform times up to {max_wait:.1f} s after each start",
        flush=True,
    )

    soaked = scratch / "soaked"
    rounds = []
    soak_started = time.perf_counter()
    for index in range(args.rounds):
        before = log_steps(soaked)
        wait = rng.uniform(0.2, max_wait)
        which = rng.choice([signal.SIGINT, signal.SIGKILL])
        process = subprocess.Popen(
            train_command(soaked, args.steps, args.eval_every),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            process.wait(timeout=wait)
            finished_by_itself = True
        except subprocess.TimeoutExpired:
            finished_by_itself = False
            process.send_signal(which)
        stdout, stderr = process.communicate(timeout=600)
        after = log_steps(soaked)
        row = {
            "round": index,
            "wait_s": round(wait, 2),
            "signal": None if finished_by_itself else signal.Signals(which).name,
            "status": process.returncode,
            "phase": "finished"
            if finished_by_itself
            else what_it_was_doing(before, after, process.returncode, stderr),
            "last_logged_step_before": before[-1]["step"] if before else None,
            "last_logged_step_after": after[-1]["step"] if after else None,
            "traceback": "Traceback" in stderr and not in_python_imports(process.returncode, stderr),
        }
        rounds.append(row)
        print(json.dumps(row), flush=True)
        if row["traceback"]:
            print(stderr[-3000:], file=sys.stderr)
        if finished_by_itself:
            # The run finished before this stop: train a fresh folder from scratch for the rest.
            break
    final = subprocess.run(
        train_command(soaked, args.steps, args.eval_every), env=env, capture_output=True, text=True
    )
    soak_s = time.perf_counter() - soak_started
    if final.returncode != 0:
        raise SystemExit(f"the final start failed:\n{final.stderr[-3000:]}")

    want, got = state_leaves(reference), state_leaves(soaked)
    equal_leaves = sum(a.shape == b.shape and np.array_equal(a, b) for a, b in zip(want, got, strict=True))
    want_log, got_log = log_steps(reference), log_steps(soaked)
    want_metrics = json.loads((reference / "metrics.json").read_text())["test"]
    got_metrics = json.loads((soaked / "metrics.json").read_text())["test"]
    leftovers = sorted(
        str(path.relative_to(soaked))
        for path in soaked.rglob("*")
        if "partial" in path.name or "staging" in path.name
    )

    def losses(log):
        return [(entry["step"], entry["loss"]) for entry in log if "loss" in entry]

    def evaluations(log):
        return [(entry["step"], entry["eval"]) for entry in log if "eval" in entry]

    def once_each(steps):
        return len(steps) == len(set(steps)) and steps == sorted(steps)

    expected_status = {130, -signal.SIGKILL}
    checks = {
        "parameters and optimiser state bit-identical": equal_leaves == len(want),
        "test metrics equal": want_metrics == got_metrics,
        "one log entry per logged step and evaluation": once_each([step for step, _ in losses(got_log)])
        and once_each([step for step, _ in evaluations(got_log)]),
        "same logged steps, losses and evaluations as the uninterrupted run": losses(want_log)
        == losses(got_log)
        and evaluations(want_log) == evaluations(got_log),
        "every stop ended with 130 or by the kill (or in Python's imports or shut-down)": all(
            row["status"] in expected_status or row["phase"] in ("imports", "shutdown")
            for row in rounds
            if row["signal"] is not None
        ),
        "no traceback (but Python's own, in its imports)": not any(row["traceback"] for row in rounds),
        "no staging or partial files left": not leftovers,
    }
    stops = [row for row in rounds if row["signal"] is not None]
    summary = {
        "stops": len(stops),
        "SIGINT": sum(row["signal"] == "SIGINT" for row in stops),
        "SIGKILL": sum(row["signal"] == "SIGKILL" for row in stops),
        "by_phase": {
            phase: sum(row["phase"] == phase for row in stops)
            for phase in sorted({r["phase"] for r in stops})
        },
        "finished_before_a_stop": any(row["signal"] is None for row in rounds),
        "uninterrupted_s": round(reference_s, 1),
        "start_up_s": round(start_s, 1),
        "steps_per_s": round(steps_per_s, 1),
        "latest_stop_s": round(max_wait, 1),
        "soaked_s": round(soak_s, 1),
        "leaves": len(want),
        "equal_leaves": equal_leaves,
        "log_entries": len(got_log),
        "leftovers": leftovers,
    }
    print()
    harness.print_table(("check", "holds"), [(name, "yes" if ok else "NO") for name, ok in checks.items()])
    print(json.dumps(summary, indent=2))
    out = Path(args.out) if args.out else harness.RESULTS / f"soak_{harness.platform_tag()}.json"
    harness.write_json(
        out,
        {"steps": args.steps, "rounds": args.rounds, "checks": checks, "summary": summary, "stops": rounds},
    )
    if not all(checks.values()):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
