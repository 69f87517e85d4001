"""Reproduce a table: `python -m mixnerf_eqx.sweep --config NAME|FILE.toml [--seeds 0,1,2] [...]`.

Trains and evaluates the config on every scene of its benchmark (or `--scenes`) with every
seed, one run folder each under `--out`; runs again to resume what is unfinished (finished
runs are read, not trained again). Writes `table.md` and `table.json`: each scene's metrics
(mean and standard deviation over seeds), their mean over scenes (with its spread over
seeds) and the published number from the config's `reproduces` line. `--engine submitit`
hands the runs to submitit (Slurm, or local processes) instead of running them here.
"""

import argparse
import sys
from pathlib import Path

from .._config import SEED_MAX, ConfigError, load_config, replace_setting
from .._runs.loop import TrainingDiverged
from .._runs.sweep import (
    SweepRun,
    aggregate,
    format_markdown,
    plan_sweep,
    run_local,
    run_submitit,
    write_table,
)
from .._util.interrupt import deferred_interrupts
from .._util.lock import hold_folder
from .._util.typecheck import add_typecheck_argument, typecheck_argument
from ..data import DatasetError
from .common import report_error
from .train import DEFAULT_CONFIG


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.sweep", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--config",
        default=DEFAULT_CONFIG,
        help=f"a packaged config's name or a TOML file (default: {DEFAULT_CONFIG})",
    )
    parser.add_argument("--seeds", default="0", help="comma-separated seeds (default: 0)")
    parser.add_argument("--scenes", default="", help="comma-separated scenes (default: the benchmark's)")
    parser.add_argument(
        "--out", type=Path, default=None, help="sweep folder (default: runs/sweep_<config name>)"
    )
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: data.data_dir, else $MIXNERF_DATA_DIR)"
    )
    parser.add_argument(
        "--engine",
        choices=("local", "submitit"),
        default="local",
        help="local: one run after another in this process; submitit: as jobs (the cluster extra)",
    )
    parser.add_argument(
        "--cluster",
        choices=("auto", "slurm", "local"),
        default="auto",
        help="submitit's cluster (auto: Slurm where sbatch exists, else local processes)",
    )
    parser.add_argument(
        "--timeout-min", type=int, default=24 * 60, help="submitit: a job's time limit in minutes"
    )
    parser.add_argument("--partition", default=None, help="submitit on Slurm: the partition")
    parser.add_argument("--gpus-per-run", type=int, default=0, help="submitit: GPUs per job (default 0)")
    parser.add_argument("--cpus-per-run", type=int, default=None, help="submitit: CPUs per job")
    add_typecheck_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the runs' progress bars")
    parser.add_argument(
        "overrides", nargs="*", metavar="section.key=value", help="config overrides, e.g. train.max_steps=200"
    )
    return parser.parse_intermixed_args(argv)


def _seeds(text: str) -> list[int]:
    try:
        seeds = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ConfigError(f"--seeds must be comma-separated integers, got {text!r}") from None
    if not seeds or any(not 0 <= seed <= SEED_MAX for seed in seeds):
        raise ConfigError(f"--seeds must list integers in [0, {SEED_MAX}] (wider seeds alias), got {text!r}")
    return seeds


def _submitit_parameters(args: argparse.Namespace) -> dict:
    if args.timeout_min < 1:
        raise ConfigError(f"--timeout-min must be positive, got {args.timeout_min}")
    if args.gpus_per_run < 0:
        raise ConfigError(f"--gpus-per-run must be 0 or more, got {args.gpus_per_run}")
    parameters = {"timeout_min": args.timeout_min, "gpus_per_node": args.gpus_per_run, "tasks_per_node": 1}
    if args.cpus_per_run is not None:
        parameters["cpus_per_task"] = args.cpus_per_run
    if args.partition:
        parameters["slurm_partition"] = args.partition
    return parameters


def run(args: argparse.Namespace) -> int:
    """Runs the sweep `args` describe; returns the exit status (1 if a run failed)."""
    config = load_config(args.config, args.overrides)
    if args.data_dir is not None:
        config = replace_setting(config, "data", data_dir=args.data_dir)
    out = args.out or Path("runs") / f"sweep_{config.name}"
    scenes = [scene.strip() for scene in args.scenes.split(",") if scene.strip()]
    runs = plan_sweep(config, out, scenes=scenes, seeds=_seeds(args.seeds))
    print(f"sweep of {config.name}: {len(runs)} runs in {out}")
    out.mkdir(parents=True, exist_ok=True)
    # One sweep per folder: a second sweep on the same `--out` fails here, before any run.
    with hold_folder(out, "sweep", "--out"):
        return _run_holding(args, config, out, runs)


def _run_holding(args: argparse.Namespace, config, out: Path, runs: list[SweepRun]) -> int:
    """`run`, once the sweep folder is this process's."""

    def on_run(index: int, sweep_run: SweepRun, status: str) -> None:
        print(f"[{index + 1}/{len(runs)}] {sweep_run.scene}, seed {sweep_run.seed}: {status}", flush=True)

    if args.engine == "local":
        results, failures = run_local(runs, progress=not args.no_progress, on_run=on_run)
    else:
        try:
            import submitit  # noqa: F401
        except ImportError:
            raise ConfigError(
                "--engine submitit needs the cluster extra: pip install -e '.[cluster]'"
            ) from None
        cluster = None if args.cluster == "auto" else args.cluster
        results, failures = run_submitit(
            runs, out / "jobs", cluster=cluster, parameters=_submitit_parameters(args), on_run=on_run
        )
    table = aggregate(config, runs, results)
    table["failed"] = {f"{scene} seed {seed}": message for (scene, seed), message in failures.items()}
    markdown, data = write_table(table, out)
    print("\n" + format_markdown(table))
    print(f"table: {markdown} and {data}")
    return 1 if failures else 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        with typecheck_argument(args), deferred_interrupts():
            return run(args)
    except (ConfigError, DatasetError, ValueError, OSError) as error:
        return report_error(error)
    except TrainingDiverged as error:
        print(f"\ntraining stopped: {error}; run the sweep again to go on", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\ninterrupted: run the same command again to resume the sweep", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
