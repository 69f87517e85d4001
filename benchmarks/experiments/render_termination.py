"""How much does stopping finished rays add to the occupancy grid's skipping when rendering?

The skipping render (`mx.inference.Skipping`) drops two kinds of samples: those in cells the
grid marks empty (its threshold chosen on validation pixels, as `eval --skipping on` chooses
it) and those of rays already opaque, checked between `segments` pieces of each level, where
the transmittance has fallen below `stop_transmittance` (1e-4 in every config). The threshold
is chosen; the stopping point is not. This asks what other stopping points would give, with
the grid and threshold fixed as the run's config chooses them:

- on `--rays` pixels drawn from the validation views (the training views where a scene has
  none; never a test view): PSNR of the dense render and of each setting, and the field
  evaluations made against dense (padding included, `RenderCounts.reduction`);
- on the test views (all, or `--max-views` evenly spaced), for the record: the same;
- on the same validation pixels, what stopping could give at most: the share of each level's
  samples that lie behind the point where the dense coarse render's transmittance falls below
  each stopping point (were every one of them dropped, and nothing else).

One grid per run, then one render of those pixels and views per setting; each setting's
`stop_transmittance` and `segments` are static, so each compiles its own program.

    python benchmarks/experiments/render_termination.py runs/SWEEP/fern/seed_2 --data-dir ../shared/data \\
        --out benchmarks/results/render_termination_cpu_fern
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import mixnerf_eqx as mx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from harness import write_json, write_markdown  # noqa: E402

# (stop_transmittance, segments): the configs' setting first, then later stops, more pieces,
# and no stopping at all (the grid alone).
SETTINGS = ((1e-4, 4), (1e-3, 4), (1e-2, 4), (3e-2, 4), (1e-2, 8), (0.0, 4))
# The stopping points whose most possible savings are counted.
BOUND_STOPS = (1e-4, 1e-3, 1e-2, 3e-2, 0.1)


def psnr(rendered: np.ndarray, truth: np.ndarray) -> float:
    """Over every pixel given, pooled (any shape: pixels, or a stack of views)."""
    error = np.mean((np.asarray(rendered, np.float64) - np.asarray(truth, np.float64)) ** 2)
    return mx.metrics.mse_to_psnr(float(error))


@eqx.filter_jit
def _coarse_and_fine(model, rays):
    samples = model.sample_coarse(rays)
    coarse = model.composite(model.query_field(samples, rays), samples, rays)
    return coarse.weights, coarse.t_edges, model.sample_fine(rays, coarse).t_edges


def finished_shares(model, rays, chunk: int, stops) -> dict[str, dict[str, float]]:
    """Per stopping point: the share of coarse and of fine samples whose interval starts where
    the coarse level's transmittance (1 minus the weights in front) is already below it."""
    behind = {stop: [0, 0] for stop in stops}
    total = [0, 0]
    flat = rays.reshape(-1)
    count = flat.origins.shape[0]
    for start in range(0, count, chunk):
        rows = slice(start, start + chunk)
        piece = jax.tree_util.tree_map(lambda x, rows=rows: jnp.asarray(x[rows]), flat)
        weights, edges, fine_edges = (np.asarray(a, np.float64) for a in _coarse_and_fine(model, piece))
        in_front = np.concatenate([np.zeros_like(weights[:, :1]), np.cumsum(weights, axis=-1)], axis=-1)
        coarse_lit = 1.0 - in_front[:, :-1]
        # A fine interval lies in the coarse interval holding its start.
        holder = np.stack(
            [np.searchsorted(e, f[:-1], side="right") - 1 for e, f in zip(edges, fine_edges, strict=True)]
        )
        holder = np.clip(holder, 0, weights.shape[-1])
        fine_lit = 1.0 - np.take_along_axis(in_front, holder, axis=-1)
        for stop in stops:
            behind[stop][0] += int(np.sum(coarse_lit < stop))
            behind[stop][1] += int(np.sum(fine_lit < stop))
        total[0] += coarse_lit.size
        total[1] += fine_lit.size
    return {
        f"{stop:g}": {"coarse": behind[stop][0] / total[0], "fine": behind[stop][1] / total[1]}
        for stop in stops
    }


def probe(run_dir: str, args) -> dict:
    run = mx.runs.restore_run(run_dir, data_dir=args.data_dir)
    dataset, occupancy = run.dataset, run.config.occupancy
    started = time.perf_counter()
    grid, choice = mx.runs.grid_for_rendering(occupancy, dataset, run.model, key=jax.random.PRNGKey(0))
    grid_seconds = time.perf_counter() - started
    split = "val" if dataset.val is not None else "train"
    rays, colours = mx.inference.threshold_rays(dataset, args.rays, key=jax.random.PRNGKey(1), split=split)
    test = dataset.test
    if args.max_views and args.max_views < test.num_views:
        chosen = np.linspace(0, test.num_views - 1, args.max_views).round().astype(int).tolist()
        test = test.select(chosen)
    dense = mx.inference.render_rays(run.model, rays, args.chunk)
    dense_test = mx.inference.render_views(run.model, test, dataset.near, dataset.far, args.chunk)
    record = {
        "run": run_dir,
        "step": run.step,
        "pixels_from": split,
        "pixels": int(colours.shape[0]),
        "test_views": test.num_views,
        "threshold": float(grid.threshold),
        "threshold_choice": None if choice is None else dataclasses.asdict(choice),
        "occupied": float(grid.occupied_fraction()),
        "grid_s": grid_seconds,
        "pixels_psnr_dense": psnr(dense.rgb, colours),
        "test_psnr_dense": psnr(dense_test.rgb, test.images),
        "settings": [],
        "behind_stop": finished_shares(run.model, rays, args.chunk, BOUND_STOPS),
    }
    occupied = f"{record['occupied']:.1%} of cells occupied"
    print(f"{run_dir}: threshold {record['threshold']:.4g}, {occupied}", flush=True)
    for stop, segments in SETTINGS:
        skipping = mx.inference.Skipping(
            grid=grid, stop_transmittance=stop, segments=segments, chunk=occupancy.render_chunk_points or None
        )
        pixels = mx.inference.render_rays(run.model, rays, args.chunk, skipping=skipping)
        views = mx.inference.render_views(
            run.model, test, dataset.near, dataset.far, args.chunk, skipping=skipping
        )
        row = {
            "stop_transmittance": stop,
            "segments": segments,
            "pixels_psnr_change": psnr(pixels.rgb, colours) - record["pixels_psnr_dense"],
            "pixels_fewer": pixels.counts.reduction,
            "test_psnr_change": psnr(views.rgb, test.images) - record["test_psnr_dense"],
            "test_fewer": views.counts.reduction,
        }
        record["settings"].append(row)
        print(f"  {row}", flush=True)
    return record


def table(records: list[dict]) -> str:
    lines = [
        "| run | stop_transmittance | segments | fewer evaluations (validation pixels) | PSNR change there "
        "| fewer evaluations (test views) | test PSNR change |",
        "|---|---|---|---|---|---|---|",
    ]
    for record in records:
        for row in record["settings"]:
            cells = (
                record["run"],
                f"{row['stop_transmittance']:g}",
                str(row["segments"]),
                f"{row['pixels_fewer']:.2f}x",
                f"{row['pixels_psnr_change']:+.3f}",
                f"{row['test_fewer']:.2f}x",
                f"{row['test_psnr_change']:+.3f}",
            )
            lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "| run | stopping point | coarse samples behind it | fine samples behind it (validation pixels) |",
        "|---|---|---|---|",
    ]
    for record in records:
        for stop, share in record["behind_stop"].items():
            lines.append(f"| {record['run']} | {stop} | {share['coarse']:.3f} | {share['fine']:.3f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--rays", type=int, default=16384, help="validation pixels rendered per setting")
    parser.add_argument("--max-views", type=int, default=0, help="test views, evenly spaced (0: all)")
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--out", default=None, help="write OUT.json and OUT.md")
    args = parser.parse_args()
    records = [probe(run_dir, args) for run_dir in args.runs]
    text = table(records)
    print(text)
    if args.out:
        write_json(Path(args.out + ".json"), {"records": records, "argv": sys.argv[1:]})
        write_markdown(Path(args.out + ".md"), text + "\n")


if __name__ == "__main__":
    main()
