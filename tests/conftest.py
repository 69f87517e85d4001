import atexit
import dataclasses
import os
import shutil
import tempfile

# Each worker process of the suite is a JAX client: on a GPU none may take most of its memory
# up front, or the second one would find none left (set before JAX is imported).
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402
from helpers import TINY_OVERRIDES
from hypothesis import settings

from mixnerf_eqx import fit, load_config
from mixnerf_eqx.data import load_dataset

# CI runs the property tests on a fixed sequence of examples, so that a red run can be
# reproduced exactly; elsewhere every run explores new examples.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

# Many tests train the same tiny model: each `fit` traces a new step function, but its XLA
# program is the same, so a compilation cache (fresh for each session, so it cannot go stale)
# lets the compiler's work be done once. The executables are the same, so are the results.
_XLA_CACHE = tempfile.mkdtemp(prefix="mixnerf-eqx-xla-")
atexit.register(shutil.rmtree, _XLA_CACHE, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops JAX's compiled programs after each test module.

    A whole run compiles thousands of small XLA programs; each executable keeps its code
    mapped, and one process holding all of them crashed the CPU compiler near the end of the
    suite. The persistent cache above still spares the recompilation where programs repeat.
    """
    yield
    jax.clear_caches()


@pytest.fixture
def tiny_config(tmp_path):
    config = load_config("builtin", TINY_OVERRIDES)
    return dataclasses.replace(config, train=dataclasses.replace(config.train, run_dir=str(tmp_path / "run")))


@pytest.fixture(scope="session")
def tiny_scene():
    config = load_config("builtin", TINY_OVERRIDES)
    return load_dataset(config.data)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory, tiny_scene):
    """A run folder of the tiny config trained for 60 steps (the tiny scene has validation
    views), and its model: enough for the predictive pass to see something."""
    config = load_config("builtin", TINY_OVERRIDES)
    run_dir = tmp_path_factory.mktemp("short") / "run"
    config = dataclasses.replace(
        config, train=dataclasses.replace(config.train, run_dir=str(run_dir), max_steps=60, eval_every=0)
    )
    model = fit(config, dataset=tiny_scene, progress=False, write_renders=False).model
    return run_dir, model
