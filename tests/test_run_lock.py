"""One writer per run folder (`mixnerf_eqx._util.lock`): real second processes, started in the
middle of a run and at the same time as the first."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import TINY_OVERRIDES

from mixnerf_eqx._util.lock import LOCK_NAME, FolderBusyError, hold_folder

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="no flock on Windows")

_REPO = Path(__file__).resolve().parents[1]


def _train_command(run_dir: Path, steps: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "mixnerf_eqx.train",
        "--config",
        str(_REPO / "configs" / "builtin.toml"),
        "--run-dir",
        str(run_dir),
        "--no-progress",
        "--no-compilation-cache",
        *TINY_OVERRIDES,
        f"train.max_steps={steps}",
        "train.checkpoint_every=1000000",
        "train.eval_every=0",
    ]


def _logged_steps(run_dir: Path) -> list[int]:
    path = run_dir / "train_log.jsonl"
    if not path.exists():
        return []
    entries = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [entry["step"] for entry in entries if "loss" in entry]


def test_a_second_holder_in_the_same_process_is_refused_and_the_lock_is_free_after(tmp_path):
    with hold_folder(tmp_path):
        holder = (tmp_path / LOCK_NAME).read_text()
        assert f"pid {os.getpid()}" in holder
        with pytest.raises(
            FolderBusyError, match=f"in use by another run \\(pid {os.getpid()}.*train.run_dir"
        ):
            with hold_folder(tmp_path):
                pass
    with hold_folder(tmp_path, "sweep", "--out"):
        pass


def test_a_failed_block_leaves_no_lock_where_there_was_none(tmp_path):
    # A user's folder that was not a run folder: a refused or failed run leaves no .lock.
    with pytest.raises(RuntimeError, match="boom"), hold_folder(tmp_path):
        assert (tmp_path / LOCK_NAME).exists()
        raise RuntimeError("boom")
    assert not (tmp_path / LOCK_NAME).exists()
    # A run that ends normally keeps its lock file (emptied), and a later failure keeps it too.
    with hold_folder(tmp_path):
        pass
    assert (tmp_path / LOCK_NAME).read_text() == ""
    with pytest.raises(RuntimeError), hold_folder(tmp_path):
        raise RuntimeError("boom")
    assert (tmp_path / LOCK_NAME).exists()


def test_a_lock_file_removed_by_its_holder_is_not_taken(tmp_path, monkeypatch):
    # The file this process opened was removed (by a failing holder) before it locked it: the
    # lock is taken on the file the path names now, never on the orphan.
    import mixnerf_eqx._util.lock as lock

    opened = []
    real_open = open

    def opening(path, mode="r", *args, **kwargs):
        handle = real_open(path, mode, *args, **kwargs)
        if Path(path).name == LOCK_NAME and not opened:
            opened.append(handle)
            os.unlink(path)  # as a failing holder would, between our open and our flock
        return handle

    monkeypatch.setattr(lock, "open", opening, raising=False)
    with hold_folder(tmp_path):
        locked = os.stat(tmp_path / LOCK_NAME).st_ino
        assert opened and opened[0].closed  # the orphan was let go
        assert f"pid {os.getpid()}" in (tmp_path / LOCK_NAME).read_text()
    assert locked == os.stat(tmp_path / LOCK_NAME).st_ino


def test_a_train_started_mid_run_fails_and_the_lock_dies_with_its_holder(tmp_path):
    run_dir = tmp_path / "run"
    first = subprocess.Popen(
        _train_command(run_dir, 100_000), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 240
        while len(_logged_steps(run_dir)) < 2:
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "the first run logged nothing in 240 s"
            time.sleep(0.5)
        second = subprocess.run(_train_command(run_dir, 20), capture_output=True, text=True, timeout=240)
        assert second.returncode == 2, second.stderr
        assert "in use by another run" in second.stderr and f"pid {first.pid}" in second.stderr
        assert "Traceback" not in second.stderr
        # The first writer was not disturbed: its log still grows, step by step, once each.
        before = len(_logged_steps(run_dir))
        while len(_logged_steps(run_dir)) <= before:
            assert first.poll() is None, first.stderr.read()
            time.sleep(0.5)
        steps = _logged_steps(run_dir)
        assert steps == sorted(set(steps))
    finally:
        first.send_signal(signal.SIGKILL)
        first.communicate(timeout=60)
    # A killed holder leaves no stale lock: the folder can be taken at once.
    with hold_folder(run_dir):
        pass


def test_two_trains_started_together_one_runs_and_one_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    processes = [
        subprocess.Popen(
            _train_command(run_dir, 6), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in processes]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    refused = next(err for code, err in results if code == 2)
    assert "in use by another run" in refused
    assert _logged_steps(run_dir) == sorted(set(_logged_steps(run_dir)))
    assert (run_dir / "metrics.json").exists()


def test_a_sweep_folder_in_use_is_refused_before_any_run(tmp_path, capsys):
    from mixnerf_eqx.cli.sweep import main as sweep_main

    out = tmp_path / "sweep"
    out.mkdir()
    with hold_folder(out, "sweep", "--out"):
        code = sweep_main(
            [
                "--config",
                str(_REPO / "configs" / "builtin.toml"),
                "--out",
                str(out),
                "--no-progress",
                *TINY_OVERRIDES,
            ]
        )
    assert code == 2
    err = capsys.readouterr().err
    assert "in use by another sweep" in err and "--out" in err
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


def test_a_failed_train_leaves_no_empty_run_folder(tmp_path):
    # The scene's files are missing: the run fails after its folder was made, while loading.
    run_dir = tmp_path / "never"
    command = [
        sys.executable,
        "-m",
        "mixnerf_eqx.train",
        "--config",
        str(_REPO / "configs" / "llff3.toml"),
        "--run-dir",
        str(run_dir),
        "--data-dir",
        str(tmp_path / "no_data"),
        "--no-progress",
    ]
    failed = subprocess.run(command, capture_output=True, text=True, timeout=240)
    assert failed.returncode == 2, failed.stderr
    assert "Traceback" not in failed.stderr
    assert not run_dir.exists(), sorted(p.name for p in run_dir.iterdir())
