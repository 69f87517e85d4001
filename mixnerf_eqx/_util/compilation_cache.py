"""JAX's persistent compilation cache for the command-line tools.

Compiling the training step and the render functions takes a large share of a short run on a
CPU (`benchmarks/speed.md`, "Compilation and start-up"). With the cache, a second run of the same
settings in a new process loads the compiled programs from disk instead. JAX keys each entry
by the program, the JAX and XLA versions and the device, so a stale entry is never used.

The commands use the folder JAX is already given (`$JAX_COMPILATION_CACHE_DIR`, or
`jax.config` in the calling Python), otherwise
`$MIXNERF_COMPILATION_CACHE`, otherwise `$XDG_CACHE_HOME/mixnerf_eqx/jax` (by default
`~/.cache/mixnerf_eqx/jax`); `--no-compilation-cache` or `MIXNERF_COMPILATION_CACHE=off`
turns it off. From Python, `enable_compilation_cache(path)` does the same.
"""

import argparse
import os
from pathlib import Path

import jax

# Programs that compile faster than this are not written (the eager helpers of a run).
_MIN_COMPILE_SECONDS = 0.5
_OFF = ("off", "0", "false", "no", "")


def default_cache_dir() -> Path | None:
    """The cache folder the commands use, or `None` when the environment turns it off."""
    chosen = os.environ.get("MIXNERF_COMPILATION_CACHE")
    if chosen is not None:
        return None if chosen.strip().lower() in _OFF else Path(chosen).expanduser()
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "mixnerf_eqx" / "jax"


def enable_compilation_cache(path: str | os.PathLike) -> Path:
    """Turns JAX's persistent compilation cache on, in `path` (created if missing)."""
    folder = Path(path).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_SECONDS)
    return folder


def add_compilation_cache_argument(parser: argparse.ArgumentParser) -> None:
    """Adds `--no-compilation-cache` to a command line."""
    parser.add_argument(
        "--no-compilation-cache",
        action="store_true",
        help="do not read or write JAX's compilation cache (default: ~/.cache/mixnerf_eqx/jax)",
    )


def use_compilation_cache(args: argparse.Namespace) -> Path | None:
    """Acts on `--no-compilation-cache` and the environment; returns the folder in use. An
    unusable folder is reported and the command goes on without a cache."""
    if args.no_compilation_cache:
        return None
    configured = jax.config.jax_compilation_cache_dir
    if configured:
        # Set through JAX itself ($JAX_COMPILATION_CACHE_DIR, or by the caller in Python).
        return Path(configured)
    folder = default_cache_dir()
    if folder is None:
        return None
    try:
        return enable_compilation_cache(folder)
    except OSError as error:
        print(f"warning: compilation cache off ({folder}: {error.strerror or error})")
        return None
