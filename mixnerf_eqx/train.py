"""`python -m mixnerf_eqx.train`: see `mixnerf_eqx.cli.train`."""

from ._util.entry import command_main

main = command_main("train", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
