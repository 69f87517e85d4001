"""The command lines, `python -m mixnerf_eqx.<verb>` (train, eval, render, sweep)."""
