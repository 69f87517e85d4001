"""What the web viewer renders: a browser camera's rays and one preview image per mode.

The browser (viser) gives a camera as a rotation `wxyz` and a `position` in OpenCV axes (x
right, y down, looking along +z), a vertical field of view and an aspect ratio. This project's
rays use OpenGL axes (y up, looking along -z, `mixnerf_eqx._nn.rays`), so the one conversion
is `R_opengl = R_opencv @ diag(1, -1, -1)`, made in `ViewerCamera.camtoworld` and nowhere
else. For forward-facing (NDC) scenes the rays are mapped into the scene's NDC space, the one
its training cameras define, whatever the viewer's field of view.

Previews come in a fixed set of widths (`PREVIEW_WIDTHS`) and are rendered in chunks of a
fixed size (`PREVIEW_CHUNK`, padding the smallest previews up to one chunk), so moving the
camera, resizing the window or refining a coarse frame never compiles anything new: the
dense render compiles once, the predictive pass once. A viewer of a trained model can skip empty
space and finished rays in the colour, depth and opacity previews (`Skipping`, with a grid
built from that model: `python -m mixnerf_eqx.view --skipping on`); the spread and interval
modes read the whole mixture and stay dense. With skipping, each level is one compiled program
too where `occupancy.render_chunk_points > 0` (the default); with 0 its buffers are sized on
the host, a compilation per size.
"""

import dataclasses
import math
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float

from .._nn.model import MixNeRF
from .._nn.rays import RayBundle, camera_rays
from .._predictive.recalibration import Recalibration
from .._predictive.uncertainty import predict_rays
from .._util.images import colourise_depth, to_uint8
from ..data import Dataset, Views
from .rendering import render_rays
from .skipping import Skipping

# Preview widths in pixels, coarse to fine: a frame is drawn at the first while the camera
# moves and refined through the others while it is still.
PREVIEW_WIDTHS = (64, 128, 256, 512)
# Rays per compiled render call: every preview (at least 64 x 32 pixels) fills one or more.
PREVIEW_CHUNK = 2048
MODES = ("colour", "depth", "opacity", "colour spread", "depth spread", "colour 90% interval", "depth 90% interval")
# The modes that read the predictive distribution: MixNeRF runs only.
SPREAD_MODES = ("colour spread", "depth spread", "colour 90% interval", "depth 90% interval")
# The interval modes show the width of the interval of this mass (recalibrated if the viewer
# was given a `Recalibration`; the nearest mass it has otherwise).
INTERVAL_MASS = 0.9
# The colour spread (a standard deviation of colour in [0, 1]) shown from 0 to this.
COLOUR_SPREAD_MAX = 0.25


@dataclasses.dataclass(frozen=True)
class ViewerCamera:
    """A browser camera: `rotation` (camera-to-world, OpenCV axes: x right, y down, looking
    along +z) and `position` in world units, `fov` the vertical field of view in radians,
    `aspect` width over height."""

    rotation: Float[np.ndarray, "3 3"]
    position: Float[np.ndarray, "3"]
    fov: float
    aspect: float

    @classmethod
    def from_wxyz(cls, wxyz, position, fov: float, aspect: float) -> "ViewerCamera":
        """From viser's camera state (`client.camera.wxyz`, `.position`, `.fov`, `.aspect`)."""
        from viser.transforms import SO3

        rotation = SO3(np.asarray(wxyz, np.float64)).as_matrix()
        return cls(rotation, np.asarray(position, np.float64), float(fov), float(aspect))

    @property
    def wxyz(self) -> np.ndarray:
        """The rotation as viser's quaternion (w, x, y, z)."""
        from viser.transforms import SO3

        return SO3.from_matrix(self.rotation).wxyz

    def camtoworld(self) -> Float[np.ndarray, "3 4"]:
        """The camera-to-world matrix in this project's (OpenGL) axes."""
        opengl = self.rotation @ np.diag([1.0, -1.0, -1.0])
        return np.concatenate([opengl, self.position[:, None]], axis=1)

    def size(self, width: int) -> tuple[int, int]:
        """`(height, width)` of a preview `width` pixels wide (at least 2 rows)."""
        return max(2, round(width / self.aspect)), width


def camera_of_view(views: Views, index: int) -> ViewerCamera:
    """The browser camera that sees what view `index` of `views` sees (its vertical field of
    view from its focal length; a principal point off the image centre is not kept)."""
    pose = np.asarray(views.camtoworlds[index], np.float64)
    focal_y = views.focal if views.intrinsics is None else float(views.intrinsics[index][1, 1])
    fov = 2.0 * math.atan(0.5 * views.height / focal_y)
    rotation = pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return ViewerCamera(rotation, pose[:3, 3].copy(), fov, views.width / views.height)


def viewer_rays(camera: ViewerCamera, width: int, dataset: Dataset) -> RayBundle:
    """The rays of `camera`'s pixels in a preview `width` pixels wide, in `dataset`'s ray
    space (its near and far bounds; NDC with its training cameras' projection for
    forward-facing scenes; its origin plane).

    **Returns:**

    A `RayBundle` with batch shape `(height, width)`.
    """
    like = dataset.train
    height, width = camera.size(width)
    focal = 0.5 * height / math.tan(0.5 * camera.fov)
    rays = camera_rays(
        camera.camtoworld()[None],
        focal,
        height,
        width,
        dataset.near,
        dataset.far,
        ndc=like.ndc,
        ndc_camera=(like.focal, like.width, like.height) if like.ndc else None,
        origin_plane_z=like.origin_plane_z,
    )
    return rays[0]


def scene_facing(
    camera: ViewerCamera, width: int, dataset: Dataset
) -> Bool[np.ndarray, "height width"] | None:
    """Which of `camera`'s preview pixels look into a forward-facing (NDC) scene: their world
    direction heads along the scene's -z axis, toward the near plane. NDC maps a ray that
    heads away to a mirrored point on the near plane, so those pixels are not rendered.
    `None` for scenes in world space, where every direction is a ray into the scene."""
    if not dataset.train.ndc:
        return None
    height, width = camera.size(width)
    focal = 0.5 * height / math.tan(0.5 * camera.fov)
    world = camera_rays(camera.camtoworld()[None], focal, height, width, dataset.near, dataset.far)
    directions = np.asarray(world.directions[0], np.float64)
    return directions[..., 2] < -1e-6 * np.linalg.norm(directions, axis=-1)


def _padded(rays: RayBundle, count: int) -> RayBundle:
    """`rays` flattened, with the last ray repeated up to `count` rays."""
    flat = rays.reshape(-1)
    missing = count - flat.batch_shape[0]
    if missing <= 0:
        return flat
    return jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], missing, axis=0)]), flat)


def preview_image(
    model: MixNeRF,
    rays: RayBundle,
    mode: str,
    near: float,
    far: float,
    visible: Bool[np.ndarray, "height width"] | None = None,
    recalibration: Recalibration | None = None,
    skipping: Skipping | None = None,
) -> np.ndarray:
    """One preview of `rays` (batch shape `(height, width)`) as 8-bit RGB: the colour, the
    depth coloured from `near` (yellow) to `far` (blue), the opacity in grey, or the predictive
    distribution's colour spread (its standard deviation, mean over channels, from 0 to
    `COLOUR_SPREAD_MAX`) or depth spread (from 0 to a quarter of `far - near`), or the width
    of its 90% colour interval (mean over channels, from 0 to `4 COLOUR_SPREAD_MAX`) or depth
    interval (from 0 to `far - near`), recalibrated by `recalibration` (the model's own
    intervals without one). Pixels where `visible` is false (`scene_facing`) are black. With
    `skipping`, the colour, depth and opacity are rendered with it (the other modes read the
    whole mixture)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    image = _preview(model, rays, mode, near, far, recalibration, skipping)
    if visible is not None:
        image = np.where(visible[..., None], image, np.uint8(0))
    return image


def _preview(
    model: MixNeRF,
    rays: RayBundle,
    mode: str,
    near: float,
    far: float,
    recalibration: Recalibration | None,
    skipping: Skipping | None,
) -> np.ndarray:
    height, width = rays.batch_shape
    flat = _padded(rays, PREVIEW_CHUNK)
    if mode in SPREAD_MODES:
        if model.mixture is None:
            raise ValueError(f"{mode!r} needs a MixNeRF model (a mip-NeRF baseline has no mixture)")
        levels = recalibration or Recalibration.raw((INTERVAL_MASS,))
        summary = predict_rays(
            model, flat, PREVIEW_CHUNK, masses=levels.masses, levels=levels.interval_levels()
        )
        chosen = int(np.argmin(np.abs(np.asarray(levels.masses) - INTERVAL_MASS)))
        if mode == "colour spread":
            spread, top = np.mean(summary["colour_std"], axis=-1), COLOUR_SPREAD_MAX
        elif mode == "depth spread":
            spread, top = summary["depth_std"], 0.25 * (far - near)
        elif mode == "colour 90% interval":
            widths = summary["colour_upper"][chosen] - summary["colour_lower"][chosen]
            spread, top = np.mean(widths, axis=-1), 4.0 * COLOUR_SPREAD_MAX
        else:
            spread, top = summary["depth_upper"][chosen] - summary["depth_lower"][chosen], far - near
        image = colourise_depth(spread[: height * width].reshape(height, width), 0.0, top)
        return to_uint8(image)
    rendered = render_rays(model, flat, PREVIEW_CHUNK, skipping=skipping)
    if mode == "colour":
        image = rendered.rgb
    elif mode == "depth":
        image = colourise_depth(rendered.depth[: height * width].reshape(height, width), near, far)
        return to_uint8(image)
    else:
        image = np.repeat(rendered.acc.reshape(-1, 1), 3, axis=-1)
    return to_uint8(image[: height * width].reshape(height, width, 3))


def _thumbnail(image: np.ndarray, width: int = 96) -> np.ndarray:
    """`image` shrunk by a whole factor to at most `width` pixels wide, as 8-bit RGB."""
    step = max(1, math.ceil(image.shape[1] / width))
    return to_uint8(np.asarray(image)[::step, ::step, :3])


# A jump's hidden frustum is shown again once the camera has left it, but not in the first
# moments after the jump, while a camera pose the browser sent before it may still arrive.
_JUMP_SETTLE_S = 1.0


@dataclasses.dataclass
class _ClientView:
    """One browser's own part of the viewer: its frustums, the one hidden because its camera
    jumped there, and its status line."""

    status: object
    frustums: list = dataclasses.field(default_factory=list)
    hidden: object = None
    hidden_at: float = 0.0  # when the camera jumped there (a pose sent before may still arrive)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)


class Viewer:
    """A web viewer of a model on a local port (viser): the scene rendered from the browser's
    camera, with a selector for colour, depth, opacity and, for MixNeRF, the predictive colour
    and depth spread; the training and test cameras as frustums with their images (a click
    moves the browser's camera there). Each frame is drawn coarse first (`PREVIEW_WIDTHS[0]`
    pixels wide) and refined up to `max_width` while the camera is still.

    Each browser has its own camera, frustums (the one it jumped to is hidden for it alone)
    and status line; the panel's selector (and "pause training") is one for all of them.

    `update(model, step)` shows new parameters (training: `python -m mixnerf_eqx.train
    --viewer`), at most once per `refresh_s` seconds of a still camera; with `training=True`
    the panel has a "pause training" box that `wait_while_paused` honours.

    **Arguments:**

    - `model`: the model shown (`None` until the first `update`).
    - `dataset`: the scene: its cameras, images, ray space and near/far bounds.
    - `host`, `port`: where to serve (port 0: a free one); `url` says where it is.
    - `max_width`: the finest preview width (one of `PREVIEW_WIDTHS`).
    - `mixture`: offer the predictive spreads (default: whether `model` has a mixture; give it
      when `model` is `None` until the first `update`).
    - `recalibration`: the intervals the interval modes show (`mx.uncertainty.fit_recalibration` on the
      scene's validation views; the model's own without one).
    - `skipping`: skip empty space and finished rays in the colour, depth and opacity previews
      (a grid built from `model`, `mx.runs.grid_for_rendering`); it cannot follow `update`.
    """

    def __init__(
        self,
        model: MixNeRF | None,
        dataset: Dataset,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_width: int = 256,
        training: bool = False,
        refresh_s: float = 2.0,
        mixture: bool | None = None,
        recalibration: Recalibration | None = None,
        skipping: Skipping | None = None,
    ):
        import viser

        if max_width not in PREVIEW_WIDTHS:
            raise ValueError(f"max_width must be one of {PREVIEW_WIDTHS}, got {max_width}")
        if skipping is not None and (model is None or training):
            raise ValueError(
                "skipping needs the trained model its grid was built from: a viewer that follows "
                "training renders densely (skipping=None)"
            )
        self.dataset = dataset
        self.widths = tuple(width for width in PREVIEW_WIDTHS if width <= max_width)
        self.refresh_s = refresh_s
        self.recalibration = recalibration
        self.skipping = skipping
        self.frames = 0  # previews sent, over all clients
        self.frame_seconds: dict[int, float] = {}  # the last preview's time per width
        self._model, self._version, self._step = model, 0, None
        self._stopped = threading.Event()
        self._threads: list[threading.Thread] = []
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        if mixture is None:
            mixture = model is not None and model.mixture is not None
        self.mode = self.server.gui.add_dropdown(
            "Show", MODES if mixture else MODES[:3], initial_value="colour"
        )
        self.paused = self.server.gui.add_checkbox("Pause training", False) if training else None
        # Every view's camera, in the order of the frustums each client gets.
        self.cameras = [
            (split, index, camera_of_view(views, index))
            for split, views in (("train", dataset.train), ("test", dataset.test))
            for index in range(views.num_views)
        ]
        positions = np.asarray(dataset.train.camtoworlds)[:, :3, 3]
        spread = float(np.median(np.linalg.norm(positions - positions.mean(axis=0), axis=-1)))
        self.frustum_scale = 0.15 * spread if spread > 0 else 0.1
        self.clients: dict[int, _ClientView] = {}  # per browser: frustums, the hidden one, status
        self._gone: set[int] = set()  # clients that disconnected: their threads stop
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self._gone.add(client.client_id))

    def _add_cameras(self, client) -> list:
        """`client`'s frustum of every training and test view, with its image; a click jumps
        that client's camera there."""
        colours = {"train": (40, 120, 220), "test": (220, 90, 40)}
        views = {"train": self.dataset.train, "test": self.dataset.test}
        handles = []
        for split, index, camera in self.cameras:
            handle = client.scene.add_camera_frustum(
                f"/cameras/{split}/{index}",
                fov=camera.fov,
                aspect=camera.aspect,
                scale=self.frustum_scale,
                color=colours[split],
                image=_thumbnail(views[split].images[index]),
                wxyz=camera.wxyz,
                position=camera.position,
            )
            handle.on_click(lambda event, camera=camera, h=handle: self.move_camera(event.client, camera, h))
            handles.append(handle)
        return handles

    def move_camera(self, client, camera: ViewerCamera, frustum=None) -> None:
        """Puts `client`'s browser camera at `camera` (its pose and field of view); `frustum`,
        the client's one drawn there, is hidden from it until its camera moves away."""
        with client.atomic():
            client.camera.fov = camera.fov
            client.camera.position = camera.position
            client.camera.wxyz = camera.wxyz
        view = self.clients.get(client.client_id)
        if view is None:  # not connected (yet, or any more): nothing of its own to hide
            return
        with view.lock:
            if view.hidden is not None:
                view.hidden.visible = True
            view.hidden, view.hidden_at = frustum, time.monotonic()
            if frustum is not None:
                frustum.visible = False

    def _connect(self, client) -> None:
        view = self.clients[client.client_id] = _ClientView(client.gui.add_markdown(""))
        view.frustums.extend(self._add_cameras(client))
        self.move_camera(client, self.cameras[0][2], view.frustums[0])
        thread = threading.Thread(
            target=self._serve, args=(client,), daemon=True, name=f"viewer-{client.client_id}"
        )
        self._threads.append(thread)
        thread.start()

    def update(self, model: MixNeRF, step=None) -> None:
        """Shows `model` from now on (a new frame once the refresh interval has passed)."""
        if self.skipping is not None:
            raise ValueError(
                "this viewer skips with a grid of the model it was given, which an update would leave "
                "behind: a viewer that follows training renders densely (skipping=None)"
            )
        self._model, self._step = model, step
        self._version += 1

    def wait_while_paused(self) -> None:
        """Returns once "pause training" is unticked (at once without the box); a Ctrl-C is
        taken while waiting."""
        from .._util.interrupt import raise_if_interrupted

        while self.paused is not None and self.paused.value and not self._stopped.is_set():
            raise_if_interrupted()
            time.sleep(0.05)

    def render(self, camera: ViewerCamera, width: int, mode: str | None = None) -> np.ndarray:
        """The preview of `camera`, `width` pixels wide, in `mode` (default: the panel's)."""
        model = self._model
        if model is None:
            raise ValueError("no model to render yet")
        started = time.perf_counter()
        dataset = self.dataset
        rays = viewer_rays(camera, width, dataset)
        visible = scene_facing(camera, width, dataset)
        image = preview_image(
            model,
            rays,
            mode or self.mode.value,
            dataset.near,
            dataset.far,
            visible,
            self.recalibration,
            self.skipping,
        )
        self.frame_seconds[width] = time.perf_counter() - started
        return image

    def _serve(self, client) -> None:
        """One client's frames: coarse at once when the camera or the mode changes, then finer
        while they stay. New parameters (training) restart the ladder at most once per
        `refresh_s`; until then the frame in progress goes on refining with the newest model.
        A frame that fails is reported in the client's status line and the loop goes on."""
        try:
            self._frames_of(client, self.clients[client.client_id])
        finally:
            self.clients.pop(client.client_id, None)

    def _frames_of(self, client, view_state: _ClientView) -> None:
        drawn, level, shown_at = None, 0, 0.0
        while not self._stopped.is_set() and client.client_id not in self._gone:
            try:
                state = client.camera
                camera = ViewerCamera.from_wxyz(state.wxyz, state.position, state.fov, state.aspect)
            except AssertionError:  # the browser has not sent its camera yet
                time.sleep(0.05)
                continue
            with view_state.lock:
                hidden = view_state.hidden
                settled = time.monotonic() - view_state.hidden_at > _JUMP_SETTLE_S
                if hidden is not None and settled:
                    if np.linalg.norm(camera.position - hidden.position) > self.frustum_scale:
                        hidden.visible, view_state.hidden = True, None
            view = (tuple(camera.rotation.ravel()), tuple(camera.position), camera.fov, camera.aspect)
            wanted = (view, self.mode.value, self._version)
            if drawn is None or wanted[:2] != drawn[:2]:
                drawn, level = wanted, 0  # the camera or the mode changed: coarse at once
            elif wanted != drawn and time.monotonic() - shown_at >= self.refresh_s:
                drawn, level = wanted, 0  # new parameters, and the last frame is old enough
            if self._model is None or level >= len(self.widths):
                time.sleep(0.02)
                continue
            width = self.widths[level]
            started = time.perf_counter()
            try:
                image = self.render(camera, width, wanted[1])
            except Exception as error:  # noqa: BLE001 (one bad frame must not end the client's frames)
                view_state.status.content = f"cannot show {wanted[1]}: {error}"
                level = len(self.widths)
                continue
            seconds = time.perf_counter() - started
            if client.client_id in self._gone:
                break
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            shown_at, level = time.monotonic(), level + 1
            self.frames += 1
            step = "" if self._step is None else f"step {int(self._step)}, "
            view_state.status.content = f"{step}{width} px wide in {1000 * seconds:.0f} ms"

    def stop(self) -> None:
        """Stops serving and waits for the render threads."""
        self._stopped.set()
        for thread in self._threads:
            thread.join(timeout=10)
        self.server.stop()
