"""Is MixNeRF's predictive distribution calibrated? The calibration table of the predictive API.

For each scene: train MixNeRF (the library's `TrainState` and step, through the harness), then
on the held-out test views measure, from the colour mixture of the coarse level (where the NLL
is trained):

- the coverage of the central 50/80/90/95% per-channel intervals against the true pixels,
- the held-out negative log-likelihood per pixel (the joint colour density),
- sparsification curves and their area against the oracle (AUSE), for colour (the render's
  absolute error against the mixture's standard deviation) and, where the true depth is known,
  for depth (the rendered depth's error against the termination distance's spread),

first with the model's own scales, then with one temperature on every beta fitted (by
`mx.fit_temperature`) on pixels of other views the model never trained on, which are never the
test views: for the built-in scene the cameras of its 7-view test set (none of which is a
camera of the 8-view set), for LLFF the images that are neither training nor test images.
Also timed: the predictive pass over the test views against an ordinary (dense) render of
them, both compiled beforehand, with the same chunk.

    python benchmarks/calibration.py --data-dir ../shared/data

Results: `results/calibration_cpu.json` and `results/calibration_cpu.md`.
"""

import argparse
import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from harness import (
    RESULTS,
    TrainingRun,
    data_dir_override,
    machine_info,
    platform_tag,
    write_json,
    write_markdown,
)

import mixnerf_eqx as mx
from mixnerf_eqx.data import Views, load_dataset, rays_for_views

MASSES = (0.5, 0.8, 0.9, 0.95)

# The CPU-sized model of the benchmarks (fidelity.py) for fern; the built-in scene runs its
# quick-start config as it is.
CPU_MODEL = (
    "mlp.width=64",
    "mlp.depth=4",
    "mlp.skip_layer=2",
    "mlp.view_width=32",
    "train.batch_size=512",
    "optim.warmup_steps=50",
    "loss.lambda_colour_steps=50",
    "train.anneal_steps=50",
)

SCENES: dict[str, tuple[str, tuple[str, ...]]] = {
    "builtin": ("configs/builtin.toml", ()),
    # fern 3-view at 56x42 (images_8 area-downsampled by 9), 100 epochs of its training pixels.
    "fern": ("configs/llff3_fast.toml", (*CPU_MODEL, "data.image_downscale=9", "train.max_steps=1379")),
}


def calibration_views(name: str, config: mx.Config, dataset) -> Views:
    """Views the model never trained on and that are not its test views (see the docstring)."""
    if config.data.dataset == "builtin":
        other = load_dataset(dataclasses.replace(config.data, num_test_views=7)).test
    else:
        everything = load_dataset(dataclasses.replace(config.data, num_train_views=17)).train
        keep = [i for i, view_id in enumerate(everything.ids) if view_id not in dataset.train.ids]
        other = everything.select(keep)
    for pose in other.camtoworlds:
        for used in (*dataset.train.camtoworlds, *dataset.test.camtoworlds):
            if np.allclose(pose, used, atol=1e-6):
                raise RuntimeError(f"{name}: a calibration camera is a training or test camera")
    return other


def calibration_pixels(model: mx.MixNeRF, views: Views, dataset, count: int, seed: int):
    """`count` random pixels of `views`: their coarse colour mixtures and true colours."""
    rays = rays_for_views(views, dataset.near, dataset.far).reshape(-1)
    colours = views.images.reshape(-1, 3)
    chosen = np.random.default_rng(seed).choice(
        colours.shape[0], size=min(count, colours.shape[0]), replace=False
    )
    picked = jax.tree_util.tree_map(lambda x: x[chosen], rays)
    return mx.collect_mixtures(model, picked), jnp.asarray(colours[chosen])


def timed_passes(model: mx.MixNeRF, views: Views, dataset, chunk: int) -> dict[str, float]:
    """Seconds per view of a dense render, of the predictive pass (what `eval --uncertainty`
    runs) and of the same with the mode of each pixel's colour density, all compiled first."""
    first = views.select([0])
    passes = {
        "render": lambda v: mx.render_views(model, v, dataset.near, dataset.far, chunk),
        "predictive": lambda v: mx.predict_views(model, v, dataset.near, dataset.far, chunk),
        "predictive_with_mode": lambda v: mx.predict_views(
            model, v, dataset.near, dataset.far, chunk, with_mode=True
        ),
    }
    seconds = {}
    for name, run_pass in passes.items():
        run_pass(first)
        started = time.perf_counter()
        run_pass(views)
        seconds[f"{name}_s_per_view"] = (time.perf_counter() - started) / views.num_views
    seconds["ratio"] = seconds["predictive_s_per_view"] / seconds["render_s_per_view"]
    seconds["ratio_with_mode"] = seconds["predictive_with_mode_s_per_view"] / seconds["render_s_per_view"]
    return seconds


def run_scene(name: str, args: argparse.Namespace) -> dict[str, Any]:
    base, overrides = SCENES[name]
    overrides = [*overrides, *data_dir_override(args.data_dir), f"train.seed={args.seed}"]
    if args.steps:
        overrides.append(f"train.max_steps={args.steps}")
    config = mx.load_config(base, overrides)
    dataset = load_dataset(config.data)
    run = TrainingRun(config, dataset)
    compile_s = run.compile()
    started = time.perf_counter()
    for _ in range(config.train.max_steps):
        run.advance()
    train_s = time.perf_counter() - started
    model = run.model
    test = dataset.test
    print(
        f"{name}: trained {config.train.max_steps} steps in {train_s:.0f} s (compiled in {compile_s:.0f} s)"
    )

    other = calibration_views(name, config, dataset)
    mixtures, colours = calibration_pixels(model, other, dataset, args.calibration_pixels, args.seed)
    raw_nll = float(-jnp.mean(mixtures.log_prob(colours)))
    temperature = mx.fit_temperature(mixtures, colours)
    fitted_nll = float(-jnp.mean(mixtures.with_temperature(temperature).log_prob(colours)))
    print(f"{name}: temperature {temperature:.4f} (calibration NLL {raw_nll:.3f} -> {fitted_nll:.3f})")

    chunk = args.chunk
    reports = {}
    for label, factor in (("raw", 1.0), ("calibrated", temperature)):
        maps = mx.predict_views(
            model, test, dataset.near, dataset.far, chunk, masses=MASSES, temperature=factor
        )
        reports[label] = mx.calibration_report(maps, test.images, test.depths)
        reports[label]["psnr_of_render"] = float(
            np.mean([mx.metrics.psnr(maps["rgb"][i], test.images[i]) for i in range(test.num_views)])
        )
    cost = timed_passes(model, test, dataset, chunk)
    return {
        "scene": name,
        "config": base,
        "overrides": overrides,
        "steps": config.train.max_steps,
        "train_s": train_s,
        "test_views": list(test.ids),
        "test_size": [test.width, test.height],
        "calibration_views": list(other.ids),
        "calibration_pixels": int(colours.shape[0]),
        "temperature": temperature,
        "calibration_nll": {"raw": raw_nll, "fitted": fitted_nll},
        "raw": reports["raw"],
        "calibrated": reports["calibrated"],
        "cost": cost,
        "chunk": chunk,
    }


def table(results: list[dict[str, Any]]) -> str:
    header = (
        "| scene | scales | T | coverage 50% | 80% | 90% | 95% | held-out NLL | AUSE colour (random) "
        "| AUSE depth (random) |"
    )
    lines = [header, "|" + "---|" * 10]
    for result in results:
        for label in ("raw", "calibrated"):
            report = result[label]
            coverage = [report["coverage"][f"{mass:g}"] for mass in MASSES]
            cells = [
                "/".join(f"{value:.2f}" for value in entry["per_channel"]) + f" ({entry['mean']:.3f})"
                for entry in coverage
            ]
            depth = "n/a"
            if report["depth_ause"] is not None:
                depth = f"{report['depth_ause']:.3f} ({report['depth_random_area']:.3f})"
            factor = 1.0 if label == "raw" else result["temperature"]
            lines.append(
                f"| {result['scene']} | {label} | {factor:.3f} | "
                + " | ".join(cells)
                + f" | {report['nll']:.3f} | "
                f"{report['colour_ause']:.3f} ({report['colour_random_area']:.3f}) | {depth} |"
            )
    return "\n".join(lines)


def cost_table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| scene | test view | render s/view | predictive s/view (ratio) | with the mode s/view (ratio) |",
        "|---|---|---|---|---|",
    ]
    for result in results:
        cost = result["cost"]
        size = "x".join(str(side) for side in result["test_size"])
        lines.append(
            f"| {result['scene']} | {size} | {cost['render_s_per_view']:.3f} | "
            f"{cost['predictive_s_per_view']:.3f} ({cost['ratio']:.2f}) | "
            f"{cost['predictive_with_mode_s_per_view']:.3f} ({cost['ratio_with_mode']:.2f}) |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir", default=None, help="dataset root (for fern)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--steps", type=int, default=0, help="training steps (0: the config's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk", type=int, default=4096, help="rays per compiled call, both passes")
    parser.add_argument("--calibration-pixels", type=int, default=8192)
    parser.add_argument("--tag", default="", help="suffix of the result files")
    args = parser.parse_args()
    results = [run_scene(name, args) for name in args.scenes]
    stem = f"calibration_{platform_tag()}{'_' + args.tag if args.tag else ''}"
    write_json(RESULTS / f"{stem}.json", {"results": results})
    text = (
        "Coverage: per channel R/G/B (mean); NLL in nats per pixel (joint RGB density, lower is "
        "better); AUSE with, in brackets, that of an uninformative order.\n\n"
        + table(results)
        + "\n\nCost of the predictive pass against an ordinary dense render (both compiled; "
        + f"chunk {args.chunk}):\n\n"
        + cost_table(results)
        + f"\n\nMachine: {machine_info()['platform']}, {machine_info()['cpu_count']} CPUs.\n"
    )
    write_markdown(RESULTS / f"{stem}.md", text)
    print(text)


if __name__ == "__main__":
    main()
