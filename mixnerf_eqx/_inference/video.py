"""Rendering a camera path and writing its frames as an MP4 video (H.264, encoded by the
FFmpeg that the `imageio-ffmpeg` wheel carries: nothing is downloaded) and, on request, PNGs.

A video is written frame by frame, so memory holds one frame whatever the length. It is
written under a temporary name and renamed when complete; a video cut short (Ctrl-C) is
closed as a playable file of the frames so far and named `*.partial.mp4`.
"""

import contextlib
import dataclasses
import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from jaxtyping import Float

from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from .._util.images import colourise_depth, save_png, to_uint8
from ..data import Dataset, rays_at_poses, rays_for_views
from .camera_path import camera_path
from .rendering import render_rays
from .skipping import Skipping


def check_destination(path: Path) -> None:
    """Says in one `ValueError` why the video file `path` (and its `.partial.mp4` beside it)
    cannot be written, before any frame is rendered: a folder of that name, a file where a
    folder above it should be, or a folder that cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"the video {path} is an existing folder; name a file")
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"cannot write the video {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write the video {path}: {ancestor} is not writable")


def side_by_side(panels: list[Float[np.ndarray, "height width channels"]]) -> np.ndarray:
    """The panels left to right as one 8-bit frame, padded with white to even sides (the
    H.264 encoder's chroma subsampling needs them)."""
    frame = to_uint8(np.concatenate(panels, axis=1))
    height, width = frame.shape[:2]
    return np.pad(frame, ((0, height % 2), (0, width % 2), (0, 0)), constant_values=255)


def frame_panels(
    rgb: Float[np.ndarray, "height width channels"],
    depth: Float[np.ndarray, "height width"],
    *,
    near: float,
    far: float,
    spread: Float[np.ndarray, "height width"] | None = None,
    spread_max: float = 1.0,
) -> list[np.ndarray]:
    """A frame's panels: colour, colour-mapped depth and, if given, the colour spread (the
    same colour map from 0 to `spread_max`)."""
    panels = [rgb, colourise_depth(depth, near, far)]
    if spread is not None:
        panels.append(colourise_depth(spread, 0.0, spread_max))
    return panels


class VideoWriter:
    """An MP4 file (and optionally a folder of PNG frames) written one frame at a time.

    The frames are piped to the FFmpeg executable of the `imageio-ffmpeg` wheel, started in
    a session of its own: Ctrl-C then reaches this process only, which closes the video
    cleanly instead of losing it with the encoder.

    **Arguments:**

    - `path`: the video file (`.mp4`).
    - `fps`: frames per second.
    - `frames_dir`: a folder for the frames as `frame_00000.png`, ...; `None` writes none.
    - `crf`: H.264's constant rate factor (lower is better; 18 is visually lossless).
    """

    def __init__(self, path: Path, fps: float, *, frames_dir: Path | None = None, crf: int = 18):
        self.path, self.fps, self.crf, self.frames_dir = Path(path), fps, crf, frames_dir
        check_destination(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if frames_dir is not None:
            frames_dir.mkdir(parents=True, exist_ok=True)
        self.staging = self.path.with_name(self.path.stem + ".partial.mp4")
        self.count = 0
        self.encoder: subprocess.Popen | None = None
        self.size: tuple[int, int] | None = None

    def _start(self, height: int, width: int) -> subprocess.Popen:
        import imageio_ffmpeg

        command = [
            imageio_ffmpeg.get_ffmpeg_exe(),
            *("-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24"),
            *("-s", f"{width}x{height}", "-r", f"{self.fps:g}", "-i", "-", "-an"),
            *("-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", str(self.crf)),
            *("-movflags", "+faststart", str(self.staging)),
        ]
        return subprocess.Popen(
            command, stdin=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
        )

    def append(self, frame: np.ndarray) -> None:
        """Adds an 8-bit RGB frame with even sides (`side_by_side` makes one); every frame of
        a video has the size of the first."""
        height, width = frame.shape[:2]
        if self.encoder is None:
            self.size = (height, width)
            self.encoder = self._start(height, width)
        if (height, width) != self.size:
            raise ValueError(
                f"frame {self.count} is {width}x{height}; the video is {self.size[1]}x{self.size[0]}"
            )
        assert self.encoder.stdin is not None
        self.encoder.stdin.write(np.ascontiguousarray(frame, np.uint8).tobytes())
        if self.frames_dir is not None:
            save_png(self.frames_dir / f"frame_{self.count:05d}.png", frame.astype(np.float32) / 255.0)
        self.count += 1

    def _close(self) -> None:
        if self.encoder is None:
            return
        assert self.encoder.stdin is not None and self.encoder.stderr is not None
        self.encoder.stdin.close()
        with self.encoder.stderr:
            message = self.encoder.stderr.read().decode(errors="replace").strip()
        if self.encoder.wait() != 0:
            raise OSError(f"the video encoder failed on {self.staging}: {message or 'no message'}")

    def finish(self) -> Path:
        """Closes the file and gives it its final name."""
        self._close()
        self.staging.replace(self.path)
        return self.path

    def abandon(self) -> Path:
        """Closes the file as it is (the frames so far) under its `.partial.mp4` name."""
        self._close()
        return self.staging


def path_frames(dataset: Dataset, kind: str, num_frames: int) -> tuple[int, Callable[[int], RayBundle]]:
    """The number of frames of the video `kind` (`"test"`: the test views; otherwise a
    `camera_path` kind) and a function from a frame's index to its rays."""
    near, far = dataset.near, dataset.far
    if kind == "test":
        return dataset.test.num_views, lambda index: rays_for_views(dataset.test.select([index]), near, far)
    poses = camera_path(dataset, kind, num_frames).astype(np.float32)
    return len(poses), lambda index: rays_at_poses(dataset.test, poses[index : index + 1], near, far)


@dataclasses.dataclass(frozen=True)
class Video:
    """A written video: its file, frames per second, frame count and size in pixels."""

    path: Path
    fps: float
    num_frames: int
    width: int
    height: int
    seconds: float


def render_video(
    model: MixNeRF,
    dataset: Dataset,
    path: Path,
    *,
    kind: str = "auto",
    num_frames: int = 120,
    fps: float = 30.0,
    chunk: int = 4096,
    skipping: Skipping | None = None,
    frames_dir: Path | None = None,
    spread: Callable[[RayBundle], np.ndarray] | None = None,
    spread_max: float = 0.25,
    on_frame: Callable[[int, int], None] | None = None,
) -> Video:
    """Renders a camera path through `dataset`'s scene into an MP4 file, one frame at a time.

    **Arguments:**

    - `model`: the trained model.
    - `dataset`: the scene (its cameras set the path, the image size and the ray space).
    - `path`: the video file.
    - `kind`: `"auto"`, `"spiral"`, `"orbit"` (see `camera_path`) or `"test"` (the test views).
    - `num_frames`, `fps`: the path's length and the video's frame rate.
    - `chunk`, `skipping`: as in `render_rays` (memory is bounded by the chunk).
    - `frames_dir`: also write each frame as a PNG there.
    - `spread`: a per-pixel uncertainty of a frame's rays (e.g. the predictive colour spread),
      shown as a third panel coloured from 0 to `spread_max`; `None`: colour and depth only.
    - `on_frame`: called as `on_frame(frames done, frames in all)` after each frame.

    **Returns:**

    A `Video`. Ctrl-C (inside `deferred_interrupts`) stops between chunks of rays; the
    frames so far are kept in a playable `*.partial.mp4` beside `path`.
    """
    started = time.perf_counter()
    total, rays_of = path_frames(dataset, kind, num_frames)
    writer = VideoWriter(path, fps, frames_dir=frames_dir)
    try:
        for index in range(total):
            rays = rays_of(index)
            rendered = render_rays(model, rays, chunk, skipping=skipping).select(0)
            uncertainty = None if spread is None else np.asarray(spread(rays))[0]
            panels = frame_panels(
                rendered.rgb,
                rendered.depth,
                near=dataset.near,
                far=dataset.far,
                spread=uncertainty,
                spread_max=spread_max,
            )
            frame = side_by_side(panels)
            writer.append(frame)
            if on_frame is not None:
                on_frame(index + 1, total)
    except BaseException:
        # The frames so far stay playable; the error that stopped them is the one reported.
        with contextlib.suppress(OSError):
            writer.abandon()
        raise
    written = writer.finish()
    height, width = frame.shape[:2]
    return Video(written, fps, total, width, height, time.perf_counter() - started)
