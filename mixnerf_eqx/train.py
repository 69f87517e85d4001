"""`python -m mixnerf_eqx.train`: see `mixnerf_eqx.cli.train`."""

from .cli.train import main as main

if __name__ == "__main__":
    raise SystemExit(main())
