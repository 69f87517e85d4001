"""`python -m mixnerf_eqx.sweep`: see `mixnerf_eqx.cli.sweep`."""

from .cli.sweep import main as main

if __name__ == "__main__":
    raise SystemExit(main())
