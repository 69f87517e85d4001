"""`benchmarks/calibration.py`'s cost split: the colour quantile solve is timed on the chunks
the predictive pass itself solves, and `--cost-only` refuses what it cannot do."""

import sys
from pathlib import Path

import numpy as np
import pytest

import mixnerf_eqx._predictive.uncertainty as pass_module

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import calibration  # noqa: E402


def _recording(calls, original):
    def record(fn, rays, chunk, extra=None):
        parts, count = original(fn, rays, chunk, extra)
        calls.append((count, [int(np.shape(_part_leaf(part))[0]) for part in parts]))
        return parts, count

    return record


def _part_leaf(part):
    # A chunk's output: a summary dict (the pass) or a colour mixture (the timing).
    return part["colour_median"] if isinstance(part, dict) else part.location


def test_the_quantile_timing_solves_the_chunks_the_pass_solves(short_run, tiny_scene, monkeypatch):
    _, model = short_run
    views = tiny_scene.test.select([0, 1])
    chunk = 300  # not a divisor of a view's rays: the last chunk of each view is padded
    passes, timed = [], []
    monkeypatch.setattr(pass_module, "map_ray_chunks", _recording(passes, pass_module.map_ray_chunks))
    monkeypatch.setattr(calibration, "map_ray_chunks", _recording(timed, calibration.map_ray_chunks))
    pass_module.predict_views(model, views, tiny_scene.near, tiny_scene.far, chunk)
    seconds = calibration.colour_quantile_seconds(model, views, tiny_scene, chunk)
    rays_per_view = views.width * views.height
    assert passes == timed
    assert passes == [(rays_per_view, [chunk] * -(-rays_per_view // chunk))] * 2
    assert seconds > 0


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--cost-only"], "exactly one with --runs"),
        (["--cost-only", "--runs", "a", "b", "--tag", "t"], "exactly one with --runs"),
        (["--cost-only", "--runs", "a"], "needs a --tag"),
        (["--cost-only", "--runs", "a", "--tag", "t", "--no-time"], "cannot be combined with --no-time"),
    ],
)
def test_cost_only_refuses_what_it_cannot_do(arguments, message, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["calibration.py", *arguments])
    with pytest.raises(SystemExit) as raised:
        calibration.main()
    assert message in str(raised.value)
