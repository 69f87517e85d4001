"""Runs the notebooks as tests (nbmake, `pytest` from the repository root) with a small step count.

Every notebook reads its number of training steps from `MIXNERF_EQX_NOTEBOOK_STEPS` (its own
default when unset), so the suite checks that each one runs from top to bottom without
waiting for a real training run. The kernel inherits this process's environment.
"""

import atexit
import os
import shutil
import tempfile

# Enough steps to exercise the whole loop (warm-up, a checkpoint, the final evaluation).
os.environ.setdefault("MIXNERF_EQX_NOTEBOOK_STEPS", "20")
# Jupyter's own deprecation warning about its configuration folders, which the suite's
# `filterwarnings = error` would turn into a failure of every notebook.
os.environ.setdefault("JUPYTER_PLATFORM_DIRS", "1")

# The short runs train into a fresh folder that this process removes when the suite ends, so
# that running the notebooks leaves nothing in the system's temporary folder.
if "MIXNERF_EQX_NOTEBOOK_RUN_DIR" not in os.environ:
    _RUN_ROOT = tempfile.mkdtemp(prefix="mixnerf-notebook-")
    atexit.register(shutil.rmtree, _RUN_ROOT, ignore_errors=True)
    os.environ["MIXNERF_EQX_NOTEBOOK_RUN_DIR"] = os.path.join(_RUN_ROOT, "run")
