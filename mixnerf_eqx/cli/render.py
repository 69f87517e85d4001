"""Render a video of a run: `python -m mixnerf_eqx.render RUN_DIR [--path auto|spiral|orbit|test] [...]`.

Loads the run's config and its latest (or the given) checkpoint and renders a camera path
through the scene: a spiral in front of a forward-facing (LLFF) scene, an orbit around a
360-degree one (Blender, DTU, the built-in scene), or the test views. Each frame shows the
colour, the depth (colour-mapped between the scene's near and far bounds) and, with
`--uncertainty`, the predictive colour spread, side by side. Frames are rendered one at a
time in chunks of rays (memory stays bounded) and written to `RUN_DIR/video/<path>.mp4`.
"""

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from .._config import ConfigError
from .._inference.video import check_destination, render_video
from .._nn.rays import RayBundle
from .._runs.run_folder import Run, grid_for_rendering, make_skipping, restore_run
from .._util import json_io as strict_json
from .._util.compilation_cache import add_compilation_cache_argument
from .._util.progress import Progress
from .._util.typecheck import add_typecheck_argument
from .common import add_run_arguments, add_skipping_argument, run_command


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.render", description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    parser.add_argument(
        "--path",
        choices=("auto", "spiral", "orbit", "test"),
        default="auto",
        help="camera path (auto: spiral for forward-facing scenes, orbit otherwise; test: the test views)",
    )
    parser.add_argument("--frames", type=int, default=120, help="frames on a spiral or orbit (default 120)")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    parser.add_argument("--out", type=Path, default=None, help="MP4 file (default RUN_DIR/video/PATH.mp4)")
    parser.add_argument("--save-frames", action="store_true", help="also write every frame as a PNG")
    parser.add_argument(
        "--uncertainty",
        action="store_true",
        help="add a third panel: the predictive colour spread per pixel (needs the predictive module)",
    )
    parser.add_argument("--chunk", type=int, default=None, help="rays rendered at once (default: the run's)")
    add_skipping_argument(parser)
    add_typecheck_argument(parser)
    add_compilation_cache_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser.parse_intermixed_args(argv)


def _check_arguments(args: argparse.Namespace) -> None:
    if args.frames < 1:
        raise ConfigError(f"--frames must be a positive number of frames, got {args.frames}")
    # Encoders take frame rates as rationals of bounded terms: a rate outside [0.1, 1000]
    # fails inside the encoder (an infinite one as a broken pipe).
    if not (math.isfinite(args.fps) and 0.1 <= args.fps <= 1000):
        raise ConfigError(f"--fps must be a number of frames per second in [0.1, 1000], got {args.fps:g}")
    if args.chunk is not None and args.chunk < 1:
        raise ConfigError(f"--chunk must be a positive number of rays, got {args.chunk}")
    if args.out is not None and args.out.suffix.lower() != ".mp4":
        raise ConfigError(f"--out must name an .mp4 file, got {args.out}")


def _colour_spread(run: Run, chunk: int) -> Callable[[RayBundle], np.ndarray]:
    """The predictive distribution's colour spread per pixel (its standard deviation, the
    mean over the channels), from the predictive module."""
    try:
        from .._predictive.uncertainty import predict_rays
    except ImportError:
        raise ConfigError(
            "--uncertainty needs the predictive distribution (mixnerf_eqx._predictive.uncertainty), "
            "which this version does not have"
        ) from None
    if run.config.method != "mixnerf":
        raise ConfigError("--uncertainty needs a MixNeRF run; a mip-NeRF run has no mixture to spread")

    def spread(rays: RayBundle) -> np.ndarray:
        summary = predict_rays(run.model, rays, chunk)
        return np.mean(summary["colour_std"], axis=-1)

    return spread


def run(args: argparse.Namespace) -> dict:
    """Renders the video `args` ask for and returns what was written to its JSON file."""
    if args.out is not None:
        check_destination(args.out)  # before loading the run, and before any frame
    restored = restore_run(args.run_dir, checkpoint=args.checkpoint, data_dir=args.data_dir)
    config = restored.config
    skipping = None
    if args.skipping == "on" or (args.skipping == "auto" and config.occupancy.renders_skip):
        grid, _ = grid_for_rendering(
            config.occupancy, restored.dataset, restored.model, key=jax.random.fold_in(restored.state.key, 0)
        )
        skipping = make_skipping(config.occupancy, grid)
    chunk = args.chunk or (config.occupancy.chunk if skipping is not None else config.train.render_chunk)
    spread = _colour_spread(restored, chunk) if args.uncertainty else None
    out = args.out or args.run_dir / "video" / f"{args.path}.mp4"
    frames_dir = out.with_name(out.stem + "_frames") if args.save_frames else None
    total = restored.dataset.test.num_views if args.path == "test" else args.frames
    bar = Progress(total, unit="frame", enabled=not args.no_progress)
    try:
        video = render_video(
            restored.model,
            restored.dataset,
            out,
            kind=args.path,
            num_frames=args.frames,
            fps=args.fps,
            chunk=chunk,
            skipping=skipping,
            frames_dir=frames_dir,
            spread=spread,
            on_frame=lambda done, _: bar.update(done),
        )
    except KeyboardInterrupt:
        partial = out.with_name(out.stem + ".partial.mp4")
        print(
            f"\ninterrupted after {bar.done} of {total} frames: they are in {partial}; nothing in the "
            "run was changed",
            file=sys.stderr,
        )
        raise
    finally:
        bar.close()
    summary = {
        "run_dir": str(args.run_dir),
        "checkpoint": str(restored.checkpoint),
        "step": restored.step,
        "scene": restored.dataset.name,
        "path": args.path,
        "video": str(video.path),
        "frames_dir": None if frames_dir is None else str(frames_dir),
        "fps": video.fps,
        "num_frames": video.num_frames,
        "width": video.width,
        "height": video.height,
        "panels": ["colour", "depth"] + (["colour spread"] if spread is not None else []),
        "skipping": skipping is not None,
        "seconds": video.seconds,
    }
    video.path.with_suffix(".json").write_text(strict_json.dumps(summary, indent=2))
    print(
        f"{video.path}: {video.num_frames} frames at {video.fps:g} fps, {video.width}x{video.height} "
        f"({' | '.join(summary['panels'])}), rendered in {video.seconds:.1f} s"
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    def body() -> None:
        _check_arguments(args)
        run(args)

    return run_command(args, body, interrupted=None)


if __name__ == "__main__":
    sys.exit(main())
