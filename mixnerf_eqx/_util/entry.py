"""The commands' entry modules (`python -m mixnerf_eqx.<name>`): their `main`, loaded so that a
Ctrl-C while the command's modules load ends with one line and status 130, not a traceback."""

import importlib
import sys
from collections.abc import Callable


def command_main(name: str, module: str) -> Callable[..., int]:
    """`mixnerf_eqx.cli.<name>.main`, imported for the entry module named `module` (its
    `__name__`): run as the command, a Ctrl-C during the import exits 130 (nothing was done
    yet); imported by other code, the interrupt is the caller's."""
    try:
        return importlib.import_module(f"mixnerf_eqx.cli.{name}").main
    except KeyboardInterrupt:
        if module != "__main__":
            raise
        print("stopped while loading; nothing was done", file=sys.stderr)
        raise SystemExit(130) from None
