"""Evaluate a run: `python -m mixnerf_eqx.eval RUN_DIR [--checkpoint DIR] [--data-dir DIR] [...]`.

Loads the run's config and its latest (or the given) checkpoint, renders the test views one at
a time in chunks of rays (memory stays bounded whatever the resolution), writes per-image and
mean metrics to `RUN_DIR/eval/metrics.json` with colour and depth PNGs beside it, and prints a
table. LPIPS needs the optional `lpips` extra; without it LPIPS is reported as unavailable.
With `--uncertainty` it also writes the predictive distribution's spread beside the error maps,
the arrays in `uncertainty.npz`, depth and its interval as `.npy` arrays in scene units, a
coloured point cloud per view (`.ply`, each point with its uncertainty), and the calibration
measures; the intervals are recalibrated on the scene's validation views (`--calibration`,
default conformal; `docs/predictive.md`). Last, it
draws the run's training curves from its log into `RUN_DIR/curves.png` (with matplotlib).
"""

import argparse
import contextlib
import json
import math
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np

from .._config import ConfigError
from .._inference.evaluation import evaluate
from .._inference.rendering import Rendered
from .._predictive.exports import write_depth_exports
from .._predictive.recalibration import METHODS, Recalibration
from .._predictive.uncertainty import (
    depths_are_ray_distances,
    calibration_report,
    coverage_report,
    fit_recalibration,
    predict_views,
    write_uncertainty_maps,
)
from .._runs.run_folder import (
    Run,
    dataset_record,
    grid_for_rendering,
    make_skipping,
    render_summary,
    restore_run,
    write_view_renders,
)
from .._util import json_io as strict_json
from .._util.compilation_cache import add_compilation_cache_argument
from .._util.curves import plot_curves
from .._util.interrupt import raise_if_interrupted
from .._util.lock import hold_folder
from .._util.progress import Progress
from .._util.typecheck import add_typecheck_argument
from ..data import evenly_spaced
from ..metrics import lpips_available
from .common import add_run_arguments, add_skipping_argument, run_command

METRIC_COLUMNS = ("psnr", "ssim", "lpips", "average", "depth_mae")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.eval", description=__doc__.split("\n")[0])
    add_run_arguments(parser)
    parser.add_argument(
        "--chunk", type=int, default=None, help="rays rendered at once, at most a view's (default: the run's)"
    )
    parser.add_argument(
        "--split",
        choices=("test", "val"),
        default="test",
        help="the views to score: the protocol's test views (scored once, for the record), or the "
        "validation views that settings are chosen on (default: test)",
    )
    parser.add_argument(
        "--max-views",
        type=int,
        default=0,
        help="evaluate this many of the split's views, evenly spaced (0: all)",
    )
    add_skipping_argument(parser)
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: RUN_DIR/eval, or RUN_DIR/eval_val for --split val)",
    )
    parser.add_argument("--no-renders", action="store_true", help="write no PNGs")
    parser.add_argument(
        "--uncertainty",
        action="store_true",
        help="also write the predictive distribution's spread (PNGs beside the error maps, arrays in "
        "uncertainty.npz) and its calibration against the true pixels (docs/predictive.md)",
    )
    parser.add_argument(
        "--temperature",
        type=float,
        default=None,
        help="with --uncertainty: multiply every beta by this factor (a post-hoc calibration; default 1)",
    )
    parser.add_argument(
        "--calibration",
        choices=METHODS,
        default=None,
        help="with --uncertainty: how the intervals are recalibrated, fitted on the scene's validation "
        "views: conformal (a coverage guarantee for exchangeable pixels; the default where the scene has "
        "validation views and they are not the views scored), isotonic, or raw (the model's own intervals)",
    )
    parser.add_argument("--no-lpips", action="store_true", help="skip LPIPS (and the average)")
    add_typecheck_argument(parser)
    add_compilation_cache_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser.parse_intermixed_args(argv)


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


def _skipping_for(run: Run, mode: str):
    """The grid, skipping options and threshold choice `--skipping` asks for, and its time."""
    started = time.perf_counter()
    config = run.config
    if not (mode == "on" or (mode == "auto" and config.occupancy.renders_skip)):
        return None, None, None, 0.0
    grid, choice = grid_for_rendering(
        config.occupancy, run.dataset, run.model, key=jax.random.fold_in(run.state.key, run.step)
    )
    return grid, make_skipping(config.occupancy, grid), choice, time.perf_counter() - started


def _print_summary(result: dict, grid, choice, out: Path, renders: bool) -> None:
    print(format_table(result["per_view"], result["mean"]))
    print(
        f"\n{result['scene']}, step {result['step']}, {result['num_views']} views in "
        f"{result['seconds']:.1f} s; LPIPS {result['lpips']}"
    )
    render = result["render"]
    if grid is not None:
        how = "from the config"
        if choice is not None:
            pixels = "validation" if choice.views == "val" else "training"
            measure = "the PSNR lost there" if choice.measure == "psnr" else "a bound on the PSNR lost"
            how = f"chosen on {pixels} pixels by {measure}"
        if choice is not None and not choice.within_tolerance:
            how += f", no threshold kept the loss within {choice.tolerance_db} dB"
        print(
            f"skipping: density threshold {float(grid.threshold):.4g} ({how}), "
            f"{render['occupied_fraction']:.1%} of the grid occupied, "
            f"{render['field_evaluations_per_frame']:.0f} field evaluations per frame instead of "
            f"{render['dense_evaluations_per_frame']:.0f} ({render['evaluation_reduction']:.2f}x fewer)"
        )
    if "uncertainty" in result:
        report = result["uncertainty"]
        calibrated = report["calibration"]
        coverage = ", ".join(
            f"{mass}: {value['pooled']:.3f} (raw {report['coverage'][mass]['mean']:.3f})"
            for mass, value in calibrated["colour_coverage"].items()
        )
        depth = "n/a" if report["depth_ause"] is None else f"{report['depth_ause']:.4f}"
        depth_coverage = calibrated["depth_coverage"]
        if depth_coverage is not None:
            depth_cells = ", ".join(f"{mass}: {value['pooled']:.3f}" for mass, value in depth_coverage.items())
            coverage += f"; depth coverage {depth_cells}"
        how = (
            "the model's own intervals"
            if calibrated["method"] == "raw"
            else f"{calibrated['method']} intervals (fitted on {calibrated['fitted_on']})"
        )
        print(
            f"uncertainty: {how}, colour "
            f"coverage {coverage}; calibration error {calibrated['calibration_error']:.4f}, NLL "
            f"{calibrated['nll_per_channel']:.3f} per channel; AUSE colour {report['colour_ause']:.4f}, depth "
            f"{depth}; {report['seconds_per_frame']:.2f} s per frame; arrays: {out / 'uncertainty.npz'}, "
            f"depth (.npy) and point clouds (.ply) per view"
        )
    unbounded = result.get("uncertainty", {}).get("calibration", {}).get("unbounded", {})
    for what, masses in unbounded.items():
        if masses:
            listed = ", ".join(f"{mass:g}" for mass in masses)
            print(
                f"note: the {what} intervals of mass {listed} have an end without bound (the range's end): "
                "more validation truths fell beyond the model's predictive distribution on that side than "
                "the interval may miss"
            )
    print(f"metrics: {out / 'metrics.json'}")
    if renders:
        print(f"renders: {out}")


def run(args: argparse.Namespace) -> dict:
    """Evaluates as `args` say and returns what was written to `metrics.json`."""
    run_dir = args.run_dir
    restored = restore_run(run_dir, checkpoint=args.checkpoint, data_dir=args.data_dir)
    config, dataset = restored.config, restored.dataset
    if args.uncertainty:  # before anything is rendered: what the intervals can be fitted on
        args.calibration = _calibration_method(restored, args.calibration, args.split)
    views = dataset.split(args.split)  # a split the scene lacks: one line, status 2
    view_ids = None
    if args.max_views > 0:
        view_ids = evenly_spaced(views.num_views, min(args.max_views, views.num_views))
    num_views = views.num_views if view_ids is None else len(view_ids)
    final = args.out or run_dir / ("eval" if args.split == "test" else f"eval_{args.split}")
    # One evaluation at a time into a folder: a second one is refused before it builds a grid
    # or touches the first one's staging folder or results.
    lock, target = contextlib.ExitStack(), final.resolve()
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        lock.enter_context(
            hold_folder(target.parent, "evaluation", "--out", name=f".{target.name}.eval.lock", label=final)
        )
    except PermissionError:
        raise ConfigError(f"{final.parent} is not writable: give --out a folder you can write to") from None
    with lock:
        grid, skipping, choice, grid_seconds = _skipping_for(restored, args.skipping)
        chunk = args.chunk or (config.occupancy.chunk if skipping is not None else config.train.render_chunk)
        out = _staging_folder(final)
        try:
            bar = Progress(num_views, unit="view", enabled=not args.no_progress)
            chosen = views if view_ids is None else views.select(view_ids)

            def after_view(index: int, entry: dict, rendered: Rendered) -> None:
                if not args.no_renders:
                    truth = chosen.images[index]
                    write_view_renders(out, entry["view"], rendered, truth, near=dataset.near, far=dataset.far)
                bar.update(index + 1, psnr=f"{entry['psnr']:.2f}")

            try:
                evaluation = evaluate(
                    restored.model,
                    dataset,
                    chunk=chunk,
                    view_ids=view_ids,
                    with_lpips=not args.no_lpips,
                    on_view=after_view,
                    skipping=skipping,
                    split=args.split,
                )
            finally:
                bar.close()
            render = render_summary(evaluation.counts, evaluation.seconds, num_views, grid, choice)
            render["grid_seconds"] = grid_seconds
            lpips_note = "computed"
            if args.no_lpips:
                lpips_note = "skipped (--no-lpips)"
            elif not lpips_available():
                lpips_note = "unavailable: install the lpips extra (pip install -e '.[lpips]')"
            result = {
                "run_dir": str(run_dir),
                "checkpoint": str(restored.checkpoint),
                "step": restored.step,
                "scene": dataset.name,
                "dataset": dataset_record(config, dataset),
                "split": args.split,
                "num_views": num_views,
                "lpips": lpips_note,
                "seconds": evaluation.seconds + grid_seconds,
                "render": render,
                "mean": evaluation.means,
                "per_view": evaluation.per_view,
            }
            if args.uncertainty:
                result["uncertainty"] = _uncertainty(
                    restored,
                    chosen,
                    chunk,
                    out,
                    temperature=args.temperature,
                    renders=not args.no_renders,
                    method=args.calibration,
                )
            (out / "metrics.json").write_text(strict_json.dumps(result, indent=2))
            raise_if_interrupted()  # a Ctrl-C during the evaluation stops it before the replacement
            _put_in_place(out, final)
        except BaseException:
            shutil.rmtree(out, ignore_errors=True)  # the results there were stay whole
            raise
        args.results_in_place = final  # what a Ctrl-C from here on says
        _print_summary(result, grid, choice, final, not args.no_renders)
        # After the results are in place: the run's training curves, beside its log.
        curves = plot_curves(run_dir)
        if curves is not None:
            result["curves"] = str(curves)
            staged = final / "metrics.json.partial"
            staged.write_text(strict_json.dumps(result, indent=2))
            staged.replace(final / "metrics.json")
            print(f"training curves: {curves}")
        return result


# What eval writes: a folder holding anything else is not replaced (`--out` may name a folder
# of the user's), and a folder is eval's only where its marker (or an eval's metrics.json, from
# before the marker) says so.
_EVAL_SUFFIXES = {".png", ".json", ".npz", ".npy", ".ply"}
_MARKER = ".mixnerf_eval"


def _written_by_eval(folder: Path) -> bool:
    """Whether `folder` is an evaluation's output: it holds eval's marker, or an eval's
    `metrics.json` (with its run and per-view entries) and nothing but eval's kinds of file."""
    if not folder.is_dir():
        return False
    if (folder / _MARKER).is_file():
        return True
    metrics = folder / "metrics.json"
    try:
        written = json.loads(metrics.read_text())
    except (OSError, ValueError):
        return False
    if not isinstance(written, dict) or not {"run_dir", "per_view", "split"} <= set(written):
        return False
    return all(p.is_file() and p.suffix in _EVAL_SUFFIXES for p in folder.iterdir())


def _staging_folder(final: Path) -> Path:
    """A fresh folder beside `final` that receives every file of this evaluation; it replaces
    `final` only when all are written (`_put_in_place`), so that an interrupted or failed
    evaluation leaves the results there were whole. Only folders eval wrote are ever replaced
    or removed."""
    _recover(final)
    if final.exists() and not (final.is_dir() and not any(final.iterdir())) and not _written_by_eval(final):
        foreign = [p.name for p in final.iterdir()] if final.is_dir() else []
        listed = ", ".join(sorted(foreign)[:3]) or "it is a file"
        raise ConfigError(
            f"{final} holds files eval did not write ({listed}): give --out a new or empty folder"
        )
    staging = final.with_name(final.name + ".partial")
    if staging.exists():
        if not _written_by_eval(staging) and any(staging.iterdir() if staging.is_dir() else [staging]):
            raise ConfigError(f"{staging} exists and eval did not write it: move it away, or give another --out")
        shutil.rmtree(staging, ignore_errors=True)
    try:
        staging.mkdir(parents=True)
    except PermissionError:
        raise ConfigError(f"{final.parent} is not writable: give --out a folder you can write to") from None
    except FileExistsError:
        raise ConfigError(f"{staging} is in the way (a file): move it away, or give another --out") from None
    (staging / _MARKER).write_text("written by python -m mixnerf_eqx.eval\n")
    return staging


def _recover(final: Path) -> None:
    """Undoes a replacement cut short between its two renames (the old results come back).
    Only a `.old` folder that eval wrote is touched."""
    old = final.with_name(final.name + ".old")
    if not _written_by_eval(old):
        return
    if not final.exists():
        old.rename(final)
    else:
        shutil.rmtree(old, ignore_errors=True)


def _put_in_place(staging: Path, final: Path) -> None:
    """Replaces `final` by `staging`: rename the old folder aside, the new one into place, and
    remove the old one."""
    old = final.with_name(final.name + ".old")
    if old.exists():  # not eval's (`_recover` took eval's): in the way
        raise ConfigError(f"{old} exists and eval did not write it: move it away, or give another --out")
    if final.exists():
        final.rename(old)
    staging.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def _calibration_method(restored: Run, asked: str | None, split: str) -> str:
    """The recalibration `eval --uncertainty` fits, checked before anything is rendered: the
    one asked for, or by default conformal where the scene has validation views that are not
    the views being scored (else the model's own intervals, said in one line)."""
    if restored.model.mixture is None:
        raise ConfigError("--uncertainty reads the mixture: this run's model (the mip-NeRF baseline) has none")
    dataset = restored.dataset
    has_val = dataset.val is not None and dataset.val.num_views > 0
    if asked is None:
        if split == "val" or not has_val:
            why = "the views scored are the validation views" if split == "val" else f"{dataset.name} has no validation views"
            print(f"uncertainty: the model's own intervals ({why}, which recalibration is fitted on)")
            return "raw"
        return "conformal"
    if asked != "raw" and split == "val":
        raise ConfigError(
            f"--calibration {asked} is fitted on the validation views, so it cannot score them: "
            "use --calibration raw with --split val"
        )
    if asked != "raw" and not has_val:
        raise ConfigError(
            f"{dataset.name} has no validation views to calibrate the intervals on ({dataset.val_source}): "
            "give --calibration raw for the model's own intervals"
        )
    return asked


def _recalibration(restored: Run, chunk: int, *, method: str, temperature: float) -> Recalibration:
    """`method` fitted on the scene's validation views (never on the views being scored;
    `_calibration_method` checked that)."""
    if method == "raw":
        return Recalibration.raw()
    dataset = restored.dataset
    try:
        return fit_recalibration(
            restored.model,
            dataset.val,
            dataset.near,
            dataset.far,
            method,
            chunk=chunk,
            temperature=temperature,
            description=f"the {dataset.val.num_views} validation views",
        )
    except ValueError as error:  # too few calibration pixels for the masses
        raise ConfigError(f"--calibration {method}: {error}") from None


def _uncertainty(
    restored: Run, views, chunk: int, out: Path, *, temperature: float, renders: bool, method: str
) -> dict:
    """The predictive pass over `views`, its intervals recalibrated by `method`: maps (PNGs
    unless `renders` is false, arrays in `uncertainty.npz`, depth `.npy` and point clouds) and
    the calibration measures."""
    recalibration = _recalibration(restored, chunk, method=method, temperature=temperature)
    started = time.perf_counter()
    dataset = restored.dataset
    maps = predict_views(
        restored.model,
        views,
        dataset.near,
        dataset.far,
        chunk,
        temperature=temperature,
        masses=recalibration.masses,
        levels=recalibration.interval_levels(),
    )
    seconds = time.perf_counter() - started
    np.savez_compressed(out / "uncertainty.npz", view_ids=np.asarray(views.ids), **maps)
    write_depth_exports(out, views, maps, near=dataset.near, far=dataset.far)
    if renders:
        write_uncertainty_maps(out, views, maps, near=dataset.near, far=dataset.far)
    # True depths count where they are distances along the rendered rays (not NDC, DTU's planes).
    depths = views.depths if depths_are_ray_distances(views) else None
    report = calibration_report(maps, views.images, depths)
    # "coverage" stays the model's own intervals' (beside the raw NLL), read from the
    # distribution functions at the truths: the central interval of mass m covers a truth
    # whose PIT value u has |2u - 1| <= m. "calibration" has the recalibrated intervals'.
    scores = np.abs(2.0 * maps["colour_cdf"].astype(np.float64) - 1.0)
    report["coverage"] = {}
    for mass in recalibration.masses:
        per_channel = (scores <= mass).reshape(-1, scores.shape[-1]).mean(axis=0)
        report["coverage"][f"{mass:g}"] = {"per_channel": per_channel.tolist(), "mean": float(per_channel.mean())}
    report["calibration"] = coverage_report(maps, views.images, depths, recalibration)
    report["calibration"]["levels"] = recalibration.to_json()
    report["temperature"] = temperature
    report["seconds_per_frame"] = seconds / max(views.num_views, 1)
    return report


# The temperatures eval accepts: far wider than any fitted one (0.9 to 1.5 in the benchmarks).
_TEMPERATURES = (1e-3, 1e3)


def _check_arguments(args: argparse.Namespace) -> None:
    if args.chunk is not None and args.chunk < 1:
        raise ConfigError(f"--chunk must be a positive number of rays, got {args.chunk}")
    if args.temperature is not None and not args.uncertainty:
        raise ConfigError("--temperature scales the predictive distribution: it needs --uncertainty")
    if args.calibration is not None and not args.uncertainty:
        raise ConfigError("--calibration recalibrates the predictive intervals: it needs --uncertainty")
    if args.temperature is None:
        args.temperature = 1.0
    if not (math.isfinite(args.temperature) and _TEMPERATURES[0] <= args.temperature <= _TEMPERATURES[1]):
        raise ConfigError(
            f"--temperature must lie in [{_TEMPERATURES[0]:g}, {_TEMPERATURES[1]:g}] (a factor on every beta; "
            f"beyond that the scales leave float32's range), got {args.temperature:g}"
        )
    if args.max_views < 0:
        raise ConfigError(f"--max-views must be 0 (all test views) or positive, got {args.max_views}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    args.results_in_place = None

    def body() -> None:
        _check_arguments(args)
        try:
            run(args)
        except KeyboardInterrupt:
            if args.results_in_place is None:
                print("\ninterrupted: evaluation stopped; nothing was changed in the run", file=sys.stderr)
            else:
                print(
                    f"\ninterrupted: the evaluation's results are in place in {args.results_in_place}; the "
                    "training curves were not drawn",
                    file=sys.stderr,
                )
            raise

    return run_command(args, body)


if __name__ == "__main__":
    sys.exit(main())
