"""`python -m mixnerf_eqx.eval`: see `mixnerf_eqx.cli.eval`."""

from .cli.eval import main as main

if __name__ == "__main__":
    raise SystemExit(main())
