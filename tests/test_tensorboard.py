"""`train.log_to = ["jsonl", "tensorboard"]`: the event files hold what the JSONL holds.

The event files are read back here with a reader of their own (TFRecord framing, then
tensorboardX's `Event` protocol buffer), not with the writer's code.
"""

import dataclasses
import json
import shutil
import struct

import numpy as np
import pytest

import mixnerf_eqx as mx

pytest.importorskip("tensorboardX")
from tensorboardX.proto import event_pb2  # noqa: E402


def read_events(folder):
    """Every `(tag, step, value)` scalar and `(tag, step, height, width)` image in the event
    files of `folder`, read as TensorBoard reads them: a session that starts at step `s`
    (a resumed run's `purge_step`) discards what came before it from step `s` on."""
    scalars, images = [], []
    for path in sorted(folder.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime_ns):
        data = path.read_bytes()
        offset = 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset : offset + 8])
            record = data[offset + 12 : offset + 12 + length]
            offset += 12 + length + 4  # length, its CRC, the record, its CRC
            event = event_pb2.Event.FromString(record)
            if event.HasField("session_log") and event.session_log.status == event.session_log.START:
                scalars = [item for item in scalars if item[1] < event.step]
                images = [item for item in images if item[1] < event.step]
            for value in event.summary.value:
                if value.HasField("image"):
                    images.append((value.tag, event.step, value.image.height, value.image.width))
                else:
                    scalars.append((value.tag, event.step, value.simple_value))
    return scalars, images


def _expected_scalars(run_dir):
    """The scalars of `run_dir`'s JSONL, as the event files should hold them."""
    expected = {}
    for line in (run_dir / "train_log.jsonl").read_text().splitlines():
        entry = json.loads(line)
        if "eval" in entry:
            for name, value in entry["eval"].items():
                if value is not None:
                    expected[f"val/{name}", entry["step"]] = value
        else:
            for name, value in entry.items():
                if name != "step" and isinstance(value, (int, float)) and np.isfinite(value):
                    expected[f"train/{name}", entry["step"]] = value
    return expected


def _logged_config(run_dir, *overrides):
    """The tiny config, six steps, logging to TensorBoard too, in `run_dir`."""
    from helpers import TINY_OVERRIDES

    base = [*TINY_OVERRIDES, 'train.log_to=["jsonl", "tensorboard"]', "train.max_steps=6"]
    return mx.load_config("builtin", [*base, *overrides, f'train.run_dir="{run_dir}"'])


def _assert_the_events_mirror_the_log(run_dir):
    """The event files of `run_dir` hold each scalar of its JSONL once, at its step, and nothing
    else; returns them."""
    scalars, _ = read_events(run_dir / "tensorboard")
    got = {(tag, step): value for tag, step, value in scalars}
    assert len(got) == len(scalars)  # one value per tag and step
    expected = _expected_scalars(run_dir)
    assert set(got) == set(expected)
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, rel=1e-6, abs=1e-30), key
    return got


@pytest.fixture(scope="module")
def logged_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("tb") / "run"
    config = _logged_config(run_dir, "train.eval_every=3", "train.num_eval_views=1")
    mx.fit(config, progress=False, write_renders=False, log_every=2)
    return run_dir


def test_the_event_files_hold_every_logged_scalar(logged_run):
    got = _assert_the_events_mirror_the_log(logged_run)
    assert {"train/loss", "train/psnr", "train/lr", "train/nll_colour", "val/psnr"} <= {t for t, _ in got}


def test_a_resumed_run_purges_the_events_past_its_checkpoint(tmp_path):
    """A run killed after its last checkpoint redoes the steps after it: the JSONL drops their
    entries and the event files, read as TensorBoard reads them, hold each step once."""
    run_dir = tmp_path / "run"
    config = _logged_config(run_dir, "train.checkpoint_every=2")
    mx.fit(config, progress=False, write_renders=False, log_every=1)
    # The kill: the newest checkpoint (step 6) never made it to disk.
    shutil.rmtree(run_dir / "checkpoints" / "step_00000006")
    mx.fit(config, progress=False, write_renders=False, log_every=1)
    assert len(list((run_dir / "tensorboard").glob("events.out.tfevents.*"))) == 2
    got = _assert_the_events_mirror_the_log(run_dir)
    assert {step for tag, step in got if tag == "train/loss"} == set(range(1, 7))


def test_a_missing_tensorboardx_stops_the_run_before_it_starts(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name: None if name == "tensorboardX" else real(name)
    )
    config = _logged_config(tmp_path / "r")
    with pytest.raises(mx.ConfigError, match=r"pip install 'mixnerf_eqx\[tensorboard\]'"):
        mx.fit(config, progress=False)
    assert not (tmp_path / "r").exists()


def test_each_evaluation_writes_its_images(logged_run):
    _, images = read_events(logged_run / "tensorboard")
    found = {(tag, step): (height, width) for tag, step, height, width in images}
    names = ("val/colour", "val/depth", "val/error", "val/colour_spread")
    assert set(found) == {(name, step) for name in names for step in (3,)}
    assert set(found.values()) == {(32, 32)}


def test_the_jsonl_stays_required():
    with pytest.raises(mx.ConfigError, match='train.log_to must hold "jsonl"'):
        mx.load_config("builtin", ['train.log_to=["tensorboard"]'])
    config = mx.load_config("builtin")
    assert config.train.log_to == ("jsonl",)
    assert dataclasses.replace(config.train, log_to=("jsonl", "tensorboard")).log_to[1] == "tensorboard"


def test_a_sweep_writes_one_tensorboard_run_per_scene_and_seed(tmp_path):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx.cli import sweep

    overrides = [o for o in TINY_OVERRIDES if not o.startswith("train.max_steps")]
    overrides += ["train.max_steps=4", "data.num_test_views=1", 'train.log_to=["jsonl", "tensorboard"]']
    arguments = ["--config", "builtin", "--seeds", "0,1", "--out", str(tmp_path), "--no-progress"]
    assert sweep.main([*arguments, *overrides]) == 0
    folders = sorted(path.parent.relative_to(tmp_path) for path in tmp_path.rglob("events.out.tfevents.*"))
    assert [str(folder) for folder in folders] == ["builtin/seed_0/tensorboard", "builtin/seed_1/tensorboard"]
    for folder in folders:
        scalars, _ = read_events(tmp_path / folder)
        assert {step for tag, step, _ in scalars if tag == "train/loss"} == {4}
