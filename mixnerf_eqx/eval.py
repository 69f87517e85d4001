"""`python -m mixnerf_eqx.eval`: see `mixnerf_eqx.cli.eval`."""

from ._util.entry import command_main

main = command_main("eval", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
