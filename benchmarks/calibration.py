"""Does MixNeRF's predictive distribution hold its coverage? Raw, temperature, isotonic and
conformal intervals, fitted on validation views and scored on test views.

For each scene and seed: train MixNeRF (`mx.fit`, the scene's config as shipped), then fit on
the scene's validation views (which are neither training nor test views, and not near the
test views: `mixnerf_eqx.data`'s splits) one temperature on every beta (`mx.uncertainty.fit_temperature`),
an isotonic map of the predictive CDF and split-conformal intervals (`mx.uncertainty.fit_recalibration`),
and score each on the test views, from the coarse level's colour mixture (where the NLL
trains) and the fine level's termination distance:

- the coverage of the 50/80/90/95% intervals, pooled over the test pixels and channels and
  its range over the test views, and the mean width of the 90% interval,
- FlipNeRF's NLL (the channels' marginal densities, averaged over pixels and channels, nats)
  and calibration error (mean squared gap between PIT values and their empirical CDF, mean
  of the channels),
- AUSE for colour and, where the true depth is known, for depth (the model's spreads; a
  temperature changes the colour's order, since the spread of the components' locations does
  not scale with beta).

Also timed, for the first seed (unless `--no-time`): the predictive pass over the test views
against an ordinary (dense) render of them, both compiled beforehand, with the same chunk,
and the pass's colour quantile solve alone.

    python benchmarks/calibration.py --data-dir ../shared/data --seeds 0 1 2

or, for runs trained elsewhere (a sweep's folders at the benchmark's resolution), their latest
checkpoints scored the same way, on an evenly spaced subset of the test views if asked:

    python benchmarks/calibration.py --runs runs/full_lego/mixnerf/lego/seed_0 ... \\
        --data-dir ../shared/data --test-views 5 --no-time --tag lego400

or, to time one such run and score nothing (`--cost-only`; a tag is required):

    python benchmarks/calibration.py --runs runs/fern_dist5/a/fern/seed_2 --data-dir ../shared/data \\
        --cost-only --test-views 1 --tag cost_fern504_split

Results: `results/calibration_cpu.json` and `results/calibration_cpu.md`.
"""

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from harness import (
    RESULTS,
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
    "builtin": ("builtin_grid", ()),
    # fern 3-view at 56x42 (images_8 area-downsampled by 9), 100 epochs of its training pixels.
    "fern": ("configs/llff3_fast.toml", (*CPU_MODEL, "data.image_downscale=9", "train.max_steps=1379")),
}


METHODS = ("raw", "temperature", "isotonic", "conformal")


def timed_passes(model: mx.MixNeRF, views: Views, dataset, chunk: int) -> dict[str, float]:
    """Seconds per view of a dense render, of the predictive pass (what `eval --uncertainty`
    runs) and of the same with the mode of each pixel's colour density, all compiled first."""
    first = views.select([0])
    passes = {
        "render": lambda v: mx.render_views(model, v, dataset.near, dataset.far, chunk),
        "predictive": lambda v: mx.uncertainty.predict_views(model, v, dataset.near, dataset.far, chunk),
        "predictive_with_mode": lambda v: mx.uncertainty.predict_views(
            model, v, dataset.near, dataset.far, chunk, with_mode=True
        ),
    }
    seconds = {}
    for name, run_pass in passes.items():
        run_pass(first)
        started = time.perf_counter()
        run_pass(views)
        seconds[f"{name}_s_per_view"] = (time.perf_counter() - started) / views.num_views
    seconds["colour_quantiles_s_per_view"] = colour_quantile_seconds(model, views, dataset, chunk)
    seconds["ratio"] = seconds["predictive_s_per_view"] / seconds["render_s_per_view"]
    seconds["ratio_with_mode"] = seconds["predictive_with_mode_s_per_view"] / seconds["render_s_per_view"]
    seconds["ratio_without_colour_quantiles"] = (
        seconds["predictive_s_per_view"] - seconds["colour_quantiles_s_per_view"]
    ) / seconds["render_s_per_view"]
    return seconds


def quantile_chunks(
    model: mx.MixNeRF, view: Views, dataset, chunk: int
) -> list[mx.uncertainty.ColourMixture]:
    """One view's colour mixtures in the chunks the predictive pass solves them in: at most
    `chunk` rays each (never more than the view has), the last padded with the last ray."""
    rays = rays_for_views(view, dataset.near, dataset.far).reshape(-1)
    mixtures = mx.uncertainty.collect_mixtures(model, rays, chunk)
    count = mixtures.location.shape[0]
    size = max(1, min(chunk, count))
    pad = -count % size
    padded = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), mixtures)
    return [
        jax.tree_util.tree_map(lambda x, start=start: x[start : start + size], padded)
        for start in range(0, count, size)
    ]


def colour_quantile_seconds(model: mx.MixNeRF, views: Views, dataset, chunk: int) -> float:
    """Seconds per view of the predictive pass's colour quantile solve alone: the median and
    both ends of each interval (9 levels, 3 channels) on each view's own mixtures, in the
    pass's chunks (`quantile_chunks`, rendered first, untimed)."""
    levels = mx.uncertainty.IntervalLevels.raw(MASSES)
    stacked = jnp.concatenate([jnp.full((1, 3), 0.5), levels.colour_lower, levels.colour_upper])
    solve = eqx.filter_jit(lambda mixture: mixture.channel_quantiles(stacked))
    seconds = 0.0
    for index in range(views.num_views):
        chunks = quantile_chunks(model, views.select([index]), dataset, chunk)
        jax.block_until_ready(solve(chunks[0]))  # compiled (once per chunk size) before the clock
        started = time.perf_counter()
        for mixture in chunks:
            jax.block_until_ready(solve(mixture))
        seconds += time.perf_counter() - started
    return seconds / views.num_views


def run_scene(name: str, seed: int, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    base, overrides = SCENES[name]
    overrides = [
        *overrides,
        *data_dir_override(args.data_dir),
        f"train.seed={seed}",
        f"train.run_dir={work / f'{name}_{seed}'}",
    ]
    if args.steps:
        overrides.append(f"train.max_steps={args.steps}")
    config = mx.load_config(base, overrides)
    dataset = load_dataset(config.data)
    started = time.perf_counter()
    model = mx.fit(config, dataset=dataset, progress=False, write_renders=False).model
    train_s = time.perf_counter() - started
    print(f"{name} seed {seed}: trained {config.train.max_steps} steps in {train_s:.0f} s")
    record = {"scene": name, "seed": seed, "config": base, "overrides": overrides}
    record["steps"] = config.train.max_steps
    timed = seed == args.seeds[0] and args.time
    return {**record, "train_s": train_s, **score(model, dataset, args, timed=timed)}


def run_folder(run_dir: str, args: argparse.Namespace, first: bool) -> dict[str, Any]:
    """The record of a run trained elsewhere (a sweep's or `train`'s folder): its latest
    checkpoint, scored as `run_scene` scores a model it trains."""
    run = mx.runs.restore_run(run_dir, data_dir=args.data_dir)
    config = run.config
    print(f"{run_dir}: {config.name} on {run.dataset.name}, seed {config.train.seed}, step {run.step}")
    record = {
        "scene": config.data.scene,
        "seed": config.train.seed,
        "config": config.name,
        "run_dir": str(run_dir),
        "steps": run.step,
    }
    return {**record, "train_s": None, **score(run.model, run.dataset, args, timed=first and args.time)}


def check_runs(run_dirs: list[str]) -> None:
    """The table averages the runs of a scene as seeds of one setting: refuse folders that
    are not runs, runs of one scene whose settings differ, and a seed given twice, before any
    work."""
    seen: dict[str, tuple[str, dict[str, Any], set[int]]] = {}
    for run_dir in run_dirs:
        path = Path(run_dir) / "config.json"
        if not path.is_file():
            raise SystemExit(f"error: {run_dir} is not a training run: it has no config.json")
        config = json.loads(path.read_text())
        scene, seed = config["data"]["scene"], config["train"]["seed"]
        # Every setting as "section.key", without what differs between seeds of one setting.
        setting = {
            f"{section}.{key}" if isinstance(values, dict) else section: value
            for section, values in config.items()
            for key, value in (values.items() if isinstance(values, dict) else [(None, values)])
            if key not in ("seed", "run_dir", "data_dir")
        }
        first, known, seeds = seen.setdefault(scene, (run_dir, setting, set()))
        differ = sorted(key for key in setting.keys() | known.keys() if setting.get(key) != known.get(key))
        if differ:
            raise SystemExit(
                f"error: {run_dir} and {first} are runs of {scene} with other settings "
                f"({', '.join(differ)}): score one setting at a time"
            )
        if seed in seeds:
            raise SystemExit(f"error: {run_dir}: seed {seed} of {scene} is given twice")
        seeds.add(seed)


def evenly(views: Views, count: int) -> Views:
    """`count` of `views`, evenly spaced (all of them for 0 or more than there are)."""
    if count <= 0 or count >= views.num_views:
        return views
    return views.select([int(i) for i in np.linspace(0, views.num_views - 1, count).round()])


def score(model: mx.MixNeRF, dataset, args: argparse.Namespace, timed: bool) -> dict[str, Any]:
    """Fit every correction on the validation views and score each on the test views."""
    val, test = dataset.split("val"), evenly(dataset.test, args.test_views)
    pit = mx.uncertainty.calibration_pit(
        model, val, dataset.near, dataset.far, args.chunk, max_pixels=args.calibration_pixels
    )
    picked = jax.tree_util.tree_map(
        lambda x: x[
            np.sort(
                np.random.default_rng(0).choice(
                    x.shape[0], min(x.shape[0], args.calibration_pixels), replace=False
                )
            )
        ],
        (rays_for_views(val, dataset.near, dataset.far).reshape(-1), jnp.asarray(val.images.reshape(-1, 3))),
    )
    temperature = mx.uncertainty.fit_temperature(
        mx.uncertainty.collect_mixtures(model, picked[0], args.chunk), picked[1]
    )
    where = f"{val.num_views} validation views"
    depth_pit = pit["depth_cdf"] if pit["depth_cdf"].size else None
    fitted = {
        "raw": (mx.uncertainty.Recalibration.raw(MASSES), 1.0),
        "temperature": (mx.uncertainty.Recalibration.raw(MASSES), temperature),
    }
    for method in ("isotonic", "conformal"):
        recalibration = mx.uncertainty.Recalibration.fit(
            method, pit["colour_cdf"], depth_pit, MASSES, fitted_on=where
        )
        fitted[method] = (recalibration, 1.0)
    reports = {}
    for method, (recalibration, factor) in fitted.items():
        maps = mx.uncertainty.predict_views(
            model,
            test,
            dataset.near,
            dataset.far,
            args.chunk,
            masses=MASSES,
            temperature=factor,
            levels=recalibration.interval_levels(),
        )
        report = mx.uncertainty.coverage_report(maps, test.images, test.depths, recalibration)
        report.update(
            {
                key: value
                for key, value in mx.uncertainty.calibration_report(maps, test.images, test.depths).items()
                if "ause" in key or "random" in key
            }
        )
        report["psnr_of_render"] = float(
            np.mean([mx.metrics.psnr(maps["rgb"][i], test.images[i]) for i in range(test.num_views)])
        )
        reports[method] = report
        cover = ", ".join(f"{value['pooled']:.3f}" for value in report["colour_coverage"].values())
        print(f"  {method}: coverage {cover}; calibration error {report['calibration_error']:.4f}")
    return {
        "test_views": list(test.ids),
        "test_size": [test.width, test.height],
        "calibration_views": list(val.ids),
        "calibration_pixels": int(pit["colour_cdf"].shape[0]),
        "temperature": temperature,
        "methods": reports,
        "cost": timed_passes(model, test, dataset, args.chunk) if timed else None,
        "chunk": args.chunk,
    }


def _mean_sd(values: list[float], digits: int) -> str:
    values = np.asarray(values, np.float64)
    if values.size < 2:
        return f"{values.mean():.{digits}f}"
    return f"{values.mean():.{digits}f} ± {values.std(ddof=1):.{digits}f}"


def table(results: list[dict[str, Any]]) -> str:
    """One row per scene and method: means ± standard deviations over the seeds."""
    header = (
        "| scene (seeds) | intervals | colour coverage 50% | 80% | 90% | 95% | worst view at 90% | "
        "90% width | depth coverage 90% | NLL | calibration error | AUSE colour | AUSE depth |"
    )
    lines = [header, "|" + "---|" * 13]
    for scene in dict.fromkeys(result["scene"] for result in results):
        runs = [result for result in results if result["scene"] == scene]
        for method in METHODS:
            reports = [run["methods"][method] for run in runs]
            cells = [_mean_sd([r["colour_coverage"][f"{m:g}"]["pooled"] for r in reports], 3) for m in MASSES]
            worst = min(r["colour_coverage"]["0.9"]["per_view_min"] for r in reports)
            width = _mean_sd([r["colour_coverage"]["0.9"]["width"] for r in reports], 3)
            depth = "n/a"
            if reports[0]["depth_coverage"] is not None:
                depth = _mean_sd([r["depth_coverage"]["0.9"]["pooled"] for r in reports], 3)
            depth_ause = (
                "n/a" if reports[0]["depth_ause"] is None else _mean_sd([r["depth_ause"] for r in reports], 3)
            )
            label = (
                method
                if method != "temperature"
                else "temperature (T " + _mean_sd([run["temperature"] for run in runs], 2) + ")"
            )
            lines.append(
                f"| {scene} ({len(runs)}) | {label} | "
                + " | ".join(cells)
                + f" | {worst:.3f} | {width} | {depth} | "
                f"{_mean_sd([r['nll_per_channel'] for r in reports], 3)} | "
                f"{_mean_sd([r['calibration_error'] for r in reports], 4)} | "
                f"{_mean_sd([r['colour_ause'] for r in reports], 3)} | {depth_ause} |"
            )
    return "\n".join(lines)


def cost_table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| scene | test view | render s/view | predictive s/view (ratio) | with the mode s/view (ratio) "
        "| its colour quantile solve s/view | the pass without it (ratio) |",
        "|---|---|---|---|---|---|---|",
    ]
    for result in results:
        cost = result["cost"]
        if cost is None:
            continue
        size = "x".join(str(side) for side in result["test_size"])
        lines.append(
            f"| {result['scene']} | {size} | {cost['render_s_per_view']:.3f} | "
            f"{cost['predictive_s_per_view']:.3f} ({cost['ratio']:.2f}) | "
            f"{cost['predictive_with_mode_s_per_view']:.3f} ({cost['ratio_with_mode']:.2f}) | "
            + (
                f"{cost['colour_quantiles_s_per_view']:.3f} | "
                f"{cost['predictive_s_per_view'] - cost['colour_quantiles_s_per_view']:.3f} "
                f"({cost['ratio_without_colour_quantiles']:.2f}) |"
                if "colour_quantiles_s_per_view" in cost
                else "not measured | |"
            )
        )
    return "\n".join(lines)


def cost_only(args: argparse.Namespace) -> None:
    """Time the passes on the first of `--runs` and write only the cost table."""
    try:
        run = mx.runs.restore_run(args.runs[0], data_dir=args.data_dir)
    except (mx.ConfigError, mx.runs.CheckpointError) as error:
        raise SystemExit(f"error: {error}") from None
    test = evenly(run.dataset.test, args.test_views)
    result = {
        "scene": run.config.data.scene,
        "seed": run.config.train.seed,
        "config": run.config.name,
        "run_dir": str(args.runs[0]),
        "steps": run.step,
        "test_views": list(test.ids),
        "test_size": [test.width, test.height],
        "chunk": args.chunk,
        "cost": timed_passes(run.model, test, run.dataset, args.chunk),
    }
    stem = f"calibration_{platform_tag()}{'_' + args.tag if args.tag else ''}"
    write_json(RESULTS / f"{stem}.json", {"results": [result]})
    text = (
        f"Cost of the predictive pass against an ordinary dense render (both compiled; chunk {args.chunk}), "
        f"{result['scene']} seed {result['seed']}: {result['run_dir']} "
        f"({result['config']}, step {result['steps']}), "
        f"{len(result['test_views'])} test views:\n\n"
        + cost_table([result])
        + f"\n\nMachine: {machine_info()['platform']}, {machine_info()['cpu_count']} CPUs.\n"
    )
    write_markdown(RESULTS / f"{stem}.md", text)
    print(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir", default=None, help="dataset root (fern, or the scenes of --runs)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--steps", type=int, default=0, help="training steps (0: the config's)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--chunk", type=int, default=4096, help="rays per compiled call, both passes")
    parser.add_argument("--calibration-pixels", type=int, default=65536)
    parser.add_argument("--tag", default="", help="suffix of the result files")
    parser.add_argument(
        "--runs",
        nargs="+",
        default=None,
        help="score these trained run folders (their latest checkpoints) instead of training --scenes",
    )
    parser.add_argument(
        "--test-views", type=int, default=0, help="score this many of the test views, evenly spaced (0: all)"
    )
    parser.add_argument(
        "--time",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="time the passes on the first seed or run (--no-time on a loaded machine)",
    )
    parser.add_argument(
        "--cost-only",
        action="store_true",
        help="with one --runs folder and a --tag: time the passes (on --test-views) and score nothing",
    )
    args = parser.parse_args()
    if args.cost_only:
        if not args.runs or len(args.runs) != 1:
            raise SystemExit("error: --cost-only times one trained run: give exactly one with --runs")
        if not args.tag:
            raise SystemExit(
                "error: --cost-only needs a --tag (its files must not replace the calibration's)"
            )
        if not args.time:
            raise SystemExit("error: --cost-only only times: it cannot be combined with --no-time")
        cost_only(args)
        return
    if args.runs:
        check_runs(args.runs)
        try:
            results = [run_folder(run_dir, args, first=index == 0) for index, run_dir in enumerate(args.runs)]
        except (mx.ConfigError, mx.runs.CheckpointError) as error:
            raise SystemExit(f"error: {error}") from None
    else:
        with tempfile.TemporaryDirectory() as work:
            results = [run_scene(name, seed, args, Path(work)) for name in args.scenes for seed in args.seeds]
    stem = f"calibration_{platform_tag()}{'_' + args.tag if args.tag else ''}"
    write_json(RESULTS / f"{stem}.json", {"results": results})
    timed = any(result["cost"] is not None for result in results)
    cost = (
        "Cost of the predictive pass against an ordinary dense render (both compiled; "
        + f"chunk {args.chunk}):\n\n"
        + cost_table(results)
        if timed
        else "Not timed (`--no-time`)."
    )
    sources = "".join(
        f"- {result['scene']} seed {result['seed']}: {result['run_dir']} "
        f"({result['config']}, step {result['steps']})\n"
        for result in results
        if result.get("run_dir")
    )
    text = (
        "Coverage pooled over the test pixels and channels (mean ± sd over seeds); worst view: the "
        "lowest per-view coverage of any seed; NLL per channel in nats (FlipNeRF's definition); "
        "every setting fitted on validation views.\n\n"
        + (f"Runs scored:\n\n{sources}\n" if sources else "")
        + table(results)
        + "\n\n"
        + cost
        + f"\n\nMachine: {machine_info()['platform']}, {machine_info()['cpu_count']} CPUs.\n"
    )
    write_markdown(RESULTS / f"{stem}.md", text)
    print(text)


if __name__ == "__main__":
    main()
