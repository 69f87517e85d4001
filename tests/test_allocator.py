"""The commands start again with mimalloc preloaded, once, and leave the environment as given.

A `sitecustomize` module on the child's path records, as the process ends, whether mimalloc
is mapped into it and what its environment holds; `exec` replaces the first process before it
ends, so the record is the one of the process that did the work.
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from helpers import TINY_OVERRIDES

from mixnerf_eqx._util import allocator as _allocator
from mixnerf_eqx._util.allocator import allocator_in_use, allocator_library

linux_only = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="LD_PRELOAD and /proc are Linux's"
)

PROBE = textwrap.dedent(
    """
    import atexit, json, os

    MARKS = ("MIXNERF_ORIGINAL_LD_PRELOAD", "MIXNERF_ALLOCATOR_TRIED")

    def _record():
        with open(os.environ["PROBE_OUT"], "a") as out:
            maps = open("/proc/self/maps").read()
            out.write(json.dumps({
                "pid": os.getpid(),
                "mimalloc": "libmimalloc" in maps,
                "LD_PRELOAD": os.environ.get("LD_PRELOAD"),
                "marks": sorted(k for k in MARKS if k in os.environ),
            }) + "\\n")

    atexit.register(_record)
    """
)


def _run_probed(tmp_path: Path, args: list[str], **env_changes: str | None) -> list[dict]:
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(PROBE)
    out = tmp_path / "probe.jsonl"
    out.unlink(missing_ok=True)
    env = dict(os.environ, PROBE_OUT=str(out))
    env["PYTHONPATH"] = os.pathsep.join([str(site), *filter(None, [env.get("PYTHONPATH")])])
    for key, value in env_changes.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    finished = subprocess.run(
        [sys.executable, *args],
        env=env,
        cwd=tmp_path,
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    _run_probed.stderr = finished.stderr
    return [json.loads(line) for line in out.read_text().splitlines()]


def test_the_library_is_chosen_by_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("MIXNERF_ALLOCATOR", "system")
    assert allocator_library() is None
    monkeypatch.setenv("MIXNERF_ALLOCATOR", str(tmp_path / "missing.so"))
    with pytest.raises(FileNotFoundError, match="MIXNERF_ALLOCATOR"):
        allocator_library()
    other = tmp_path / "libother.so"
    other.write_bytes(b"\x7fELF" + bytes(60))  # an ELF header: taken as a library
    monkeypatch.setenv("MIXNERF_ALLOCATOR", str(other))
    assert allocator_library() == other.resolve()
    text = tmp_path / "notes.txt"
    text.write_text("not a library")
    monkeypatch.setenv("MIXNERF_ALLOCATOR", str(text))
    with pytest.raises(FileNotFoundError, match="is not a shared library"):
        allocator_library()
    assert allocator_in_use() == "system"
    monkeypatch.delenv("MIXNERF_ALLOCATOR")
    default = allocator_library()
    if sys.platform.startswith("linux"):
        assert default is not None and default.is_file() and default.name.startswith("libmimalloc.so")


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["python", "-m", "mixnerf_eqx.train", "--help"], True),
        (["python", "-u", "-X", "dev", "-W", "error", "-m", "mixnerf_eqx.sweep"], True),
        (["python", "-mmixnerf_eqx.eval", "runs/x"], True),
        (["python", "-m", "mixnerf_eqx.render"], True),
        (["python", "-Im", "mixnerf_eqx.train"], True),
        (["python", "-B", "-Xdev", "-Wdefault", "-m", "mixnerf_eqx.train"], True),
        (["python", "-W", "error", "-Bm", "mixnerf_eqx.eval"], True),
        (["python", "--check-hash-based-pycs", "never", "-m", "mixnerf_eqx.sweep"], True),
        (["python", "-Bc", "import mixnerf_eqx", "-m", "mixnerf_eqx.train"], False),
        (["python", "-X", "-m", "mixnerf_eqx.train"], False),
        (["python", "-m", "pytest", "-m", "mixnerf_eqx.train"], False),
        (["python", "-m", "mixnerf_eqx"], False),
        (["python", "-m"], False),
        (["python", "script.py", "-m", "mixnerf_eqx.train"], False),
        (["python", "-c", "import mixnerf_eqx", "-m", "mixnerf_eqx.train"], False),
        (["python", "-", "-m", "mixnerf_eqx.train"], False),
        (["python"], False),
    ],
)
def test_only_the_commands_start_again(argv, expected):
    assert _allocator._started_as_command(argv) is expected


@linux_only
def test_a_command_runs_with_mimalloc_and_hands_on_the_environment_it_was_given(tmp_path):
    if allocator_library() is None:
        pytest.skip("cmeel-mimalloc is not installed")
    records = _run_probed(
        tmp_path, ["-m", "mixnerf_eqx.train", "--help"], LD_PRELOAD=None, MIXNERF_ALLOCATOR=None
    )
    assert len(records) == 1, records  # the first process was replaced, not left running
    assert records[0]["mimalloc"]
    assert records[0]["LD_PRELOAD"] is None
    assert records[0]["marks"] == []
    # An empty LD_PRELOAD is given back as it was.
    records = _run_probed(
        tmp_path, ["-m", "mixnerf_eqx.eval", "--help"], LD_PRELOAD="", MIXNERF_ALLOCATOR=None
    )
    assert records[0]["mimalloc"] and records[0]["LD_PRELOAD"] == ""


@linux_only
def test_a_users_own_preload_wins(tmp_path):
    import ctypes.util

    libm = ctypes.util.find_library("m")
    if libm is None:
        pytest.skip("no libm to preload")
    records = _run_probed(
        tmp_path, ["-m", "mixnerf_eqx.train", "--help"], LD_PRELOAD=libm, MIXNERF_ALLOCATOR=None
    )
    assert len(records) == 1 and not records[0]["mimalloc"]
    assert records[0]["LD_PRELOAD"] == libm and records[0]["marks"] == []


@linux_only
def test_the_system_allocator_and_scripts_are_left_alone(tmp_path):
    records = _run_probed(tmp_path, ["-m", "mixnerf_eqx.train", "--help"], MIXNERF_ALLOCATOR="system")
    assert not records[0]["mimalloc"]
    records = _run_probed(tmp_path, ["-c", "import mixnerf_eqx"], MIXNERF_ALLOCATOR=None, LD_PRELOAD=None)
    assert not records[0]["mimalloc"]


@linux_only
def test_a_preload_that_fails_is_not_retried(tmp_path):
    # An ELF header and nothing usable behind it: the loader ignores it with a message, and
    # the command goes on once.
    fake = tmp_path / "libfake.so"
    fake.write_bytes(b"\x7fELF" + bytes(60))
    records = _run_probed(
        tmp_path, ["-m", "mixnerf_eqx.train", "--help"], MIXNERF_ALLOCATOR=str(fake), LD_PRELOAD=None
    )
    assert "cannot be preloaded" in _run_probed.stderr  # it was started again, with the preload
    assert len(records) == 1
    assert records[0]["LD_PRELOAD"] is None and records[0]["marks"] == []
    # Not an ELF file at all: named before any restart, and the command goes on as it is.
    text = tmp_path / "libtext.so"
    text.write_bytes(b"not an ELF file")
    records = _run_probed(
        tmp_path, ["-m", "mixnerf_eqx.train", "--help"], MIXNERF_ALLOCATOR=str(text), LD_PRELOAD=None
    )
    assert "is not a shared library (no ELF header" in _run_probed.stderr
    assert "cannot be preloaded" not in _run_probed.stderr  # never handed to the loader
    assert len(records) == 1 and records[0]["LD_PRELOAD"] is None


@linux_only
def test_training_is_the_same_under_either_allocator(tmp_path):
    """Where buffers live changes nothing computed: the log and the test metrics are equal
    bit for bit."""
    if allocator_library() is None:
        pytest.skip("cmeel-mimalloc is not installed")
    outputs = {}
    for choice in ("system", "mimalloc"):
        run_dir = tmp_path / choice
        args = ["-m", "mixnerf_eqx.train", "--config", "builtin", "--no-progress", "--run-dir", str(run_dir)]
        records = _run_probed(
            tmp_path, [*args, *TINY_OVERRIDES, "train.max_steps=10"], MIXNERF_ALLOCATOR=choice
        )
        assert records[0]["mimalloc"] is (choice == "mimalloc")
        log = [json.loads(line) for line in (run_dir / "train_log.jsonl").read_text().splitlines()]
        metrics = json.loads((run_dir / "metrics.json").read_text())
        outputs[choice] = ([{k: v for k, v in e.items() if k != "steps_per_s"} for e in log], metrics["test"])
    assert outputs["system"][0] and outputs["system"] == outputs["mimalloc"]


@linux_only
def test_a_script_can_start_itself_again_with_the_allocator(tmp_path):
    if allocator_library() is None:
        pytest.skip("cmeel-mimalloc is not installed")
    script = tmp_path / "script.py"
    script.write_text(
        "import sys\n"
        "import mixnerf_eqx as mx\n"
        "mx.runtime.preload_allocator()\n"
        "print(sys.argv[1:], mx.runtime.allocator_in_use())\n"
    )
    records = _run_probed(tmp_path, [str(script), "a", "b"], MIXNERF_ALLOCATOR=None, LD_PRELOAD=None)
    assert len(records) == 1 and records[0]["mimalloc"]
    assert records[0]["LD_PRELOAD"] is None and records[0]["marks"] == []
    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "MIXNERF_ALLOCATOR")}
    shown = subprocess.run(
        [sys.executable, str(script), "a", "b"], env=env, capture_output=True, text=True, check=True
    )
    assert shown.stdout.startswith("['a', 'b'] ") and "libmimalloc" in shown.stdout


@linux_only
def test_a_program_read_from_standard_input_is_not_started_again(tmp_path):
    if allocator_library() is None:
        pytest.skip("cmeel-mimalloc is not installed")
    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "MIXNERF_ALLOCATOR")}
    program = "import mixnerf_eqx as mx\nmx.runtime.preload_allocator()\nprint('ran', mx.runtime.allocator_in_use())\n"
    shown = subprocess.run(
        [sys.executable, "-"], input=program, env=env, capture_output=True, text=True, check=True, timeout=300
    )
    assert shown.stdout == "ran system\n"
    assert "standard input" in shown.stderr and "LD_PRELOAD=" in shown.stderr
