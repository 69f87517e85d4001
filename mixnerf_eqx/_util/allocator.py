"""mimalloc for the command-line tools on Linux: a third off a CPU training step.

XLA's CPU runtime allocates the buffers of every execution of a compiled function when it
starts and frees them when it ends. glibc's malloc serves the large ones (and, on XLA's
worker threads, smaller ones from per-thread arenas that it trims) with fresh pages from the
kernel and gives them back on `free`, so each training step first touches tens of MB again:
130 steps of the quick start took three million page faults, and its tri-plane gradient
ran at less than half the speed (`benchmarks/speed.md`, "The CPU step"; the profile in
`benchmarks/LOG.md`). mimalloc
keeps freed pages for reuse; the step's values are unchanged, only where its buffers live.

A process can only get another allocator when it starts (`LD_PRELOAD`), so the commands
(`python -m mixnerf_eqx.train`, `eval`, `render`, `sweep`, ...) start themselves again, once,
with mimalloc preloaded, before JAX or the model is imported (`mixnerf_eqx._util.entry`).
The library comes from the `cmeel-mimalloc` wheel, a dependency on Linux. The preload is
taken out of the environment again once it is in effect, so that the programs a command
starts (FFmpeg for videos, a sweep's submitit jobs) start with the environment the user gave:
to give submitit jobs mimalloc too, set `LD_PRELOAD` to `allocator_library()` yourself.
Only Linux has `LD_PRELOAD` as used here; elsewhere nothing is done. A process that already
preloads libraries of the user's (`LD_PRELOAD` not empty: an allocator, a sanitiser) keeps
them alone, and one that cannot be started again without losing work (a program read from
standard input, an interactive session, a Jupyter kernel) is left as it is, with a warning.

`MIXNERF_ALLOCATOR` chooses: unset or `mimalloc` (the default), `system` (glibc's malloc, as
without this module), or the path of another allocator's shared library (tcmalloc, for
example). In a notebook or your own script, start Python with
`LD_PRELOAD=$(python -c "import mixnerf_eqx as mx; print(mx.runtime.allocator_library())")`, or call
`mx.runtime.preload_allocator()` first thing in a script (the benchmarks do: it starts the script
again with the library preloaded). `mx.runtime.allocator_in_use()` says which one a process runs with.
"""

import os
import sys
from pathlib import Path

ALLOCATOR_ENV = "MIXNERF_ALLOCATOR"
# The commands that start themselves again (`python -m mixnerf_eqx.<name>`).
COMMANDS = ("train", "eval", "render", "sweep", "view", "next_view")
# Set in the environment of the process started again: whether `LD_PRELOAD` was set (empty)
# before, to restore once the allocator is in effect, and a mark that stops a second start if
# the preload did not work.
_ORIGINAL_PRELOAD = "MIXNERF_ORIGINAL_LD_PRELOAD"
_TRIED = "MIXNERF_ALLOCATOR_TRIED"
_SYSTEM = ("system", "off", "0", "none", "")


def allocator_library() -> Path | None:
    """The shared library `MIXNERF_ALLOCATOR` chooses: mimalloc from the `cmeel-mimalloc`
    wheel by default, `None` for `system` or where there is none (not Linux, not
    installed). A path that does not exist is an error."""
    choice = os.environ.get(ALLOCATOR_ENV, "mimalloc").strip()
    if choice.lower() in _SYSTEM:
        return None
    if choice.lower() != "mimalloc":
        path = Path(choice).expanduser()
        if not path.is_file():
            raise FileNotFoundError(
                f"{ALLOCATOR_ENV}={choice!r} is not a file (give a shared library, or 'system')"
            )
        if not _is_elf(path):
            # The dynamic loader would only say "cannot be preloaded" and go on without it.
            raise FileNotFoundError(
                f"{ALLOCATOR_ENV}={choice!r} is not a shared library (no ELF header; give a .so "
                "file such as libmimalloc.so, or 'system')"
            )
        return path.resolve()
    if not sys.platform.startswith("linux"):
        return None
    from importlib import metadata

    try:
        distribution = metadata.distribution("cmeel-mimalloc")
    except metadata.PackageNotFoundError:
        return None
    for file in distribution.files or ():
        if file.name.startswith("libmimalloc.so"):
            path = Path(str(distribution.locate_file(file)))
            if path.is_file():
                return path.resolve()
    return None


def _is_elf(path: Path) -> bool:
    """Whether `path` starts as an ELF file does (a shared library on Linux)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(4) == b"\x7fELF"
    except OSError:
        return False


def _is_loaded(library: Path) -> bool:
    """Whether `library` is mapped into this process (Linux: `/proc/self/maps`)."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return False
    return str(library) in maps or library.name in maps


def _started_as_command(argv: list[str]) -> bool:
    """Whether this interpreter was started as `python [options] -m mixnerf_eqx.<command>`
    (`argv` as `sys.orig_argv`). Options are read as CPython reads them: short flags may be
    grouped (`-Bm`), `-W` and `-X` take the rest of their group or the next argument, and
    `-c`, `-m`, a script or `-` end the options."""
    commands = {f"mixnerf_eqx.{name}" for name in COMMANDS}
    index = 1
    while index < len(argv):
        arg = argv[index]
        if arg == "--check-hash-based-pycs":
            index += 2
            continue
        if not arg.startswith("-") or arg == "-" or arg.startswith("--"):
            return False  # a script, standard input, or a long option this does not know
        group = arg[1:]
        for position, flag in enumerate(group):
            rest = group[position + 1 :]
            if flag == "c":
                return False
            if flag == "m":
                module = rest or (argv[index + 1] if index + 1 < len(argv) else "")
                return module in commands
            if flag in "WX":
                index += 0 if rest else 1  # the argument is the rest of the group, or the next one
                break
        index += 1
    return False


def _interactive() -> str | None:
    """Why starting this process again would lose work, or `None`: standard input already
    read (`python -`, `python < script.py`), an interactive session, a Jupyter kernel."""
    if "ipykernel" in sys.modules:
        return "a Jupyter kernel"
    if sys.flags.interactive or hasattr(sys, "ps1"):
        return "an interactive session"
    if sys.argv and sys.argv[0] in ("", "-"):
        return "a program read from standard input"
    return None


def allocator_in_use() -> str:
    """The allocator this process runs with: the path of the preloaded library that
    `allocator_library()` names, or `"system"`."""
    try:
        library = allocator_library()
    except FileNotFoundError:
        return "system"
    return str(library) if library is not None and _is_loaded(library) else "system"


def preload_allocator() -> None:
    """Starts this process again, with the same command line, with `allocator_library()`
    preloaded, unless it already runs with it (or there is none, or it could not be
    preloaded). For scripts that time training (the benchmarks call it first); everything
    the process did before the call is done again, so call it before any work."""
    try:
        library = allocator_library()
    except FileNotFoundError as error:
        print(f"warning: {error}; going on with the system allocator", file=sys.stderr)
        return
    if library is None or not sys.platform.startswith("linux"):
        return
    if os.environ.get("LD_PRELOAD") and _ORIGINAL_PRELOAD not in os.environ:
        return  # the user preloads libraries of their own (an allocator, a sanitiser): theirs win
    if _is_loaded(library) or os.environ.get(_TRIED):
        # In effect (or it could not be preloaded): the programs this one starts get the
        # environment the user gave.
        original = os.environ.pop(_ORIGINAL_PRELOAD, None)
        if original is not None:
            # "=" where `LD_PRELOAD` was set and empty (a non-empty one is never replaced), "" where
            # it was not set.
            if original == "=":
                os.environ["LD_PRELOAD"] = ""
            else:
                os.environ.pop("LD_PRELOAD", None)
        os.environ.pop(_TRIED, None)
        return
    lost = _interactive()
    if lost is not None:
        print(
            f"warning: not starting {lost} again with {library.name}: start Python with LD_PRELOAD={library}",
            file=sys.stderr,
        )
        return
    env = dict(os.environ)
    env[_ORIGINAL_PRELOAD] = "=" if "LD_PRELOAD" in env else ""
    env[_TRIED] = "1"
    env["LD_PRELOAD"] = str(library)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    try:
        os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
    except OSError as error:
        print(
            f"warning: could not start again with {library} ({error}); going on without it", file=sys.stderr
        )


def started_as_command() -> bool:
    """Whether this process was started as `python -m mixnerf_eqx.<command>`."""
    return _started_as_command(sys.orig_argv)
