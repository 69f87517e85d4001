"""`python -m mixnerf_eqx.view`: see `mixnerf_eqx.cli.view`."""

from .cli.view import main as main

if __name__ == "__main__":
    raise SystemExit(main())
