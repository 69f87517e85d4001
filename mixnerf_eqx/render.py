"""`python -m mixnerf_eqx.render`: see `mixnerf_eqx.cli.render`."""

from ._util.entry import command_main

main = command_main("render", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
