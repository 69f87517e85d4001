"""Train MixNeRF: `python -m mixnerf_eqx.train [--config configs/<name>.toml] [section.key=value ...]`.

Without `--config` it trains on the built-in procedural scene with `configs/builtin.toml`,
reports the test metrics and writes renders. Runs resume from their latest checkpoint.
"""

import argparse
import os
import sys
from pathlib import Path

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "builtin.toml"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.train", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--config", type=Path, default=None, help="TOML config (default: configs/builtin.toml)"
    )
    parser.add_argument("--run-dir", default=None, help="output folder (default: the config's train.run_dir)")
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: data.data_dir, else $MIXNERF_DATA_DIR)"
    )
    parser.add_argument("--no-typecheck", action="store_true", help="turn off runtime shape checks")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "overrides", nargs="*", metavar="section.key=value", help="config overrides, e.g. train.max_steps=200"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.no_typecheck:
        os.environ["MIXNERF_EQX_TYPECHECK"] = "0"
    from mixnerf_eqx import ConfigError, load_config
    from mixnerf_eqx._train import TrainingDiverged, fit

    config_path = args.config
    if config_path is None:
        if not DEFAULT_CONFIG.is_file():
            print(
                f"error: no --config given and the default {DEFAULT_CONFIG.name} was not found",
                file=sys.stderr,
            )
            return 2
        config_path = DEFAULT_CONFIG
    overrides = list(args.overrides)
    if args.run_dir is not None:
        overrides.append(f"train.run_dir={args.run_dir!r}".replace("'", '"'))
    if args.data_dir is not None:
        overrides.append(f"data.data_dir={args.data_dir!r}".replace("'", '"'))
    if args.no_typecheck:
        overrides.append("train.typecheck=false")
    try:
        config = load_config(config_path, overrides)
        print(f"config {config_path} ({config.name}); outputs in {config.train.run_dir}")
        result = fit(config, progress=not args.no_progress)
    except (ConfigError, ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except TrainingDiverged as error:
        print(f"\ntraining stopped: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    test = result.metrics["test"]
    print(
        f"\ntest metrics after {result.metrics['step']} steps on {result.metrics['scene']} "
        f"({len(result.metrics['per_view'])} held-out views):"
    )
    for name, value in test.items():
        print(f"  {name:10s} " + ("n/a (install the lpips extra)" if value is None else f"{value:.4f}"))
    render = result.metrics["render"]
    if render["skipping"]:
        print(
            f"rendering skipped empty space and finished rays: {render['field_evaluations_per_frame']:.0f} "
            f"field evaluations per frame instead of {render['dense_evaluations_per_frame']:.0f} "
            f"({render['evaluation_reduction']:.2f}x fewer; "
            f"{render['occupied_fraction']:.1%} of the grid occupied)"
        )
    print(f"metrics: {result.run_dir / 'metrics.json'}")
    print(f"renders: {result.run_dir / 'renders'}")
    print(f"checkpoints: {result.run_dir / 'checkpoints'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
