"""Camera paths and the `render` command: the paths' geometry, the video's frames, and the
command line's errors and interruptions."""

import dataclasses
import json
import re
import subprocess

import imageio_ffmpeg
import numpy as np
import pytest
from helpers import TINY_OVERRIDES
from PIL import Image

import mixnerf_eqx as mx
from mixnerf_eqx._inference.camera_path import SPIRAL_FOCUS_DEPTH, camera_path, orbit_path, spiral_path
from mixnerf_eqx._inference.video import path_frames, render_video
from mixnerf_eqx._util.images import to_uint8
from mixnerf_eqx.cli import render
from mixnerf_eqx.data import procedural


def _check_rotations(poses):
    rotations = poses[:, :, :3]
    np.testing.assert_allclose(
        rotations.transpose(0, 2, 1) @ rotations, np.broadcast_to(np.eye(3), rotations.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)


def _distance_to_axis(poses, point):
    """How far `point` lies from each camera's optical axis (the line along its -z)."""
    axes = -poses[:, :, 2] / np.linalg.norm(poses[:, :, 2], axis=-1, keepdims=True)
    offsets = point - poses[:, :, 3]
    along = np.sum(offsets * axes, axis=-1)
    return np.linalg.norm(offsets - along[:, None] * axes, axis=-1), along


def test_the_orbit_circles_the_built_in_scene_where_its_cameras_look(tiny_scene):
    poses = np.concatenate([tiny_scene.train.camtoworlds, tiny_scene.test.camtoworlds]).astype(np.float64)
    path = orbit_path(poses, 36)
    _check_rotations(path)
    # The built-in scene's cameras look at LOOK_AT with z up: the orbit keeps their mean
    # distance from it and their mean elevation above it.
    look_at = procedural.LOOK_AT
    offsets = poses[:, :, 3] - look_at
    camera_distances = np.linalg.norm(offsets, axis=-1)
    distances = np.linalg.norm(path[:, :, 3] - look_at, axis=-1)
    np.testing.assert_allclose(distances, np.mean(camera_distances), rtol=1e-5)
    miss, ahead = _distance_to_axis(path, look_at)
    assert np.max(miss) < 1e-5 and np.all(ahead > 0)
    elevations = np.arcsin(offsets[:, 2] / camera_distances)
    path_elevations = np.arcsin((path[:, 2, 3] - look_at[2]) / distances)
    np.testing.assert_allclose(path_elevations, np.mean(elevations), atol=1e-5)
    # No roll: every frame's x axis is horizontal.
    np.testing.assert_allclose(path[:, 2, 0], 0.0, atol=1e-9)
    azimuths = np.unwrap(np.arctan2(path[:, 1, 3], path[:, 0, 3]))
    np.testing.assert_allclose(np.abs(np.diff(azimuths)), 2 * np.pi / 36, atol=1e-3)
    first_camera_azimuth = np.arctan2(poses[0, 1, 3], poses[0, 0, 3])
    assert np.cos(azimuths[0] - first_camera_azimuth) > 1 - 1e-6


def test_the_spiral_stays_in_front_of_the_cameras_and_looks_at_one_point():
    # A forward-facing rig: cameras on the plane z = 0 at offsets up to 0.3 (x) and 0.2 (y),
    # looking along -z; the average camera is the identity.
    rng = np.random.default_rng(0)
    positions = np.column_stack(
        [rng.uniform(-0.3, 0.3, 20), rng.uniform(-0.2, 0.2, 20), rng.uniform(-0.05, 0.05, 20)]
    )
    positions -= positions.mean(axis=0)
    poses = np.concatenate([np.broadcast_to(np.eye(3), (20, 3, 3)), positions[:, :, None]], axis=2)
    path = spiral_path(poses, 120)
    _check_rotations(path)
    focus = np.array([0.0, 0.0, -SPIRAL_FOCUS_DEPTH])
    miss, ahead = _distance_to_axis(path, focus)
    assert np.max(miss) < 1e-9 and np.all(ahead > 0)
    radii = np.percentile(np.abs(positions), 90, axis=0)
    spread = np.abs(path[:, :, 3])
    assert np.all(spread <= radii + 1e-9)
    # The loop reaches its radius along every axis and comes back to where it began.
    np.testing.assert_allclose(spread.max(axis=0), radii, rtol=0.01)
    np.testing.assert_allclose(path[0, :, 3], [radii[0], 0.0, 0.0], atol=1e-12)


def test_the_path_follows_the_kind_of_scene(tiny_scene):
    orbit = camera_path(tiny_scene, "auto", 8)
    np.testing.assert_array_equal(orbit, camera_path(tiny_scene, "orbit", 8))
    forward = dataclasses.replace(tiny_scene, train=dataclasses.replace(tiny_scene.train, ndc=True))
    np.testing.assert_array_equal(camera_path(forward, "auto", 8), camera_path(forward, "spiral", 8))
    with pytest.raises(ValueError, match="at least one frame"):
        camera_path(tiny_scene, "orbit", 0)


def test_a_path_for_the_other_kind_of_scene_is_drawn_with_a_warning(tiny_scene):
    forward = dataclasses.replace(tiny_scene, train=dataclasses.replace(tiny_scene.train, ndc=True))
    with pytest.warns(mx.config.SettingWarning, match="a spiral through a 360-degree scene"):
        spiral = camera_path(tiny_scene, "spiral", 8)
    with pytest.warns(mx.config.SettingWarning, match="an orbit through a forward-facing scene"):
        orbit = camera_path(forward, "orbit", 8)
    assert spiral.shape == orbit.shape == (8, 3, 4)
    # The natural paths, asked for by name or by auto, draw no warning (warnings are errors here).
    camera_path(tiny_scene, "orbit", 8)
    camera_path(forward, "spiral", 8)


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    # A small grid for the skipping render, its threshold from the config (none chosen).
    overrides = [
        "occupancy.resolution=16",
        "occupancy.choose_threshold=false",
        "occupancy.density_threshold=0.5",
    ]
    config = mx.load_config("builtin", [*TINY_OVERRIDES, *overrides])
    run_dir = tmp_path_factory.mktemp("render") / "run"
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, run_dir=str(run_dir)))
    # 20 steps and a checkpoint, without the final evaluation: a video needs no scores.
    mx.fit(config, progress=False, write_renders=False, stop_after=20)
    return run_dir


def _video_frames(path):
    """The video's frame rate and size as the decoder reads them, and its frames decoded."""
    ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
    probe = subprocess.run([ffmpeg, "-hide_banner", "-i", str(path)], capture_output=True, text=True)
    stream = next(line for line in probe.stderr.splitlines() if "Video:" in line)
    width, height = (int(v) for v in re.search(r" (\d+)x(\d+)[ ,]", stream).groups())
    fps = float(re.search(r"([\d.]+) fps", stream).group(1))
    command = [ffmpeg, "-loglevel", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
    raw = subprocess.run(command, capture_output=True, check=True).stdout
    frames = np.frombuffer(raw, np.uint8).reshape(-1, height, width, 3)
    return {"fps": fps, "size": (width, height)}, frames


def test_render_writes_an_orbit_video_with_its_frames(trained_run, capsys):
    assert (
        render.main([str(trained_run), "--frames", "6", "--fps", "12", "--save-frames", "--no-progress"]) == 0
    )
    video = trained_run / "video" / "auto.mp4"
    summary = json.loads(video.with_suffix(".json").read_text())
    assert (summary["fps"], summary["num_frames"], summary["width"], summary["height"]) == (12, 6, 64, 32)
    assert summary["panels"] == ["colour", "depth"]
    meta, frames = _video_frames(video)
    assert meta["fps"] == 12 and tuple(meta["size"]) == (64, 32) and len(frames) == 6
    assert "6 frames at 12 fps, 64x32" in capsys.readouterr().out
    # The PNG frames are the renders, exactly; the video holds them up to its compression.
    pngs = sorted((trained_run / "video" / "auto_frames").glob("frame_*.png"))
    assert len(pngs) == 6
    run = mx.runs.restore_run(trained_run)
    _, rays_of = path_frames(run.dataset, "auto", 6)
    colour = to_uint8(mx.inference.render_rays(run.model, rays_of(0)).rgb[0])
    first = np.asarray(Image.open(pngs[0]))
    np.testing.assert_array_equal(first[:, :32], colour)
    assert np.mean(np.abs(frames[0].astype(float) - first)) < 4.0


def test_render_of_the_test_views_with_skipping(trained_run):
    out = trained_run / "elsewhere" / "test.mp4"
    assert (
        render.main(
            [str(trained_run), "--path", "test", "--skipping", "on", "--out", str(out), "--no-progress"]
        )
        == 0
    )
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["skipping"] and summary["num_frames"] == 3
    assert len(_video_frames(out)[1]) == 3


def test_a_spread_adds_a_third_panel(trained_run, tmp_path):
    run = mx.runs.restore_run(trained_run)
    video = render_video(
        run.model,
        run.dataset,
        tmp_path / "spread.mp4",
        num_frames=2,
        spread=lambda rays: np.zeros(rays.batch_shape),
    )
    assert (video.width, video.height, video.num_frames) == (96, 32, 2)


def test_ctrl_c_keeps_the_frames_so_far_as_a_partial_video(trained_run, tmp_path):
    run = mx.runs.restore_run(trained_run)

    def interrupt_after_two(done, total):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_video(run.model, run.dataset, tmp_path / "cut.mp4", num_frames=5, on_frame=interrupt_after_two)
    assert not (tmp_path / "cut.mp4").exists()
    assert imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "cut.partial.mp4"))[0] == 2


def test_uncertainty_panel_from_the_predictive_distribution(trained_run):
    pytest.importorskip("mixnerf_eqx._predictive.uncertainty")
    out = trained_run / "video" / "spread.mp4"
    assert (
        render.main([str(trained_run), "--frames", "2", "--uncertainty", "--out", str(out), "--no-progress"])
        == 0
    )
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["panels"] == ["colour", "depth", "colour spread"] and summary["width"] == 96


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--frames", "0"], "--frames must be a positive number"),
        (["--fps", "-1"], "--fps must be a number of frames per second in [0.1, 1000]"),
        (["--fps", "inf"], "--fps must be a number of frames per second in [0.1, 1000], got inf"),
        (["--fps", "1e-9"], "--fps must be a number of frames per second in [0.1, 1000], got 1e-09"),
        (["--out", "video.gif"], "--out must name an .mp4 file"),
    ],
)
def test_render_refuses_meaningless_arguments(trained_run, arguments, message, capsys):
    assert render.main([str(trained_run), *arguments]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("error: ") and message in error and "\n" not in error


@pytest.mark.parametrize("where", ["folder", "under_a_file"])
def test_a_video_destination_that_cannot_be_written_is_refused_before_loading(
    where, tmp_path, capsys, monkeypatch
):
    if where == "folder":
        out = tmp_path / "x.mp4"
        out.mkdir()
        message = f"the video {out} is an existing folder"
    else:
        (tmp_path / "plain").write_text("")
        out = tmp_path / "plain" / "deeper" / "x.mp4"
        message = f"{tmp_path / 'plain'} is a file, not a folder"

    def no_loading(*args, **kwargs):
        raise AssertionError("the run was loaded before the destination was checked")

    monkeypatch.setattr(render, "restore_run", no_loading)
    # The run folder is not even a run: the destination is what is checked first.
    assert render.main([str(tmp_path), "--out", str(out), "--no-progress"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("error: ") and message in error and "\n" not in error
    assert "partial" not in error


def test_render_of_a_folder_that_is_no_run_is_one_clear_error(tmp_path, capsys):
    assert render.main([str(tmp_path)]) == 2
    assert "is not a training run" in capsys.readouterr().err
