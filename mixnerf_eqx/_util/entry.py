"""The commands' entry modules (`python -m mixnerf_eqx.<name>`): their `main`, loaded so that a
Ctrl-C while the command's modules load ends with one line and status 130, not a traceback."""

import importlib
import sys
from collections.abc import Callable

from .interrupt import STOPPED_WHILE_LOADING, stop_quieting_interrupts


def command_main(name: str, module: str) -> Callable[..., int]:
    """`mixnerf_eqx.cli.<name>.main`, imported for the entry module named `module` (its
    `__name__`): run as the command, a Ctrl-C during the import exits 130 (nothing was done
    yet); imported by other code, the interrupt is the caller's."""
    try:
        main = importlib.import_module(f"mixnerf_eqx.cli.{name}").main
    except KeyboardInterrupt:
        if module != "__main__":
            raise
        print(STOPPED_WHILE_LOADING, file=sys.stderr)
        raise SystemExit(130) from None
    stop_quieting_interrupts()  # from here on the command handles its own interrupts
    return main
