"""Train MixNeRF: `python -m mixnerf_eqx.train [--config NAME|FILE.toml] [section.key=value ...]`.

Without `--config` it trains on the built-in procedural scene with the packaged `builtin_grid`
config, reports the test metrics and writes renders. `--config` takes one of the package's
configs by name (`llff3_grid`; `mx.config.config_names()` lists them) or a TOML file. Runs resume
from their latest checkpoint.
"""

import argparse
import sys
from pathlib import Path

from .._config import ConfigError, config_path, load_config, replace_setting
from .._nn.model import check_model_names
from .._runs.loop import TrainingDiverged, fit
from .._util.compilation_cache import add_compilation_cache_argument, use_compilation_cache
from .._util.interrupt import deferred_interrupts
from .._util.typecheck import add_typecheck_argument, typecheck_argument
from .common import report_error
from .view import port_number

DEFAULT_CONFIG = "builtin_grid"  # the quick start: a packaged config


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.train", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--config",
        default=DEFAULT_CONFIG,
        help=f"a packaged config's name or a TOML file (default: {DEFAULT_CONFIG})",
    )
    parser.add_argument("--run-dir", default=None, help="output folder (default: the config's train.run_dir)")
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: data.data_dir, else $MIXNERF_DATA_DIR)"
    )
    add_typecheck_argument(parser)
    add_compilation_cache_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--viewer",
        action="store_true",
        help="serve the web viewer while training (viser, the viewer extra): the current parameters, "
        "refreshed between steps, and a box that pauses training",
    )
    parser.add_argument("--viewer-host", default="127.0.0.1", help="the viewer's address (default 127.0.0.1)")
    parser.add_argument(
        "--viewer-port", type=port_number, default=8080, help="the viewer's port (default 8080; 0: any)"
    )
    parser.add_argument(
        "--viewer-max-width",
        type=int,
        choices=(64, 128, 256, 512),
        default=128,
        help="the finest preview while training, in pixels (default 128: a small share of the CPU)",
    )
    parser.add_argument(
        "overrides", nargs="*", metavar="section.key=value", help="config overrides, e.g. train.max_steps=200"
    )
    return parser.parse_intermixed_args(argv)


def _print_report(metrics: dict, run_dir: Path) -> None:
    print(
        f"\ntest metrics after {metrics['step']} steps on {metrics['scene']} "
        f"({len(metrics['per_view'])} held-out views):"
    )
    for name, value in metrics["test"].items():
        print(f"  {name:10s} " + ("n/a (install the lpips extra)" if value is None else f"{value:.4f}"))
    render = metrics["render"]
    if render["skipping"]:
        print(
            f"rendering skipped empty space and finished rays: {render['field_evaluations_per_frame']:.0f} "
            f"field evaluations per frame instead of {render['dense_evaluations_per_frame']:.0f} "
            f"({render['evaluation_reduction']:.2f}x fewer; "
            f"{render['occupied_fraction']:.1%} of the grid occupied)"
        )
    print(f"metrics: {run_dir / 'metrics.json'}")
    print(f"renders: {run_dir / 'renders'}")
    print(f"checkpoints: {run_dir / 'checkpoints'}")


def _fit_with_viewer(config, args: argparse.Namespace):
    """`fit` with the web viewer showing the state between steps; it stops with the run."""
    from .._inference.viewer import Viewer
    from ..data import load_dataset
    from .view import check_host, check_viewer_installed, serving_line

    check_viewer_installed()
    check_host(args.viewer_host, "--viewer-host")
    dataset = load_dataset(config.data)
    viewer = None

    def show(state) -> None:
        nonlocal viewer
        if viewer is None:
            # Started at the first call, once `fit` holds the run folder: a run refused
            # (a busy folder, a config that cannot resume) starts no server.
            viewer = Viewer(
                None,
                dataset,
                host=args.viewer_host,
                port=args.viewer_port,
                max_width=args.viewer_max_width,
                training=True,
                mixture=config.method == "mixnerf",
            )
            where = serving_line(viewer, args.viewer_port)
            print(f"viewer: {where}  (the run's current parameters; pause training from the panel)", flush=True)
        viewer.update(state.model, state.step)  # the step stays on the device until a frame is drawn
        viewer.wait_while_paused()

    try:
        return fit(config, dataset=dataset, progress=not args.no_progress, on_step=show)
    finally:
        if viewer is not None:
            viewer.stop()


def _train(args: argparse.Namespace) -> int:
    try:
        path = config_path(args.config)
        config = load_config(path, args.overrides)
        # Paths are set as values, never spliced into an override string.
        if args.run_dir is not None:
            config = replace_setting(config, "train", run_dir=args.run_dir)
        if args.data_dir is not None:
            config = replace_setting(config, "data", data_dir=args.data_dir)
        check_model_names(config)
        shown = args.config if str(path) == str(args.config) else f"{args.config} ({path})"
        print(f"config {shown}, {config.name}; outputs in {config.train.run_dir}")
        if args.viewer:
            result = _fit_with_viewer(config, args)
        else:
            result = fit(config, progress=not args.no_progress)
    except (ConfigError, ValueError, OSError) as error:
        return report_error(error)
    except TrainingDiverged as error:
        print(f"\ntraining stopped: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    _print_report(result.metrics, result.run_dir)
    if result.metrics.get("unusable"):
        print(f"error: the run's results are not usable: {result.metrics['unusable']}", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    use_compilation_cache(args)
    # From here on, Ctrl-C is recorded and acted on at the training loop's next safe point: in
    # the set-up before it, Python's own KeyboardInterrupt could be raised inside a callback
    # (JAX's garbage-collection hook) and be lost (docs/reliability.md, "Soak").
    try:
        with typecheck_argument(args), deferred_interrupts():
            return _train(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
