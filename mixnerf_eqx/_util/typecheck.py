"""The one switch for runtime shape checks.

The package installs jaxtyping's import hook with beartype as it is imported (`__init__.py`),
so every annotated function and Module of `mixnerf_eqx` checks shapes and dtypes, in notebooks,
in the command-line tools and in the tests. The checks run while JAX traces: a compiled step
pays nothing for them. They are turned off with jaxtyping's own switch,
`jaxtyping.config.jaxtyping_disable`, which every checked call reads when it runs: set by
`--no-typecheck` on the command line, `set_typecheck(False)` in Python, or `JAXTYPING_DISABLE=1`
in the environment. Nothing else turns them on or off.
"""

import argparse
import contextlib
import sys
import warnings
from collections.abc import Iterator

import jaxtyping


def set_typecheck(enabled: bool) -> None:
    """Turns runtime shape checks on or off for every later call (and trace)."""
    jaxtyping.config.update("jaxtyping_disable", not enabled)


def typecheck_enabled() -> bool:
    """Whether runtime shape checks are on."""
    return not jaxtyping.config.jaxtyping_disable


def add_typecheck_argument(parser: argparse.ArgumentParser) -> None:
    """Adds `--no-typecheck` to a command line."""
    parser.add_argument(
        "--no-typecheck",
        action="store_true",
        help="turn off runtime shape checks (they cost trace time only)",
    )


@contextlib.contextmanager
def typecheck_argument(args: argparse.Namespace) -> Iterator[None]:
    """Acts on `--no-typecheck` for the duration of a command (the switch is restored after,
    so that calling a command's `main` from Python leaves the caller's setting alone). Warnings
    are shown as one line each meanwhile, as a command line's messages are."""
    previous, show = typecheck_enabled(), warnings.showwarning
    if args.no_typecheck:
        set_typecheck(False)

    def one_line(message, category, filename, lineno, file=None, line=None):
        print(f"warning: {message}", file=sys.stderr if file is None else file)

    warnings.showwarning = one_line
    try:
        yield
    finally:
        set_typecheck(previous)
        warnings.showwarning = show
