"""The web viewer: the browser camera's rays against the views' own, the preview renders and
their compilations, the server's frustums, pause and shutdown, and (where Chromium is
installed) a real browser drawing a frame and switching to depth."""

import contextlib
import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx._inference import rendering
from mixnerf_eqx._inference.viewer import (
    MODES,
    PREVIEW_WIDTHS,
    Viewer,
    ViewerCamera,
    camera_of_view,
    preview_image,
    scene_facing,
    viewer_rays,
)
from mixnerf_eqx._util.images import to_uint8
from mixnerf_eqx.data import rays_for_views

pytest.importorskip("viser")

REPO = Path(__file__).resolve().parents[1]
FIELDS = ("origins", "directions", "viewdirs", "radii", "near", "far")


def _forward_facing(scene):
    """`scene` as a forward-facing (NDC) scene: cameras near the origin looking along -z."""
    poses = np.tile(np.eye(4, dtype=np.float32)[:3], (scene.train.num_views, 1, 1))
    angles = np.linspace(-0.1, 0.1, scene.train.num_views)
    poses[:, 0, 0], poses[:, 0, 2] = np.cos(angles), np.sin(angles)
    poses[:, 2, 0], poses[:, 2, 2] = -np.sin(angles), np.cos(angles)
    poses[:, :, 3] = np.stack([angles, 0.5 * angles, 0.1 * angles], axis=-1)
    train = dataclasses.replace(scene.train, camtoworlds=poses, ndc=True)
    return dataclasses.replace(scene, train=train, near=0.0, far=1.0)


@pytest.mark.parametrize("space", ["world", "ndc"])
def test_a_training_camera_through_the_viewer_gives_the_views_own_rays(tiny_scene, space):
    """The one conversion (viser's OpenCV camera -> this project's rays), both ways: a view's
    camera handed to the browser and back gives exactly that view's rays."""
    scene = tiny_scene if space == "world" else _forward_facing(tiny_scene)
    views = scene.train
    for index in range(views.num_views):
        camera = camera_of_view(views, index)
        again = ViewerCamera.from_wxyz(camera.wxyz, camera.position, camera.fov, camera.aspect)
        np.testing.assert_allclose(again.rotation, camera.rotation, atol=1e-6)  # float32 poses
        ours = viewer_rays(again, views.width, scene)
        theirs = rays_for_views(views.select([index]), scene.near, scene.far)
        assert ours.batch_shape == (views.height, views.width)
        for name in FIELDS:
            np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name)[0], rtol=1e-5, atol=1e-6)
    # OpenCV looks along +z with y down: the view's -z axis is the browser camera's +z axis.
    pose = np.asarray(views.camtoworlds[0], np.float64)
    np.testing.assert_allclose(camera_of_view(views, 0).rotation[:, 2], -pose[:3, 2], atol=1e-7)


def test_a_wider_viewer_camera_maps_its_rays_into_the_scenes_own_ndc_space(tiny_scene):
    """NDC is the training cameras' projection: a browser camera with another field of view
    puts each ray's origin where the training projection maps the ray's point on the near
    plane (a float64 reference written out here), not where its own projection would."""
    scene = _forward_facing(tiny_scene)
    views = scene.train
    camera = dataclasses.replace(camera_of_view(views, 1), fov=1.5 * camera_of_view(views, 1).fov)
    rays = viewer_rays(camera, 32, scene)
    height, width = camera.size(32)
    focal = 0.5 * height / np.tan(0.5 * camera.fov)
    rows, cols = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    local = np.stack([(cols - 0.5 * width) / focal, -(rows - 0.5 * height) / focal, -np.ones_like(rows)], -1)
    pose = camera.camtoworld()
    directions = local @ pose[:, :3].T
    origin = pose[:, 3]
    near_points = origin + ((-1.0 - origin[2]) / directions[..., 2])[..., None] * directions
    scale = np.array([-2.0 * views.focal / views.width, -2.0 * views.focal / views.height])
    want = scale * near_points[..., :2] / near_points[..., 2:3]
    np.testing.assert_allclose(np.asarray(rays.origins)[..., :2], want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(rays.origins)[..., 2], -1.0)


class _Camera:
    def __init__(self, camera):
        self.wxyz, self.position, self.fov, self.aspect = (
            camera.wxyz,
            camera.position,
            camera.fov,
            camera.aspect,
        )


class _Handle:
    """A stand-in for a scene node or a panel element of one client."""

    def __init__(self, **fields):
        self.visible, self.content, self.clicked = True, "", None
        self.__dict__.update(fields)

    def on_click(self, callback):
        self.clicked = callback


class _Client:
    """A stand-in for a browser: a camera the viewer reads, the widths of the frames sent, and
    its own frustums and status line."""

    def __init__(self, camera, client_id=1):
        self.client_id, self.camera, self.widths, self.frustums = client_id, _Camera(camera), [], []

        def add_frustum(_, name, **fields):
            self.frustums.append(_Handle(name=name, **fields))
            return self.frustums[-1]

        methods = {
            "set_background_image": lambda _, image, **kw: self.widths.append(image.shape[1]),
            "add_camera_frustum": add_frustum,
        }
        self.scene = type("Scene", (), methods)()
        self.gui = type("Gui", (), {"add_markdown": lambda _, content: _Handle(content=content)})()

    def atomic(self):
        return contextlib.nullcontext()


def _frames(client, count, timeout=120):
    deadline = time.monotonic() + timeout
    while len(client.widths) < count and time.monotonic() < deadline:
        time.sleep(0.02)
    return list(client.widths)


def test_frames_refine_while_training_updates_the_model(tiny_config, tiny_scene):
    """Parameters that change every step do not hold the picture at the coarsest width: the
    frame in progress refines with the newest model, and restarts once per refresh interval."""
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    viewer = Viewer(model, tiny_scene, port=0, training=True, max_width=128, refresh_s=0.5)
    stop = threading.Event()

    def training():
        while not stop.is_set():
            viewer.update(model, 0)
            time.sleep(0.01)

    trainer = threading.Thread(target=training, daemon=True)
    try:
        trainer.start()
        client = _Client(camera_of_view(tiny_scene.train, 0))
        viewer._connect(client)
        widths = _frames(client, 6)
        assert 128 in widths and widths[:2] == [64, 128], widths
    finally:
        stop.set()
        viewer.stop()


def test_a_frame_that_fails_is_reported_and_the_next_one_is_drawn(tiny_config, tiny_scene):
    """A spread asked of a model without a mixture (the panel offers it while training MixNeRF;
    here forced) says why in the status line; the client's frames go on."""
    baseline = dataclasses.replace(mx.training.init_train_state(tiny_config, tiny_scene).model, mixture=None)
    viewer = Viewer(baseline, tiny_scene, port=0, max_width=64, mixture=True)
    try:
        client = _Client(camera_of_view(tiny_scene.train, 0))
        viewer._connect(client)
        assert _frames(client, 1) == [64]
        viewer.mode.value = "colour spread"
        deadline = time.monotonic() + 60
        status = viewer.clients[client.client_id].status
        while "cannot show" not in status.content and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "cannot show colour spread: 'colour spread' needs a MixNeRF model" in status.content
        viewer.mode.value = "depth"
        assert _frames(client, 2) == [64, 64]
        assert all(thread.is_alive() for thread in viewer._threads)
    finally:
        viewer.stop()


def test_a_preview_of_a_training_camera_is_the_render_of_that_view(tiny_config, tiny_scene):
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    views = tiny_scene.test
    rays = viewer_rays(camera_of_view(views, 1), views.width, tiny_scene)
    want = mx.render_views(model, views.select([1]), tiny_scene.near, tiny_scene.far)
    colour = preview_image(model, rays, "colour", tiny_scene.near, tiny_scene.far)
    assert colour.shape == (views.height, views.width, 3) and colour.dtype == np.uint8
    # The same rays in other chunks: equal up to a quantisation step where a sum rounds apart.
    assert np.abs(colour.astype(int) - to_uint8(want.rgb[0]).astype(int)).max() <= 1
    opacity = preview_image(model, rays, "opacity", tiny_scene.near, tiny_scene.far)
    assert np.abs(opacity[..., 0].astype(int) - to_uint8(want.acc[0]).astype(int)).max() <= 1


def test_a_preview_that_skips_is_the_skipping_render_and_the_spreads_stay_dense(tiny_config, tiny_scene):
    import jax

    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    views = tiny_scene.test
    rays = viewer_rays(camera_of_view(views, 0), views.width, tiny_scene)
    flat = rays.reshape(-1)
    occupancy = dataclasses.replace(tiny_config.occupancy, resolution=16, choose_threshold=False)
    grid, _ = mx.runs.grid_for_rendering(occupancy, tiny_scene, model, key=jax.random.key(0))
    # A threshold between the cells' densities: some cells are skipped, some kept.
    grid = eqx.tree_at(lambda g: g.threshold, grid, np.float32(np.median(np.asarray(grid.density))))
    skipping = mx.runs.make_skipping(occupancy, grid)
    modes = (("colour", lambda r: r.rgb), ("opacity", lambda r: np.repeat(r.acc[..., None], 3, -1)))
    for mode, read in modes:
        want = read(mx.inference.render_rays(model, flat, 2048, skipping=skipping))
        dense = read(mx.inference.render_rays(model, flat, 2048))
        image = preview_image(model, rays, mode, tiny_scene.near, tiny_scene.far, skipping=skipping)
        expected = to_uint8(want.reshape(views.height, views.width, 3)).astype(int)
        assert np.abs(image.astype(int) - expected).max() <= 1
        # The grid skips something the dense render does not (so the comparison above can fail).
        assert np.abs(to_uint8(dense.reshape(views.height, views.width, 3)).astype(int) - expected).max() > 1
    # The spread modes read the whole mixture: the same image with or without skipping.
    near, far = tiny_scene.near, tiny_scene.far
    spread = preview_image(model, rays, "colour spread", near, far)
    assert np.array_equal(spread, preview_image(model, rays, "colour spread", near, far, skipping=skipping))
    viewer = Viewer(model, tiny_scene, port=0, max_width=64, skipping=skipping)
    try:
        assert viewer.render(camera_of_view(views, 0), 64, "colour").shape == (64, 64, 3)
        with pytest.raises(ValueError, match="a viewer that follows training renders densely"):
            viewer.update(model, step=1)
    finally:
        viewer.stop()
    for model_given, training in ((None, False), (model, True)):
        with pytest.raises(ValueError, match="skipping needs the trained model its grid was built from"):
            Viewer(model_given, tiny_scene, port=0, training=training, skipping=skipping)


def test_moving_the_camera_compiles_nothing_new(tiny_config, tiny_scene, monkeypatch):
    """Preview widths, window shapes and camera poses all reuse one compiled dense render."""
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    once = eqx.filter_jit(eqx.debug.assert_max_traces(lambda m, rays: m(rays).fine, max_traces=1))
    monkeypatch.setattr(rendering, "_render_dense", once)
    camera = camera_of_view(tiny_scene.train, 0)
    for step, width in enumerate(PREVIEW_WIDTHS[:3]):
        for aspect in (1.0, 1.5, 0.75):
            moved = dataclasses.replace(camera, position=camera.position + 0.05 * step, aspect=aspect)
            for mode in ("colour", "depth"):
                image = preview_image(model, viewer_rays(moved, width, tiny_scene), mode, 2.0, 6.0)
                assert image.shape == (max(2, round(width / aspect)), width, 3)
    for mode in ("colour spread", "depth spread"):
        image = preview_image(model, viewer_rays(camera, 64, tiny_scene), mode, 2.0, 6.0)
        assert image.shape == (64, 64, 3) and image.std() > 0
    with pytest.raises(ValueError, match="mode must be one of"):
        preview_image(model, viewer_rays(camera, 64, tiny_scene), "normals", 2.0, 6.0)


def test_interval_modes_show_the_recalibrated_90_percent_interval(tiny_config, tiny_scene):
    from mixnerf_eqx._predictive.recalibration import Recalibration

    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    rays = viewer_rays(camera_of_view(tiny_scene.test, 0), 32, tiny_scene)
    own = Recalibration.raw((0.5, 0.8, 0.9, 0.95))

    def moved(row):
        # An untrained model's intervals are wide (its colour ones beyond the colour scale's
        # top): a 2% central interval in one row stands for a recalibration that narrows it.
        lower, upper = own.colour_lower.copy(), own.colour_upper.copy()
        depth_lower, depth_upper = own.depth_lower.copy(), own.depth_upper.copy()
        lower[row], upper[row], depth_lower[row], depth_upper[row] = 0.49, 0.51, 0.49, 0.51
        return dataclasses.replace(
            own, colour_lower=lower, colour_upper=upper, depth_lower=depth_lower, depth_upper=depth_upper
        )

    for mode in ("colour 90% interval", "depth 90% interval"):
        default = preview_image(model, rays, mode, tiny_scene.near, tiny_scene.far)
        assert default.shape == (32, 32, 3)
        show = lambda recalibration: preview_image(  # noqa: E731
            model, rays, mode, tiny_scene.near, tiny_scene.far, None, recalibration
        )
        assert np.array_equal(default, show(own))
        assert np.array_equal(default, show(moved(0)))  # the 50% row: not what is shown
        assert not np.array_equal(default, show(moved(2)))  # the 90% row


def test_the_server_shows_every_camera_renders_and_stops(tiny_config, tiny_scene):
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    viewer = Viewer(model, tiny_scene, port=0, max_width=128)
    try:
        assert viewer.url.startswith("http://127.0.0.1:")
        assert len(viewer.cameras) == tiny_scene.train.num_views + tiny_scene.test.num_views
        assert tuple(viewer.mode.options) == MODES and viewer.widths == (64, 128)
        image = viewer.render(camera_of_view(tiny_scene.test, 0), 128, "depth")
        assert image.shape == (128, 128, 3) and image.std() > 0
    finally:
        viewer.stop()
    baseline = dataclasses.replace(model, mixture=None)
    viewer = Viewer(baseline, tiny_scene, port=0)
    try:
        assert "colour spread" not in viewer.mode.options  # the baseline has no mixture
    finally:
        viewer.stop()
    with pytest.raises(ValueError, match="max_width must be one of"):
        Viewer(model, tiny_scene, port=0, max_width=100)


def test_pause_holds_training_between_steps_until_unticked(tiny_config, tiny_scene):
    viewer = Viewer(None, tiny_scene, port=0, training=True)
    seen = []
    try:
        viewer.paused.value = True

        def on_step(state):
            seen.append(int(state.step))
            viewer.update(state.model, state.step)
            viewer.wait_while_paused()

        config = dataclasses.replace(tiny_config, train=dataclasses.replace(tiny_config.train, max_steps=3))
        arguments = dict(dataset=tiny_scene, progress=False, on_step=on_step)
        worker = threading.Thread(target=mx.fit, args=(config,), kwargs=arguments)
        worker.start()
        deadline = time.monotonic() + 120
        while not seen and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        assert seen == [0]  # paused before the first step
        viewer.paused.value = False
        worker.join(timeout=300)
        assert not worker.is_alive() and seen == [0, 1, 2, 3]
    finally:
        viewer.stop()


def _trained_run(tiny_config, tiny_scene, steps=60):
    # A small grid for `view --skipping on` (it changes nothing in training).
    config = dataclasses.replace(
        tiny_config,
        train=dataclasses.replace(tiny_config.train, max_steps=steps),
        occupancy=dataclasses.replace(tiny_config.occupancy, resolution=16),
    )
    mx.fit(config, dataset=tiny_scene, progress=False, write_renders=False)
    return Path(config.train.run_dir)


def test_the_view_command_prints_its_address_and_stops_on_ctrl_c(tiny_config, tiny_scene, tmp_path):
    run_dir = _trained_run(tiny_config, tiny_scene, steps=2)
    # As a terminal starts it: Ctrl-C raises KeyboardInterrupt (a runner started in the
    # background may hand SIGINT on ignored).
    program = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from mixnerf_eqx.cli.view import main; sys.exit(main(sys.argv[1:]))"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", program, str(run_dir), "--port", "0", "--max-width", "64", "--skipping", "on"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines = []
        while not any("viewer of" in line for line in lines) and process.poll() is None:
            lines.append(process.stdout.readline())  # viser's banner, then the command's line
        assert any("viewer of" in line and "http://127.0.0.1:" in line for line in lines), lines
        # The interval modes show conformal intervals fitted on the scene's validation views.
        assert any("interval modes: conformal intervals fitted on the 4 validation views" in line for line in lines)
        # --skipping on: a grid built from the checkpoint, its threshold chosen on validation pixels.
        skipping = [line for line in lines if line.startswith("skipping: density threshold")]
        assert skipping and "validation pixels" in skipping[0]
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130 and "viewer stopped" in err


@pytest.mark.browser
def test_a_browser_draws_a_frame_and_switching_to_depth_changes_it(tiny_config, tiny_scene, tmp_path):
    """Headless Chromium opens the viewer, a frame is drawn, and choosing depth in the panel
    changes the picture. `MIXNERF_VIEWER_RUN` (a run folder) and `MIXNERF_VIEWER_SCREENSHOT`
    (a PNG path) make the README's screenshot from a real run."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("Chromium is not installed (.ci/run installs Debian's chromium)")
    sync_playwright = pytest.importorskip("playwright.sync_api").sync_playwright
    from PIL import Image

    run_dir = os.environ.get("MIXNERF_VIEWER_RUN") or _trained_run(tiny_config, tiny_scene)
    run = mx.runs.restore_run(run_dir, dataset=None if os.environ.get("MIXNERF_VIEWER_RUN") else tiny_scene)
    viewer = Viewer(run.model, run.dataset, port=0, max_width=256)
    shots = {}
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=chromium,
                args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"],
            )
            page = browser.new_page(viewport={"width": 960, "height": 640})
            page.goto(viewer.url)
            for mode in ("colour", "depth"):
                if mode == "depth":
                    page.locator("input[role=combobox][value=colour]").click()
                    page.get_by_role("option", name="depth", exact=True).click()
                drawn = viewer.frames
                deadline = time.monotonic() + 120
                while (viewer.mode.value != mode or viewer.frames < drawn + len(viewer.widths)) and (
                    time.monotonic() < deadline
                ):
                    time.sleep(0.1)
                time.sleep(1.5)  # the last frame reaches the page
                path = tmp_path / f"{mode}.png"
                page.screenshot(path=path)
                shots[mode] = np.asarray(Image.open(path).convert("RGB"), np.float64)
            browser.close()
    finally:
        viewer.stop()
    assert viewer.mode.value == "depth"
    assert shots["colour"].std() > 10, "the page is blank"
    assert np.abs(shots["colour"] - shots["depth"]).mean() > 5, "switching to depth changed nothing"
    if os.environ.get("MIXNERF_VIEWER_SCREENSHOT"):
        shutil.copy(tmp_path / "colour.png", os.environ["MIXNERF_VIEWER_SCREENSHOT"])


def test_train_with_the_viewer_serves_while_it_trains_and_stops_after(tmp_path, capsys):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx.cli import train as train_cli

    overrides = [o for o in TINY_OVERRIDES if not o.startswith("train.max_steps")] + ["train.max_steps=3"]
    arguments = ["--config", "builtin", "--run-dir", str(tmp_path / "run"), "--no-progress", *overrides]
    assert train_cli.main([*arguments, "--viewer", "--viewer-port", "0"]) == 0
    out = capsys.readouterr().out
    assert "viewer: http://127.0.0.1:" in out and "test metrics after 3 steps" in out
    # No browser connected: the run is not slowed by frames nobody asked for.
    assert not [thread for thread in threading.enumerate() if thread.name.startswith("viewer-")]


def test_train_with_the_viewer_on_a_busy_folder_is_refused_before_any_server_starts(tmp_path, capsys):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx._util.lock import hold_folder
    from mixnerf_eqx.cli import train as train_cli

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    arguments = ["--config", "builtin", "--run-dir", str(run_dir), "--no-progress", *TINY_OVERRIDES]
    with hold_folder(run_dir):
        assert train_cli.main([*arguments, "--viewer", "--viewer-port", "0"]) == 2
    captured = capsys.readouterr()
    assert "in use by another run" in captured.err
    assert "viewer:" not in captured.out  # no URL printed for a server that never served
    assert not [thread for thread in threading.enumerate() if thread.name.startswith("viewer-")]


def test_a_camera_turned_away_from_a_forward_facing_scene_shows_nothing(tiny_config, tiny_scene):
    """NDC maps a ray heading away from the scene to a mirrored point on the near plane: those
    pixels are left black instead of showing a mirrored picture. Turned half way, the pixels
    looking into the scene are drawn as before."""
    scene = _forward_facing(tiny_scene)
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    camera = camera_of_view(scene.train, 0)
    assert scene_facing(camera, 32, scene).all()
    assert scene_facing(camera, 32, tiny_scene) is None  # world space: every ray is in the scene

    def turned(angle):
        c, s = np.cos(angle), np.sin(angle)
        about_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        return dataclasses.replace(camera, rotation=about_y @ camera.rotation)

    assert not scene_facing(turned(np.pi), 32, scene).any()
    half = scene_facing(turned(0.5 * np.pi), 32, scene)
    # Turned a quarter turn about the vertical axis: the columns on one side still look in.
    assert half.any() and not half.all()
    assert (half == half[:1]).all()  # whole columns
    for mode in ("colour", "depth", "opacity"):
        away = preview_image(model, viewer_rays(turned(np.pi), 32, scene), mode, 0.0, 1.0, visible=None)
        hidden = preview_image(
            model,
            viewer_rays(turned(np.pi), 32, scene),
            mode,
            0.0,
            1.0,
            scene_facing(turned(np.pi), 32, scene),
        )
        assert (hidden == 0).all() and away.std() > 0  # without the mask: a (mirrored) picture
        part = preview_image(model, viewer_rays(turned(0.5 * np.pi), 32, scene), mode, 0.0, 1.0, half)
        assert (part[~half] == 0).all()


def test_each_browser_has_its_own_frustums_hidden_frustum_and_status(tiny_config, tiny_scene):
    """Two browsers: a jump hides the frustum it lands in for the browser that jumped only,
    and moving away shows it again; each status line speaks of its own frames."""
    model = mx.training.init_train_state(tiny_config, tiny_scene).model
    viewer = Viewer(model, tiny_scene, port=0, max_width=64)
    try:
        first = _Client(camera_of_view(tiny_scene.train, 0), client_id=1)
        second = _Client(camera_of_view(tiny_scene.train, 0), client_id=2)
        viewer._connect(first)
        viewer._connect(second)
        count = tiny_scene.train.num_views + tiny_scene.test.num_views
        assert len(first.frustums) == len(second.frustums) == count
        assert _frames(first, 1) == [64] and _frames(second, 1) == [64]
        # Each starts at the first training view, its own frustum there hidden.
        assert not first.frustums[0].visible and not second.frustums[0].visible
        test_view = tiny_scene.train.num_views  # the first test view's frustum
        viewer.move_camera(first, camera_of_view(tiny_scene.test, 0), first.frustums[test_view])
        assert not first.frustums[test_view].visible and first.frustums[0].visible
        assert second.frustums[test_view].visible and not second.frustums[0].visible
        # The first browser's camera moves away from the frustum it jumped to: shown again.
        first.camera.position = first.camera.position + 10 * viewer.frustum_scale
        deadline = time.monotonic() + 60
        while not first.frustums[test_view].visible and time.monotonic() < deadline:
            time.sleep(0.02)
        assert first.frustums[test_view].visible and not second.frustums[0].visible
        status = {c.client_id: viewer.clients[c.client_id].status for c in (first, second)}
        assert status[1] is not status[2] and "64 px wide" in status[2].content
        # A click that arrives for a browser not (or no longer) connected hides nothing.
        stranger = _Client(camera_of_view(tiny_scene.train, 0), client_id=3)
        viewer.move_camera(stranger, camera_of_view(tiny_scene.test, 0), first.frustums[test_view])
        assert first.frustums[test_view].visible
    finally:
        viewer.stop()


@pytest.mark.parametrize(
    ("host", "message"),
    [
        ("8.8.8.8", "--host 8.8.8.8 is not an address of this machine"),
        ("999.1.1.1", "--host 999.1.1.1 is not an address or a known host name"),
    ],
)
def test_a_host_this_machine_cannot_serve_on_is_refused_at_once(host, message):
    # A server bound to another machine's address used to wait silently (binding here sends
    # nothing over the network).
    from mixnerf_eqx.cli.view import check_host

    with pytest.raises(ValueError, match=message):
        check_host(host)
    check_host("127.0.0.1")
