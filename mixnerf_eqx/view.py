"""`python -m mixnerf_eqx.view`: see `mixnerf_eqx.cli.view`."""

from ._util.entry import command_main

main = command_main("view", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
