"""Look at a run in the browser: `python -m mixnerf_eqx.view RUN_DIR [--port 8080] [...]`.

Loads the run's config and its latest (or the given) checkpoint and serves a web viewer
(viser, the `viewer` extra) on a local port: the scene rendered from the browser's camera as
colour, depth, opacity or, for MixNeRF, the predictive colour and depth spread; the training
and test cameras as frustums with their images (a click jumps there). Frames are drawn coarse
first and refined while the camera is still. With `--skipping on` (or `auto` where the run's
config asks for it: `occupancy.enabled` or `occupancy.render_skipping`) the colour, depth and
opacity previews skip empty space and finished rays, with a grid built from the checkpoint and
its threshold chosen as `eval` chooses it. Ctrl-C stops the server.
"""

import argparse
import socket
import sys
import time

import jax

from .._inference.viewer import PREVIEW_WIDTHS, Viewer
from .._predictive.recalibration import METHODS, Recalibration
from .._predictive.uncertainty import fit_recalibration
from .._runs.run_folder import Run, grid_for_rendering, make_skipping, restore_run
from .._util.compilation_cache import add_compilation_cache_argument
from .._util.interrupt import raise_if_interrupted
from .._util.typecheck import add_typecheck_argument
from .common import add_run_arguments, add_skipping_argument, run_command

VIEWER_EXTRA = "the viewer needs viser: pip install 'mixnerf_eqx[viewer]'"


def port_number(text: str) -> int:
    """A TCP port, 0 to 65535 (0: any free one)."""
    port = int(text)
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 to 65535, got {port}")
    return port


def serving_line(viewer: Viewer, asked: int) -> str:
    """Where `viewer` serves, and whether that is not the port asked for (viser moves on to
    the next free one)."""
    actual = viewer.server.get_port()
    moved = f" (port {asked} is in use)" if asked and actual != asked else ""
    return f"{viewer.url}{moved}"


def add_viewer_arguments(parser: argparse.ArgumentParser) -> None:
    """`--host`, `--port` and `--max-width`, as `view` and `train --viewer` take them."""
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=port_number, default=8080, help="port to serve on (default 8080; 0: any free)"
    )
    parser.add_argument(
        "--max-width",
        type=int,
        choices=PREVIEW_WIDTHS,
        default=256,
        help="the finest preview's width in pixels (default 256)",
    )


def check_host(host: str, flag: str = "--host") -> None:
    """A `ValueError` unless `host` is an address this machine can serve on: a server bound to
    another machine's address waits for nothing, silently (checked by binding a socket here,
    which sends nothing)."""
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        raise ValueError(f"{flag} {host} is not an address or a known host name") from None
    family, _, _, _, address = infos[0]
    probe = socket.socket(family, socket.SOCK_STREAM)
    try:
        probe.bind(address)
    except OSError:
        raise ValueError(
            f"{flag} {host} is not an address of this machine: serve on 127.0.0.1 (this machine only) "
            "or 0.0.0.0 (every interface)"
        ) from None
    finally:
        probe.close()


def check_viewer_installed() -> None:
    """A `ValueError` naming the extra when viser is missing."""
    try:
        import viser  # noqa: F401
    except ImportError:
        raise ValueError(VIEWER_EXTRA) from None


def viewer_recalibration(run, method: str) -> Recalibration | None:
    """The intervals the viewer's interval modes show: `method` fitted on the run's validation
    views, said in one line; `None` (the model's own) for a baseline, `raw`, or a scene without
    validation views."""
    dataset = run.dataset
    if run.model.mixture is None:
        return None
    if method == "raw":
        print("interval modes: the model's own intervals (--calibration raw)")
        return None
    if dataset.val is None or dataset.val.num_views == 0:
        print(f"{dataset.name} has no validation views: the interval modes show the model's own intervals")
        return None
    try:
        recalibration = fit_recalibration(
            run.model,
            dataset.val,
            dataset.near,
            dataset.far,
            method,
            chunk=run.config.train.render_chunk,
            description=f"the {dataset.val.num_views} validation views",
        )
    except ValueError as error:  # too few validation pixels for the masses
        print(f"interval modes: the model's own intervals ({method} could not be fitted: {error})")
        return None
    print(f"interval modes: {method} intervals fitted on {recalibration.fitted_on}")
    return recalibration


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.view", description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    add_viewer_arguments(parser)
    parser.add_argument(
        "--calibration",
        choices=METHODS,
        default="conformal",
        help="the intervals the interval modes show, fitted on the scene's validation views: conformal "
        "(the default), isotonic, or raw (the model's own; also where the scene has no validation views)",
    )
    add_skipping_argument(parser)
    add_typecheck_argument(parser)
    add_compilation_cache_argument(parser)
    return parser.parse_args(argv)


def viewer_skipping(run: Run, mode: str):
    """The skipping `--skipping` asks for (`None`: dense), its grid built from the run's model
    and said in one line."""
    occupancy = run.config.occupancy
    if not (mode == "on" or (mode == "auto" and occupancy.renders_skip)):
        return None
    grid, choice = grid_for_rendering(
        occupancy, run.dataset, run.model, key=jax.random.fold_in(run.state.key, run.step)
    )
    how = "from the config"
    if choice is not None:
        how = f"chosen on {'validation' if choice.views == 'val' else 'training'} pixels"
    print(
        f"skipping: density threshold {float(grid.threshold):.4g} ({how}), "
        f"{float(grid.occupied_fraction()):.1%} of the grid occupied (colour, depth and opacity previews)"
    )
    return make_skipping(occupancy, grid)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    def body() -> None:
        check_viewer_installed()
        check_host(args.host)
        run = restore_run(args.run_dir, checkpoint=args.checkpoint, data_dir=args.data_dir)
        recalibration = viewer_recalibration(run, args.calibration)
        skipping = viewer_skipping(run, args.skipping)
        viewer = Viewer(
            run.model,
            run.dataset,
            host=args.host,
            port=args.port,
            max_width=args.max_width,
            recalibration=recalibration,
            skipping=skipping,
        )
        where = serving_line(viewer, args.port)
        print(f"viewer of {args.run_dir} (step {run.step}): {where}  (Ctrl-C to stop)", flush=True)
        try:
            while True:
                raise_if_interrupted()
                time.sleep(0.1)
        finally:
            viewer.stop()

    return run_command(args, body, interrupted="viewer stopped")


if __name__ == "__main__":
    sys.exit(main())
