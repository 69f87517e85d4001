"""Run folders: what `fit` writes and how to read it back (re-exports only).

    import mixnerf_eqx as mx
    run = mx.runs.restore_run("runs/quickstart")     # its config, scene, state and checkpoint
    scene = run.dataset
    rendered = mx.render_views(run.model, scene.test, scene.near, scene.far)

A run folder holds `config.json`, `train_log.jsonl`, `checkpoints/` and, once evaluated,
`metrics.json` and `renders/`; one process writes it at a time (`hold_folder`).
"""

from ._runs.checkpoint import CheckpointError as CheckpointError
from ._runs.checkpoint import checkpoints as checkpoints
from ._runs.checkpoint import latest_checkpoint as latest_checkpoint
from ._runs.checkpoint import load_checkpoint as load_checkpoint
from ._runs.checkpoint import read_checkpoint_meta as read_checkpoint_meta
from ._runs.checkpoint import save_checkpoint as save_checkpoint
from ._runs.run_folder import Run as Run
from ._runs.run_folder import grid_for_rendering as grid_for_rendering
from ._runs.run_folder import make_skipping as make_skipping
from ._runs.run_folder import render_summary as render_summary
from ._runs.run_folder import restore_run as restore_run
from ._runs.run_folder import write_view_renders as write_view_renders
from ._util.lock import FolderBusyError as FolderBusyError
from ._util.lock import hold_folder as hold_folder
