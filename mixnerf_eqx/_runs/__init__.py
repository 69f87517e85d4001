"""Runs: `fit` over many steps and what it leaves in a run folder (checkpoints, the training
log, renders, a failed run told apart), read back by `restore_run`; sweeps of runs."""
