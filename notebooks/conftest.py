"""Runs the notebooks as tests (nbmake, `pytest` from the repository root) with a small step count.

Every notebook reads its number of training steps from `MIXNERF_EQX_NOTEBOOK_STEPS` (its own
default when unset), so the suite checks that each one runs from top to bottom without
waiting for a real training run. The kernel inherits this process's environment.
"""

import os

# Enough steps to exercise the whole loop (warm-up, a checkpoint, the final evaluation).
os.environ.setdefault("MIXNERF_EQX_NOTEBOOK_STEPS", "20")
# Jupyter's own deprecation warning about its configuration folders, which the suite's
# `filterwarnings = error` would turn into a failure of every notebook.
os.environ.setdefault("JUPYTER_PLATFORM_DIRS", "1")
