"""Empty-space skipping and early ray termination: field evaluations, render time and PSNR.

Renders the test views of a trained run densely (every sample evaluated) and with the
skipping renderer at a grid of settings (occupancy threshold, dilation, termination
threshold), and reports per frame: field (MLP) evaluations made and needed, the reduction
against dense, seconds, and the PSNR change. The target (issue: "at least 3x fewer MLP
evaluations per rendered lego frame, with PSNR within 0.1 dB") is checked for the best
setting that loses at most 0.1 dB, and the shortfall is printed if it is missed; the best
setting whose PSNR stays within +-0.1 dB of dense (the same image, not a less foggy one) is
printed beside it.

    python benchmarks/skipping.py RUN_DIR [--data-dir ../shared/data] [--max-views 4]

The run is read with `mx.runs.restore_run`, and the occupancy grid rebuilt from the checkpoint by
`mx.runs.grid_for_rendering` (every cell evaluated once); its cost is reported as `grid_seconds`.
The `--thresholds` rows use each threshold as given; the `--calibrate` rows (one per
tolerance) let `mixnerf_eqx.inference.choose_threshold` choose it on `--calibrate-rays` pixels
of the views and by the measure the run's config names (`occupancy.threshold_views`,
`occupancy.threshold_measure`: validation pixels and the PSNR lost there by default, training
pixels and the bound where a scene has no validation views), starting from the smallest of
`--thresholds`, as `fit` and `python -m mixnerf_eqx.eval` do with `occupancy.choose_threshold` on; their `grid_seconds` include the calibration. Each setting
renders the selected views twice and times the second pass, so that compiling the buffer sizes
a setting needs is not timed.

Output: `--out`, default `benchmarks/results/skipping_<backend>_<scene>.json`, with the command
that made it (`"command"`) and the machine.
"""

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np
from harness import RESULTS, grid_threshold, platform_tag, write_json

import mixnerf_eqx as mx
from mixnerf_eqx.data import evenly_spaced
from mixnerf_eqx.metrics import psnr


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path, help="a trained run (config.json, checkpoints/)")
    parser.add_argument("--data-dir", default=None, help="dataset root (default: the run's)")
    parser.add_argument("--max-views", type=int, default=4, help="test views, evenly spaced")
    parser.add_argument("--chunk", type=int, default=16384, help="rays per chunk (both renderers)")
    parser.add_argument("--resolution", type=int, default=128, help="occupancy grid cells per axis")
    parser.add_argument("--box-radius", type=float, default=None, help="grid box (default: the run's)")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.01, 0.1, 0.5, 1.0, 2.0])
    parser.add_argument("--dilations", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--stops", type=float, nargs="+", default=[0.0, 1e-4, 1e-3, 1e-2])
    parser.add_argument("--segments", type=int, default=4, help="pieces per level for termination")
    parser.add_argument(
        "--calibrate",
        type=float,
        nargs="*",
        default=[0.1],
        metavar="TOLERANCE_DB",
        help="also calibrate the threshold to these tolerances on the PSNR lost (none: skip)",
    )
    parser.add_argument("--calibrate-rays", type=int, default=4096, help="pixels for calibrating (of the views the run's config names)")
    parser.add_argument(
        "--out", type=Path, default=None, help="result JSON (default: benchmarks/results/skipping_*)"
    )
    return parser.parse_args(argv)


def _render(model, views, dataset, chunk, skipping):
    """Renders every view once; returns the images, seconds per frame and the counts."""
    counts = mx.inference.RenderCounts()
    rgb = np.empty((views.num_views, views.height, views.width, 3), np.float32)
    seconds = []
    for index in range(views.num_views):
        started = time.perf_counter()
        out = mx.render_views(
            model, views.select([index]), dataset.near, dataset.far, chunk, skipping=skipping
        )
        seconds.append(time.perf_counter() - started)
        rgb[index] = out.rgb[0]
        counts = counts + out.counts
    return rgb, float(np.median(seconds)), counts


def main(argv=None):
    args = parse_args(argv)
    run = mx.runs.restore_run(args.run_dir, data_dir=args.data_dir)
    dataset, model, step, key = run.dataset, run.model, run.step, run.state.key
    occupancy = dataclasses.replace(run.config.occupancy, resolution=args.resolution)
    if args.box_radius is not None:
        occupancy = dataclasses.replace(occupancy, box_radius=args.box_radius)
    ids = evenly_spaced(dataset.test.num_views, min(args.max_views, dataset.test.num_views))
    views = dataset.test.select(ids)
    pixels = views.height * views.width

    def score(rgb):
        return float(np.mean([psnr(rgb[i], views.images[i]) for i in range(views.num_views)]))

    mx.render_views(model, views.select([0]), dataset.near, dataset.far, args.chunk)  # compile
    dense_rgb, dense_seconds, dense_counts = _render(model, views, dataset, args.chunk, None)
    dense_psnr = score(dense_rgb)
    print(f"{dataset.name}, step {step}, {views.num_views} views of {views.height}x{views.width}")
    print(
        f"dense: {dense_counts.dense_evaluations / views.num_views:.0f} evaluations/frame, "
        f"{dense_seconds:.3f} s/frame, PSNR {dense_psnr:.3f}"
    )

    rows = []
    # (threshold, calibration tolerance or None): fixed thresholds first, then calibrated ones.
    grids = [(threshold, None) for threshold in args.thresholds]
    grids += [(min(args.thresholds), tolerance) for tolerance in args.calibrate]
    for threshold, tolerance in grids:
        for dilation in args.dilations:
            grid_occupancy = dataclasses.replace(
                occupancy,
                density_threshold=threshold,
                dilation=dilation,
                choose_threshold=tolerance is not None,
                threshold_tolerance_db=0.0 if tolerance is None else tolerance,
                threshold_rays=args.calibrate_rays,
                stop_transmittance=min(args.stops),
            )
            started = time.perf_counter()
            grid, _ = mx.runs.grid_for_rendering(
                grid_occupancy, dataset, model, key=jax.random.fold_in(key, step)
            )
            grid.density.block_until_ready()
            grid_seconds = time.perf_counter() - started
            threshold_used = grid_threshold(grid)
            for stop in args.stops:
                skipping = mx.inference.Skipping(grid=grid, stop_transmittance=stop, segments=args.segments)
                mx.render_views(
                    model, views.select([0]), dataset.near, dataset.far, args.chunk, skipping=skipping
                )
                rgb, seconds, counts = _render(model, views, dataset, args.chunk, skipping)
                value = score(rgb)
                row = {
                    "threshold": threshold_used,
                    "calibrated_to_db": tolerance,
                    "dilation": dilation,
                    "stop_transmittance": stop,
                    "occupied_fraction": float(grid.occupied_fraction()),
                    "evaluations_per_frame": counts.padded_evaluations / views.num_views,
                    "needed_per_frame": counts.field_evaluations / views.num_views,
                    "reduction": counts.reduction,
                    "seconds_per_frame": seconds,
                    "speedup": dense_seconds / seconds,
                    "psnr": value,
                    "psnr_change": value - dense_psnr,
                    "grid_seconds": grid_seconds,
                }
                rows.append(row)
                how = "" if tolerance is None else f" (calibrated to {tolerance:g} dB)"
                print(
                    f"threshold {threshold_used:<6g}{how} dilation {dilation} stop {stop:<6g} "
                    f"occupied {row['occupied_fraction']:6.1%}  "
                    f"evals/frame {row['evaluations_per_frame']:>10.0f} "
                    f"({row['reduction']:5.2f}x fewer)  {seconds:7.3f} s/frame ({row['speedup']:4.2f}x)  "
                    f"PSNR {value:7.3f} ({row['psnr_change']:+.3f})",
                    flush=True,
                )
    within = [r for r in rows if r["psnr_change"] >= -0.1]
    best = max(within, key=lambda r: r["reduction"]) if within else None
    if best is None:
        verdict = "no setting stays within 0.1 dB"
    elif best["reduction"] >= 3:
        verdict = (
            f"target met: {best['reduction']:.2f}x fewer evaluations, PSNR {best['psnr_change']:+.3f} dB"
        )
    else:
        verdict = (
            f"target missed: the best setting within 0.1 dB gives {best['reduction']:.2f}x fewer "
            f"evaluations (target 3x, short by {3 - best['reduction']:.2f}x)"
        )
    # The target reads "no more than 0.1 dB lower". Skipping a hazy model's low density can
    # also raise the PSNR (less fog in front of the background): then the image is not the
    # dense one. The stricter reading, |change| <= 0.1 dB, is reported beside it.
    same_image = [r for r in rows if abs(r["psnr_change"]) <= 0.1]
    best_same = max(same_image, key=lambda r: r["reduction"]) if same_image else None
    if best_same is None:
        verdict += "; no setting keeps the PSNR within +-0.1 dB of dense"
    else:
        verdict += (
            f"; within +-0.1 dB of dense: {best_same['reduction']:.2f}x fewer "
            f"(PSNR {best_same['psnr_change']:+.3f} dB)"
        )
    print(verdict)
    empty = mx.training.make_occupancy_grid(occupancy, dataset)
    result = {
        "run_dir": str(args.run_dir),
        "scene": dataset.name,
        "step": step,
        "views": [int(i) for i in views.ids],
        "pixels_per_frame": pixels,
        "grid": {
            "resolution": args.resolution,
            "box_min": np.asarray(empty.box_min).tolist(),
            "box_max": np.asarray(empty.box_max).tolist(),
            "outside_occupied": empty.outside_occupied,
        },
        "dense": {
            "evaluations_per_frame": dense_counts.dense_evaluations / views.num_views,
            "seconds_per_frame": dense_seconds,
            "psnr": dense_psnr,
        },
        "settings": rows,
        "best_within_0.1dB": best,
        "best_within_plus_minus_0.1dB": best_same,
        "verdict": verdict,
    }
    write_json(args.out or RESULTS / f"skipping_{platform_tag()}_{dataset.name}.json", result)


if __name__ == "__main__":
    main()
