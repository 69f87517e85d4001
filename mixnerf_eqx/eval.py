"""Evaluate a run: `python -m mixnerf_eqx.eval RUN_DIR [--checkpoint DIR] [--data-dir DIR] [...]`.

Loads the run's config and its latest (or the given) checkpoint, renders the test views one at
a time in chunks of rays (memory stays bounded whatever the resolution), writes per-image and
mean metrics to `RUN_DIR/eval/metrics.json` with colour and depth PNGs beside it, and prints a
table. LPIPS needs the optional `lpips` extra; without it LPIPS is reported as unavailable.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

METRIC_COLUMNS = ("psnr", "ssim", "lpips", "average", "depth_mae")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.eval", description=__doc__.split("\n")[0])
    parser.add_argument(
        "run_dir", type=Path, help="a training run's folder (holds config.json, checkpoints/)"
    )
    parser.add_argument("--checkpoint", type=Path, default=None, help="checkpoint folder (default: latest)")
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: the run's, else $MIXNERF_DATA_DIR)"
    )
    parser.add_argument("--chunk", type=int, default=None, help="rays rendered at once (default: the run's)")
    parser.add_argument(
        "--max-views", type=int, default=0, help="evaluate this many test views, evenly spaced"
    )
    parser.add_argument(
        "--skipping",
        choices=("auto", "on", "off"),
        default="auto",
        help="skip empty space and finished rays with an occupancy grid built from the checkpoint "
        "(auto: if the run's occupancy.enabled)",
    )
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: RUN_DIR/eval)")
    parser.add_argument("--no-renders", action="store_true", help="write no PNGs")
    parser.add_argument("--no-lpips", action="store_true", help="skip LPIPS (and the average)")
    parser.add_argument("--no-typecheck", action="store_true", help="turn off runtime shape checks")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser.parse_args(argv)


def format_table(per_view: list[dict], means: dict) -> str:
    """A plain-text table of the per-view metrics and their means."""
    columns = [name for name in METRIC_COLUMNS if name in means]

    def cell(value) -> str:
        return "n/a" if value is None else f"{value:.4f}"

    header = f"{'view':>8} " + " ".join(f"{name:>10}" for name in columns)
    lines = [header, "-" * len(header)]
    lines += [
        f"{entry['view']:>8} " + " ".join(f"{cell(entry[n]):>10}" for n in columns) for entry in per_view
    ]
    lines += ["-" * len(header), f"{'mean':>8} " + " ".join(f"{cell(means[n]):>10}" for n in columns)]
    return "\n".join(lines)


def load_run(run_dir: Path, checkpoint: Path | None = None, data_dir: str | None = None):
    """A training run's config, dataset and trained model.

    **Arguments:**

    - `run_dir`: the run's folder (holds `config.json` and `checkpoints/`).
    - `checkpoint`: the checkpoint folder (default: the latest).
    - `data_dir`: the dataset root, replacing the run's.

    **Returns:**

    `(config, dataset, model, step, checkpoint, key)`, `key` being the run's training key.
    """
    import dataclasses

    import equinox as eqx
    import jax

    from mixnerf_eqx import ConfigError, build_model
    from mixnerf_eqx._checkpoint import latest_checkpoint, load_checkpoint, read_checkpoint_meta
    from mixnerf_eqx._config import config_from_dict, init_key
    from mixnerf_eqx._train import make_optimizer
    from mixnerf_eqx.data import load_dataset

    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise ConfigError(f"{run_dir} is not a training run: it has no config.json. Pass a run folder.")
    checkpoint = checkpoint or latest_checkpoint(run_dir)
    if checkpoint is None:
        raise ConfigError(f"{run_dir} holds no checkpoint yet; train first (python -m mixnerf_eqx.train).")
    if not (Path(checkpoint) / "state.eqx").is_file():
        raise ConfigError(f"{checkpoint} is not a checkpoint folder (no state.eqx).")
    try:
        config_dict = json.loads((run_dir / "config.json").read_text())
    except json.JSONDecodeError as error:
        raise ConfigError(f"{run_dir / 'config.json'}: not valid JSON ({error})") from None
    config = config_from_dict(config_dict, str(run_dir / "config.json"))
    if data_dir is not None:
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, data_dir=data_dir))
    dataset = load_dataset(config.data)
    model_key, train_key = jax.random.split(init_key(config))
    model = build_model(
        config, key=model_key, frustum=dataset.frustum, white_background=dataset.white_background
    )
    opt_state = make_optimizer(config).init(eqx.filter(model, eqx.is_array))
    model, _, step, train_key = load_checkpoint(checkpoint, model=model, opt_state=opt_state, key=train_key)
    step = read_checkpoint_meta(checkpoint).get("step", step)
    return config, dataset, model, step, checkpoint, train_key


def run(args: argparse.Namespace) -> dict:
    """Evaluates as `args` say and returns what was written to `metrics.json`."""
    import dataclasses

    import jax
    from tqdm.auto import tqdm

    from mixnerf_eqx._evaluate import evaluate
    from mixnerf_eqx._skipping import RenderStats
    from mixnerf_eqx._train import make_skipping, occupancy_for_model, render_summary, write_view_renders
    from mixnerf_eqx.data._splits import evenly_spaced
    from mixnerf_eqx.metrics import lpips_available

    run_dir = args.run_dir
    config, dataset, model, step, checkpoint, train_key = load_run(run_dir, args.checkpoint, args.data_dir)
    use_skipping = args.skipping == "on" or (args.skipping == "auto" and config.occupancy.enabled)
    chunk = args.chunk or (config.occupancy.chunk if use_skipping else config.train.render_chunk)

    view_ids = None
    if args.max_views > 0:
        view_ids = evenly_spaced(dataset.test.num_views, min(args.max_views, dataset.test.num_views))
    num_views = dataset.test.num_views if view_ids is None else len(view_ids)
    out = args.out or run_dir / "eval"
    out.mkdir(parents=True, exist_ok=True)
    views = dataset.test if view_ids is None else dataset.test.select(view_ids)
    subset = dataclasses.replace(dataset, test=views)
    bar = tqdm(total=num_views, disable=args.no_progress, unit="view", dynamic_ncols=True)

    def after_view(index: int, entry: dict, outputs) -> None:
        if not args.no_renders:
            write_view_renders(out, subset, index, entry["view"], outputs)
        bar.set_postfix(psnr=f"{entry['psnr']:.2f}")
        bar.update(1)

    started = time.perf_counter()
    grid = skipping = choice = None
    if use_skipping:
        grid, choice = occupancy_for_model(
            config, dataset, model, key=jax.random.fold_in(train_key, step), with_choice=True
        )
        skipping = make_skipping(config, grid)
    grid_seconds = time.perf_counter() - started
    stats = RenderStats()
    try:
        means, per_view = evaluate(
            model,
            subset,
            chunk=chunk,
            with_lpips=not args.no_lpips,
            on_view=after_view,
            skipping=skipping,
            stats=stats,
        )
    finally:
        bar.close()
    seconds = time.perf_counter() - started
    render = render_summary(stats, seconds - grid_seconds, num_views, grid, choice)
    render["grid_seconds"] = grid_seconds
    lpips_note = "computed"
    if args.no_lpips:
        lpips_note = "skipped (--no-lpips)"
    elif not lpips_available():
        lpips_note = "unavailable: install the lpips extra (pip install -e '.[lpips]')"
    result = {
        "run_dir": str(run_dir),
        "checkpoint": str(checkpoint),
        "step": step,
        "scene": dataset.name,
        "num_views": num_views,
        "lpips": lpips_note,
        "seconds": seconds,
        "render": render,
        "mean": means,
        "per_view": per_view,
    }
    (out / "metrics.json").write_text(json.dumps(result, indent=2))
    print(format_table(per_view, means))
    print(f"\n{dataset.name}, step {step}, {num_views} views in {seconds:.1f} s; LPIPS {lpips_note}")
    if grid is not None:
        how = "calibrated" if choice is not None else "from the config"
        if choice is not None and not choice.within_tolerance:
            how += f", no threshold kept the bound within {choice.tolerance_db} dB"
        print(
            f"skipping: density threshold {grid.threshold:.4g} ({how}), "
            f"{render['occupied_fraction']:.1%} of the grid occupied, "
            f"{render['field_evaluations_per_frame']:.0f} field evaluations per frame instead of "
            f"{render['dense_evaluations_per_frame']:.0f} ({render['evaluation_reduction']:.2f}x fewer)"
        )
    print(f"metrics: {out / 'metrics.json'}")
    if not args.no_renders:
        print(f"renders: {out}")
    return result


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.no_typecheck:
        os.environ["MIXNERF_EQX_TYPECHECK"] = "0"
    from mixnerf_eqx import ConfigError

    try:
        run(args)
    except (ConfigError, ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
