"""The commands' entry modules (`python -m mixnerf_eqx.<name>`): their start-up and their `main`.

Run as a command, an entry module first starts the process again with the allocator preloaded
(`allocator.preload_allocator`; only a process started as `python -m mixnerf_eqx.<name>`, so
that a script running an entry module through `runpy` is never started again), before JAX or
the model is imported; then it makes a Ctrl-C that Python would drop reach the command
(`interrupt.redeliver_dropped_interrupts`) and imports the command's modules, so that a Ctrl-C
while they load ends with one line and status 130, not a traceback. Imported by other code, an
entry module does none of this.
"""

import importlib
import sys
from collections.abc import Callable

from .allocator import preload_allocator, started_as_command
from .interrupt import STOPPED_WHILE_LOADING, redeliver_dropped_interrupts


def command_main(name: str, module: str) -> Callable[..., int]:
    """`mixnerf_eqx.cli.<name>.main`, imported for the entry module named `module` (its
    `__name__`): run as the command (`"__main__"`), the start-up above comes first and a
    Ctrl-C during the import exits 130 (nothing was done yet); imported by other code, the
    process is left as it is and the interrupt is the caller's."""
    if module != "__main__":
        return importlib.import_module(f"mixnerf_eqx.cli.{name}").main
    if started_as_command():
        preload_allocator()
    redeliver_dropped_interrupts()
    try:
        return importlib.import_module(f"mixnerf_eqx.cli.{name}").main
    except KeyboardInterrupt:
        print(STOPPED_WHILE_LOADING, file=sys.stderr)
        raise SystemExit(130) from None
