"""One writer per folder: an advisory lock that a training run (or a sweep) holds on its folder.

`hold_folder(path)` takes an exclusive `flock` on `path/.lock` for as long as the block runs.
The kernel releases it when the holder exits in any way (return, exception, Ctrl-C, `kill -9`),
so a lock is never stale: a folder whose owner is gone can be taken at once. A second
writer fails at the start, before touching anything, with a `FolderBusyError` naming the
holder (its pid, host and start time, which the holder writes into the lock file). Readers
of a run (`eval`, `render`) take no lock on it: checkpoints and metrics are written to a staging
name and renamed into place, so a reader sees the old file or the new one, never half of one.
`eval` locks its own output instead (`.<folder>.eval.lock` beside it), one evaluation at a time.

Where `fcntl` does not exist (Windows), the lock is a no-op and says so once.
"""

import contextlib
import datetime
import os
import socket
import warnings
from collections.abc import Iterator
from pathlib import Path

from .._config import ConfigError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Linux or macOS
    fcntl = None

LOCK_NAME = ".lock"


class FolderBusyError(ConfigError):
    """Another process is writing to the folder."""


def _holder(handle) -> str:
    handle.seek(0)
    text = handle.read().strip()
    return text or "a process that has not yet said who it is"


@contextlib.contextmanager
def hold_folder(
    folder: str | Path,
    what: str = "run",
    option: str = "train.run_dir",
    name: str = LOCK_NAME,
    label: str | Path | None = None,
) -> Iterator[Path]:
    """Holds the exclusive lock of `folder` (created if missing) for the block.

    **Arguments:**

    - `folder`: the folder one process writes to.
    - `what`, `option`: named in the error (`"run"`, `"train.run_dir"`; a sweep: `"sweep"`,
      `"--out"`).
    - `name`: the lock file's name in `folder` (an evaluation locks its output's name in the
      folder that holds it, beside a training run's own lock).
    - `label`: what the error says is in use (default: `folder`).

    **Raises:**

    `FolderBusyError` when another process holds it.
    """
    folder = Path(folder)
    path = folder / name
    if fcntl is None:  # pragma: no cover
        warnings.warn(
            f"no file locks on this system: nothing stops a second writer in {folder}", stacklevel=3
        )
        yield path
        return
    created = not path.exists()
    handle = _locked(path, folder if label is None else Path(label), what, option)
    try:
        started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}, since {started}\n")
        handle.flush()
        failed = False
        try:
            yield path
        except BaseException:
            failed = True
            raise
        finally:
            handle.seek(0)
            handle.truncate()
            handle.flush()
            if failed and created:
                # A block that failed in a folder with no lock before leaves none behind (a
                # user's folder keeps no trace of a refused run). Removed while still held: a
                # process that opened this file meanwhile sees on locking that the path has
                # gone (`_locked`) and starts again on a new file.
                with contextlib.suppress(OSError):
                    path.unlink()
            # Otherwise emptied, not removed (the file of a run folder stays its lock).
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
    finally:
        handle.close()


def _locked(path: Path, folder: Path, what: str, option: str):
    """`path` opened and exclusively locked; the lock taken on the file the path names now
    (a file removed by its holder while this process waited is let go, and the new one tried)."""
    for _ in range(100):
        handle = open(path, "a+")  # noqa: SIM115 - held open by the caller
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(handle)
            handle.close()
            raise FolderBusyError(
                f"{folder} is in use by another {what} ({holder}). Wait for it to end, stop "
                f"it, or choose another {option}."
            ) from None
        try:
            current = os.stat(path).st_ino
        except FileNotFoundError:
            current = None
        if current == os.fstat(handle.fileno()).st_ino:
            return handle
        handle.close()  # the holder removed the file we locked: lock the one there now
    raise FolderBusyError(f"{folder}: its lock file keeps changing; choose another {option}.")
