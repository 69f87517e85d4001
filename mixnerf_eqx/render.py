"""`python -m mixnerf_eqx.render`: see `mixnerf_eqx.cli.render`."""

from .cli.render import main as main

if __name__ == "__main__":
    raise SystemExit(main())
