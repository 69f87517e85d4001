"""`python -m mixnerf_eqx.view`: see `mixnerf_eqx.cli.view`."""

import sys

try:
    from .cli.view import main as main
except KeyboardInterrupt:
    # Ctrl-C while the command was still loading its modules: nothing was done yet.
    if __name__ != "__main__":
        raise
    print("stopped while loading; nothing was done", file=sys.stderr)
    raise SystemExit(130) from None

if __name__ == "__main__":
    raise SystemExit(main())
