"""`benchmarks/calibration.py`'s cost split: the colour quantile solve is timed on the chunks
the predictive pass itself solves, and `--cost-only` refuses what it cannot do."""

import sys
from pathlib import Path

import numpy as np
import pytest

import mixnerf_eqx._predictive.uncertainty as pass_module

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import calibration  # noqa: E402


def test_the_quantile_timing_solves_the_chunks_the_pass_solves(short_run, tiny_scene, monkeypatch):
    _, model = short_run
    views = tiny_scene.test.select([0, 1])
    chunk = 300  # not a divisor of a view's rays: the last chunk of each view is padded
    solved = []
    original = pass_module.map_ray_chunks

    def recording(fn, rays, chunk, extra=None):
        parts, count = original(fn, rays, chunk, extra)
        solved.append([int(np.shape(part["colour_median"])[0]) for part in parts])
        return parts, count

    with monkeypatch.context() as patch:
        patch.setattr(pass_module, "map_ray_chunks", recording)
        pass_module.predict_views(model, views, tiny_scene.near, tiny_scene.far, chunk)
    timed = [
        [
            int(piece.location.shape[0])
            for piece in calibration.quantile_chunks(model, views.select([i]), tiny_scene, chunk)
        ]
        for i in range(views.num_views)
    ]
    rays_per_view = views.width * views.height
    assert solved == timed == [[chunk] * -(-rays_per_view // chunk)] * 2
    # Padding repeats the last ray's mixture, as the pass repeats the last ray.
    last = calibration.quantile_chunks(model, views.select([0]), tiny_scene, chunk)[-1]
    real = rays_per_view % chunk
    np.testing.assert_array_equal(
        np.asarray(last.location[real:]),
        np.repeat(np.asarray(last.location[real - 1 : real]), chunk - real, 0),
    )
    # A chunk larger than a view is cut to the view, as the pass cuts it.
    assert [
        int(piece.location.shape[0])
        for piece in calibration.quantile_chunks(model, views.select([0]), tiny_scene, 10**6)
    ] == [rays_per_view]
    assert calibration.colour_quantile_seconds(model, views, tiny_scene, chunk) > 0


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--cost-only"], "exactly one with --runs"),
        (["--cost-only", "--runs", "a", "b", "--tag", "t"], "exactly one with --runs"),
        (["--cost-only", "--runs", "a"], "needs a --tag"),
        (["--cost-only", "--runs", "a", "--tag", "t", "--no-time"], "cannot be combined with --no-time"),
    ],
)
def test_cost_only_refuses_what_it_cannot_do(arguments, message, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["calibration.py", *arguments])
    with pytest.raises(SystemExit) as raised:
        calibration.main()
    assert message in str(raised.value)
