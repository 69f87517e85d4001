"""`python -m mixnerf_eqx.next_view`: see `mixnerf_eqx.cli.next_view`."""

from ._util.entry import command_main

main = command_main("next_view", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
