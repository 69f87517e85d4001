"""What the command lines share: one `error:` line for a problem the user can fix."""

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from .._util.compilation_cache import use_compilation_cache
from .._util.interrupt import deferred_interrupts
from .._util.typecheck import typecheck_argument


def report_error(error: Exception) -> int:
    """Prints `error` as one `error: ...` line on stderr and returns the exit status, 2.

    An operating-system error is named by its file and its reason (`runs/x: Permission
    denied`) rather than by its errno; every other error by its message.
    """
    if isinstance(error, OSError) and not isinstance(error, FileNotFoundError):
        where = f"{error.filename}: " if error.filename else ""
        print(f"error: {where}{error.strerror or error}", file=sys.stderr)
    else:
        print(f"error: {error}", file=sys.stderr)
    return 2


def run_command(
    args: argparse.Namespace, body: Callable[[], object], *, interrupted: str | None = None
) -> int:
    """Runs a command line's `body` as `eval` and `render` do, and returns the exit status.

    The compilation cache and the type-check switch follow `args`; Ctrl-C is deferred to the
    command's safe points. A problem the user can fix (a `ValueError`: configs, datasets and
    arguments raise subclasses of it; or an `OSError`) becomes one `error:` line and status 2;
    Ctrl-C becomes status 130, after the line `interrupted` where one is given.
    """
    use_compilation_cache(args)
    try:
        with typecheck_argument(args), deferred_interrupts():
            body()
    except (ValueError, OSError) as error:
        return report_error(error)
    except KeyboardInterrupt:
        if interrupted:
            print(f"\ninterrupted: {interrupted}", file=sys.stderr)
        return 130
    return 0


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """`RUN_DIR`, `--checkpoint` and `--data-dir`, as the commands that read a run take them."""
    parser.add_argument(
        "run_dir", type=Path, help="a training run's folder (holds config.json, checkpoints/)"
    )
    parser.add_argument("--checkpoint", type=Path, default=None, help="checkpoint folder (default: latest)")
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: the run's, else $MIXNERF_DATA_DIR)"
    )


def add_skipping_argument(parser: argparse.ArgumentParser) -> None:
    """`--skipping auto|on|off`, as the commands that render a run take it."""
    parser.add_argument(
        "--skipping",
        choices=("auto", "on", "off"),
        default="auto",
        help="skip empty space and finished rays with an occupancy grid built from the checkpoint "
        "(auto: if the run's occupancy.enabled or occupancy.render_skipping)",
    )
