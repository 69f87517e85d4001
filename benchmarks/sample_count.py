"""The sample-count study (paper Table 5): quality and render time against samples per ray.

    # GPU: LLFF fern 3-view, the paper model, 128/64/32/16/8 samples per level, 2000 steps each
    python benchmarks/sample_count.py --data-dir ../shared/data

    # lego 4-view as well (8 of its 200 test views)
    python benchmarks/sample_count.py --data-dir ../shared/data --scene fern --scene lego --eval-views 8

    # CPU: a CPU-sized MLP and batch, fewer steps, 2x-downsampled test views
    python benchmarks/sample_count.py --data-dir ../shared/data --steps 300 --eval-downscale 2 \\
        --set mlp.width=64 mlp.depth=4 mlp.skip_layer=2 mlp.view_width=32 train.batch_size=512

For each scene, each sample count N (N coarse + N fine samples per ray, the paper's "samples
per ray at each level") and each variant (default: `mixnerf`, the scene's paper config, and
`mipnerf`, the same with `method = "mipnerf"`), a model is trained for `--steps` steps (the
schedule is set to that length: `train.max_steps = --steps`, with warm-up, lambda_C ramp and
annealing cut to 1/10, 1/10 and 1/5 of it where longer), by the library's jitted step compiled
ahead of time (`harness.TrainingRun`). Then every evaluation view (`--eval-views` evenly
spaced test views, 0: all of the protocol's; `--eval-downscale` area-downsamples them, a proxy
for cheap CPU runs) is rendered once by `render_frame`, after one warm-up render of the first
view, and scored: PSNR, SSIM and LPIPS (where `mixnerf_eqx.metrics.lpips_available()`), with
the DTU masks where a scene has them. Reported per run: the metrics, the median seconds per
full frame over the views (ray generation on the host, rendering and the copy back, as
`mx.render_views` does it), the render compile time (the warm-up render minus that median),
and the field (MLP) evaluations per frame, pixels x (coarse + fine) for the dense renderer
(also with the last chunk's padding). With `--skipping` (the default) every model is also rendered by the
renderer that skips empty space and finished rays, with a grid built from the trained model
and the config's `[occupancy]` settings (`mx.runs.grid_for_rendering`: the threshold chosen
when `occupancy.choose_threshold` is on; `--set occupancy.density_threshold=...` changes them), and
its PSNR, seconds and evaluations per frame are reported beside the dense ones.

Outputs: `sample_count_<tag>.jsonl` in `--out` (default benchmarks/results; tag: the JAX
backend), one line per finished run, appended as the study goes (so a stopped study keeps
its finished runs); `sample_count_<tag>.json` with every run and the machine at the end; a
printed table. Both record the command that made them (`"command"`). Sample-count overrides
come last: they win over `--set`.
"""

import argparse
import dataclasses
import statistics
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from harness import (
    RESULTS,
    DatasetCache,
    TrainingRun,
    append_jsonl,
    data_dir_override,
    expand_overrides,
    grid_threshold,
    load,
    machine_info,
    model_summary,
    override_keys,
    platform_tag,
    print_table,
    resolve,
    scene_spec,
    schedule_overrides,
    variant_spec,
    write_json,
)

import mixnerf_eqx as mx
from mixnerf_eqx.data import Dataset, Views
from mixnerf_eqx.metrics import lpips_available

DEFAULT_VARIANTS = ["mixnerf=scene", "mipnerf=scene:@baseline"]


@dataclasses.dataclass
class Frame:
    """One rendered view and what rendering it cost in field (MLP) evaluations."""

    rgb: np.ndarray  # (height, width, 3)
    depth: np.ndarray  # (height, width)
    acc: np.ndarray  # (height, width)
    field_evaluations: int  # evaluations the frame needed
    padded_evaluations: int  # evaluations made, with the last chunk's padding


def render_frame(
    model: mx.MixNeRF, views: Views, dataset: Dataset, chunk: int, skipping: mx.inference.Skipping | None = None
) -> Frame:
    """Renders the single view in `views`: the one place where this benchmark renders.

    `chunk` is the rays per render call; `skipping` turns on the renderer that skips empty
    space and finished rays. The counts come from the library's `RenderCounts`: dense, every
    ray evaluates the field at all its samples (pixels x (coarse + fine samples)); with
    skipping, only the evaluations made.
    """
    if views.num_views != 1:
        raise ValueError(f"render_frame renders one view, got {views.num_views}")
    rendered = mx.render_views(model, views, dataset.near, dataset.far, chunk, skipping=skipping)
    counts = rendered.counts
    return Frame(
        rendered.rgb[0],
        rendered.depth[0],
        rendered.acc[0],
        counts.field_evaluations,
        counts.padded_evaluations,
    )


def benchmark_renders(
    model: mx.MixNeRF, dataset: Dataset, chunk: int, skipping: mx.inference.Skipping | None = None
) -> dict[str, Any]:
    """Times `render_frame` on every test view after a warm-up, and scores the renders.

    With skipping the warm-up renders every view (the buffer sizes vary from view to view and
    each compiles once); dense, one view compiles the renderer.
    """
    test = dataset.test
    started = time.perf_counter()
    for index in range(test.num_views if skipping is not None else 1):
        render_frame(model, test.select([index]), dataset, chunk, skipping)
    first_s = time.perf_counter() - started
    with_lpips = lpips_available()
    seconds, per_view, evaluations, padded = [], [], [], []
    for index in range(test.num_views):
        one = test.select([index])
        started = time.perf_counter()
        frame = render_frame(model, one, dataset, chunk, skipping)
        seconds.append(time.perf_counter() - started)
        evaluations.append(frame.field_evaluations)
        padded.append(frame.padded_evaluations)
        mask = None if one.masks is None else one.masks[0]
        per_view.append(
            {
                "view": int(one.ids[0]),
                **mx.inference.image_metrics(frame.rgb, one.images[0], mask=mask, with_lpips=with_lpips),
            }
        )
    median_s = statistics.median(seconds)
    means = {}
    for name in ("psnr", "ssim", "lpips", "average"):
        values = [view[name] for view in per_view]
        means[name] = None if any(v is None for v in values) else float(np.mean(values))
    frame_evaluations = statistics.median(evaluations)
    return {
        **means,
        "render_s": median_s,
        "render_s_per_view": seconds,
        "first_render_s": first_s,
        "render_compile_s": max(first_s - median_s, 0.0),
        "field_evals_per_frame": int(frame_evaluations),
        "padded_evals_per_frame": int(statistics.median(padded)),
        "field_evals_per_s": frame_evaluations / median_s,
        "frame_size": [test.width, test.height],
        "chunk": chunk,
        "per_view": per_view,
    }


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data-dir", help="dataset root (default: $MIXNERF_DATA_DIR)")
    parser.add_argument(
        "--scene",
        action="append",
        type=scene_spec,
        help="fern, lego or NAME=CONFIG[:overrides] (default: fern)",
    )
    parser.add_argument(
        "--variant",
        action="append",
        type=variant_spec,
        help="NAME=scene[:overrides] or NAME=FILE[:overrides] (default: " + " ".join(DEFAULT_VARIANTS) + ")",
    )
    parser.add_argument("--samples", type=int, nargs="+", default=[128, 64, 32, 16, 8], help="per level")
    parser.add_argument("--steps", type=int, default=2000, help="training steps per run")
    parser.add_argument(
        "--set", nargs="+", action="extend", default=[], metavar="KEY=VALUE", help="overrides for every run"
    )
    parser.add_argument("--eval-views", type=int, default=0, help="evenly spaced test views (0: all)")
    parser.add_argument("--eval-downscale", type=int, default=1, help="area-downsample the test views")
    parser.add_argument("--chunk", type=int, help="rays per render call (default: train.render_chunk)")
    parser.add_argument(
        "--skipping",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also render with the occupancy grid and early termination (the config's [occupancy] settings)",
    )
    parser.add_argument("--out", default=str(RESULTS), help="output folder")
    parser.add_argument("--tag", default=None, help="file-name suffix (default: the JAX backend)")
    args = parser.parse_args()
    args.scene = args.scene or [scene_spec("fern")]
    args.variant = args.variant or [variant_spec(text) for text in DEFAULT_VARIANTS]
    args.set = list(expand_overrides(args.set))
    if any(n < 1 for n in args.samples) or args.steps < 1:
        parser.error("--samples and --steps must be positive")
    return args


def run_one(args, scene, variant, samples: int, cache: DatasetCache) -> dict[str, Any]:
    record: dict[str, Any] = {"scene": scene.name, "variant": variant.name, "samples": samples}
    resolved = resolve(scene, variant, args.set)
    if resolved.skip_reason is not None:
        print(f"[{scene.name} {variant.name} {samples}] skipped: {resolved.skip_reason}")
        return {**record, "status": "skipped", "reason": resolved.skip_reason}
    counts = [f"model.num_coarse_samples={samples}", f"model.num_fine_samples={samples}"]
    fixed = [*counts, *data_dir_override(args.data_dir), f"data.max_test_views={args.eval_views}"]
    base = load(resolved, fixed)
    explicit = override_keys([*scene.overrides, *args.set, *variant.overrides])
    schedule = schedule_overrides(base, args.steps, explicit)
    config = load(resolved, [*fixed, *schedule])
    dataset, data_info = cache.get(config)
    run = TrainingRun(config, dataset)
    compile_s = run.compile()
    status, train_s = "ok", 0.0
    try:
        for step in range(1, args.steps + 1):
            train_s += run.advance()
            if step % max(args.steps // 5, 1) == 0 and step < args.steps:
                print(
                    f"[{scene.name} {variant.name} {samples}+{samples}] step {step}: {train_s:.1f} s",
                    flush=True,
                )
    except mx.training.TrainingDiverged as error:
        status = f"diverged: {error}"
    chunk = args.chunk or config.train.render_chunk
    renders = benchmark_renders(run.model, dataset, chunk)
    if args.skipping:
        started = time.perf_counter()
        grid, _ = mx.runs.grid_for_rendering(
            config.occupancy, dataset, run.model, key=jax.random.key(args.steps)
        )
        grid_s = time.perf_counter() - started
        skipped = benchmark_renders(run.model, dataset, chunk, mx.runs.make_skipping(config.occupancy, grid))
        record["skipping"] = {
            "occupancy": dataclasses.asdict(config.occupancy),
            "density_threshold": grid_threshold(grid),
            "occupied_fraction": float(grid.occupied_fraction()),
            "grid_s": grid_s,
            **{k: v for k, v in skipped.items() if k != "per_view"},
        }
    record.update(
        {
            "status": status,
            "config_file": resolved.path,
            "overrides": [*resolved.overrides, *fixed, *schedule],
            "model": model_summary(config),
            "data": data_info,
            "steps": run.step,
            "skipped_steps": run.skipped,
            "train_compile_s": compile_s,
            "train_s": train_s,
            "steps_per_s": run.step / max(train_s, 1e-9),
            **renders,
        }
    )
    lpips_text = "n/a" if renders["lpips"] is None else f"{renders['lpips']:.4f}"
    if "skipping" in record:
        skip = record["skipping"]
        print(
            f"[{scene.name} {variant.name} {samples}+{samples}] skipping: PSNR {skip['psnr']:.3f} "
            f"({skip['psnr'] - renders['psnr']:+.3f}), {skip['padded_evals_per_frame']} evaluations/frame "
            f"({renders['field_evals_per_frame'] / max(skip['padded_evals_per_frame'], 1):.2f}x fewer), "
            f"{skip['render_s']:.3f} s/frame",
            flush=True,
        )
    print(
        f"[{scene.name} {variant.name} {samples}+{samples}] {run.step} steps in {train_s:.1f} s "
        f"(compile {compile_s:.1f} s): PSNR {renders['psnr']:.3f} SSIM {renders['ssim']:.4f} "
        f"LPIPS {lpips_text}; {renders['render_s']:.3f} s/frame "
        f"(render compile {renders['render_compile_s']:.1f} s)",
        flush=True,
    )
    return record


def main() -> None:
    args = parse_args()
    tag = args.tag or platform_tag()
    machine = machine_info()
    print(f"on {machine['device_kind']} ({machine['backend']}); LPIPS available: {lpips_available()}")
    cache = DatasetCache(args.eval_downscale)
    jsonl = Path(args.out) / f"sample_count_{tag}.jsonl"
    jsonl.parent.mkdir(parents=True, exist_ok=True)
    print(f"finished runs are appended to {jsonl}")
    rows = []
    for scene in args.scene:
        for samples in args.samples:
            for variant in args.variant:
                rows.append(run_one(args, scene, variant, samples, cache))
                append_jsonl(jsonl, {"machine": machine, **rows[-1]})
    header = (
        "scene",
        "model",
        "samples",
        "frame",
        "steps",
        "train s",
        "PSNR",
        "SSIM",
        "LPIPS",
        "s/frame",
        "render compile s",
        "field evals/frame",
        "Mevals/s",
    )
    table = []
    for row in rows:
        if row["status"] == "skipped":
            table.append((row["scene"], row["variant"], row["samples"], "skipped", *[None] * 9))
            continue
        table.append(
            (
                row["scene"],
                row["variant"],
                f"{row['samples']}+{row['samples']}",
                "x".join(str(n) for n in row["frame_size"]),
                row["steps"],
                row["train_s"],
                row["psnr"],
                row["ssim"],
                row["lpips"],
                row["render_s"],
                row["render_compile_s"],
                f"{row['field_evals_per_frame']:,}",
                row["field_evals_per_s"] / 1e6,
            )
        )
    print(f"\n{args.steps} steps per run; seconds per full frame: median over the views")
    print_table(header, table)
    payload = {
        "machine": machine,
        "args": {key: value for key, value in vars(args).items() if key not in ("scene", "variant")},
        "scenes": {spec.name: spec.describe() for spec in args.scene},
        "variants": {spec.name: spec.describe() for spec in args.variant},
        "lpips_available": lpips_available(),
        "rows": rows,
    }
    write_json(Path(args.out) / f"sample_count_{tag}.json", payload)


if __name__ == "__main__":
    main()
