"""`python -m mixnerf_eqx.sweep`: see `mixnerf_eqx.cli.sweep`."""

from ._util.entry import command_main

main = command_main("sweep", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
