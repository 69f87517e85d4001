"""The command-line tools' compilation cache: where it goes, how it is turned off, and that a
second process reads what the first wrote."""

import argparse
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from mixnerf_eqx._util.compilation_cache import (
    add_compilation_cache_argument,
    default_cache_dir,
    use_compilation_cache,
)


def _args(*argv):
    parser = argparse.ArgumentParser()
    add_compilation_cache_argument(parser)
    return parser.parse_args(list(argv))


def test_default_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("MIXNERF_COMPILATION_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "mixnerf_eqx" / "jax"
    monkeypatch.setenv("MIXNERF_COMPILATION_CACHE", str(tmp_path / "mine"))
    assert default_cache_dir() == tmp_path / "mine"
    for off in ("off", "0", "false", ""):
        monkeypatch.setenv("MIXNERF_COMPILATION_CACHE", off)
        assert default_cache_dir() is None


def test_a_folder_jax_already_has_is_kept_and_the_flag_turns_it_off():
    # The suite's conftest gives JAX a session folder: the commands leave it as it is.
    configured = jax.config.jax_compilation_cache_dir
    assert configured
    assert use_compilation_cache(_args()) == Path(configured)
    assert use_compilation_cache(_args("--no-compilation-cache")) is None
    assert jax.config.jax_compilation_cache_dir == configured


PROBE = """
import time, jax, jax.numpy as jnp
from mixnerf_eqx._util.compilation_cache import add_compilation_cache_argument, use_compilation_cache
import argparse
parser = argparse.ArgumentParser(); add_compilation_cache_argument(parser)
print(use_compilation_cache(parser.parse_args([])))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # this small program too
def body(x):
    for _ in range(60):
        x = jnp.sin(x) @ jnp.cos(x).T / x.shape[0]
    return x
jax.block_until_ready(jax.jit(body)(jnp.ones((64, 64))))
"""


def test_a_second_process_reads_the_cache_the_first_wrote(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["MIXNERF_COMPILATION_CACHE"] = str(tmp_path / "cache")
    first = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    assert first.stdout.strip().endswith(str(tmp_path / "cache"))
    entries = sorted((tmp_path / "cache").iterdir())
    assert any(path.name.startswith("jit_body") for path in entries)
    subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    # Nothing new was compiled and written for the same program.
    assert sorted((tmp_path / "cache").iterdir()) == entries


def test_an_unusable_folder_is_reported_and_the_command_goes_on(monkeypatch, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("MIXNERF_COMPILATION_CACHE", str(blocker / "cache"))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("mixnerf_eqx._util.compilation_cache.jax.config", _NoCache())
        assert use_compilation_cache(_args()) is None
    assert "compilation cache off" in capsys.readouterr().out


class _NoCache:
    jax_compilation_cache_dir = None

    def update(self, *args):  # never reached: the folder cannot be made
        raise AssertionError("the cache must not be enabled")
