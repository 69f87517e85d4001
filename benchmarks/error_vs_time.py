"""Test error against training time: how fast each variant's PSNR rises on real scenes.

    # GPU: the paper model, 8 minutes of training per variant and scene
    python benchmarks/error_vs_time.py --data-dir ../shared/data

    # CPU: a CPU-sized MLP and batch, cheap evaluations on 4x-downsampled test views
    python benchmarks/error_vs_time.py --data-dir ../shared/data --eval-downscale 4 \\
        --set mlp.width=64 mlp.depth=4 mlp.skip_layer=2 mlp.view_width=32 train.batch_size=512

    # your own variants (see benchmarks/harness.py for the spec syntax)
    python benchmarks/error_vs_time.py --data-dir ../shared/data --scene lego \\
        --variant faithful=configs/blender4.toml \\
        --variant fast=configs/blender4.toml:model.num_coarse_samples=32,model.num_fine_samples=32,\
mlp.matmul_dtype=bfloat16

Every variant is trained on every scene for `--budget-s` seconds of training time by its own
loop over the library's `TrainState` and jitted step (`mx.training.init_train_state`,
`mx.training.make_train_step`: the step `fit` uses; `harness.TrainingRun`). The step is compiled ahead
of time with `.lower(...).compile()` (its time is reported as `compile_s`, not counted), and
each step is waited for and timed, so the clock holds step time only. At the
evaluation marks (every `--eval-every-s` seconds of training time, by default an eighth of the
budget, plus a quarter of the budget and the end) the clock stops and the test PSNR and SSIM
are measured on `--eval-views` evenly spaced test views (`mx.evaluate(..., with_lpips=False)`),
area-downsampled by `--eval-downscale` if asked (cheap CPU runs: then they are a proxy, not
the protocol's numbers). A mark is evaluated after the first step that passes it. A variant
with `occupancy.enabled` (e.g. configs/blender4_fast.toml) keeps its grid up to date as `fit`
does, those updates counted as training time, and is evaluated with the skipping renderer on
a fully refreshed grid, as `fit` evaluates at the end (the refresh is not counted).

Defaults: scenes lego 4-view (configs/blender4.toml) and fern 3-view (configs/llff3.toml);
variants `mixnerf` (the scene's paper config), `mipnerf` (the same with `method = "mipnerf"`,
i.e. configs/mipnerf_*.toml), and `mixnerf-fast` / `mipnerf-fast` (32 + 32 samples and
bfloat16 matrix products). `--set key=value ...` changes every variant (a variant's own
overrides win over it).

Schedule length: the learning-rate decay runs over `train.max_steps` steps, compiled into the
step. With `--max-steps N` every variant uses N. By default each variant's N is estimated:
a throwaway copy of the run is compiled and `--calibrate-steps` steps are timed, and
N = budget / (median step time), so that each variant's schedule ends near the end of its
own budget, as it would in a real run of that length (the fast variants get more steps).
Steps past N, if the estimate was low, run at the final learning rate. Warm-up, lambda_C
ramp and annealing keep the paper's lengths unless they exceed 1/10, 1/10 and 1/5 of N
(then they are cut to that share; keys given on the command line are left alone).

Target (per scene, for each `--target FAST:FAITHFUL` pair; by default `X-fast:X` for each
variant pair present and `fast:faithful`): the fast variant reaches the faithful variant's
final PSNR within `--target-fraction` (0.25) of the budget. Reported: the training time of
the first evaluation at which the fast PSNR >= the faithful final PSNR, its share of the
budget, and by how much the target is missed otherwise. The resolution is that of the
evaluation marks.

Outputs (in `--out`, default benchmarks/results; suffix `--tag`, default the JAX backend):
`error_vs_time_<tag>.jsonl` (one line per evaluation, appended as the run goes, with a run
id), `error_vs_time_<tag>.json` (summary), `error_vs_time_<tag>_<scene>.png` (PSNR against
training seconds and against steps; skipped if matplotlib is missing). Each records the
command that made it (`"command"`; in the PNG's metadata).
"""

import argparse
import re
import time
from pathlib import Path
from typing import Any

from harness import (
    RESULTS,
    DatasetCache,
    TrainingRun,
    append_jsonl,
    calibrate_steps,
    data_dir_override,
    expand_overrides,
    load,
    machine_info,
    model_summary,
    override_keys,
    platform_tag,
    print_table,
    pyplot,
    resolve,
    save_figure,
    scene_spec,
    schedule_overrides,
    variant_spec,
    write_json,
)

import mixnerf_eqx as mx

DEFAULT_SCENES = ["lego", "fern"]
DEFAULT_VARIANTS = [
    "mixnerf=scene",
    "mipnerf=scene:@baseline",
    "mixnerf-fast=scene:@fast",
    "mipnerf-fast=scene:@baseline,@fast",
]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data-dir", help="dataset root (default: $MIXNERF_DATA_DIR)")
    parser.add_argument(
        "--scene",
        action="append",
        type=scene_spec,
        help=f"lego, fern or NAME=CONFIG[:overrides]; repeat (default: {' '.join(DEFAULT_SCENES)})",
    )
    parser.add_argument(
        "--variant",
        action="append",
        type=variant_spec,
        help="NAME=scene[:overrides] or NAME=FILE[:overrides]; repeat (default: "
        + " ".join(DEFAULT_VARIANTS)
        + ")",
    )
    parser.add_argument(
        "--set",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help="config overrides for every variant (mlp.width=64 train.batch_size=512 ...)",
    )
    parser.add_argument("--budget-s", type=float, default=480.0, help="training seconds per run")
    parser.add_argument(
        "--eval-every-s", type=float, help="training seconds between evaluations (budget / 8)"
    )
    parser.add_argument("--eval-views", type=int, default=4, help="evenly spaced test views (0: all)")
    parser.add_argument("--eval-downscale", type=int, default=1, help="area-downsample the test views")
    parser.add_argument("--chunk", type=int, help="rays per render call (default: train.render_chunk)")
    parser.add_argument(
        "--max-steps", type=int, help="schedule length for every variant (default: estimated)"
    )
    parser.add_argument("--calibrate-steps", type=int, default=5, help="timed steps of the estimate")
    parser.add_argument(
        "--target", action="append", metavar="FAST:FAITHFUL", help="variant pairs for the time target"
    )
    parser.add_argument("--target-fraction", type=float, default=0.25)
    parser.add_argument("--out", default=str(RESULTS), help="output folder")
    parser.add_argument("--tag", default=None, help="file-name suffix (default: the JAX backend)")
    args = parser.parse_args()
    args.scene = args.scene or [scene_spec(name) for name in DEFAULT_SCENES]
    args.variant = args.variant or [variant_spec(text) for text in DEFAULT_VARIANTS]
    args.set = list(expand_overrides(args.set))
    if args.eval_every_s is None:
        args.eval_every_s = args.budget_s / 8
    if args.budget_s <= 0 or args.eval_every_s <= 0 or not 0 < args.target_fraction <= 1:
        parser.error("--budget-s and --eval-every-s must be positive, --target-fraction in (0, 1]")
    for what, specs in (("scene", args.scene), ("variant", args.variant)):
        names = [spec.name for spec in specs]
        if len(set(names)) != len(names):
            parser.error(f"{what} names must be unique, got {names}")
    names = [spec.name for spec in args.variant]
    if args.target:
        pairs = []
        for text in args.target:
            fast, sep, faithful = text.partition(":")
            if not sep or fast not in names or faithful not in names:
                parser.error(f"--target {text!r}: expected FAST:FAITHFUL with variant names from {names}")
            pairs.append((fast, faithful))
    else:
        pairs = [(f"{name}-fast", name) for name in names if f"{name}-fast" in names]
        if "fast" in names and "faithful" in names:
            pairs.append(("fast", "faithful"))
    args.pairs = pairs
    return args


def eval_marks(budget: float, every: float, fraction: float) -> list[float]:
    """Training times at which to evaluate: multiples of `every`, the target mark and the end."""
    marks = {round(every * k, 6) for k in range(1, int(budget / every) + 1) if every * k <= budget}
    marks |= {round(fraction * budget, 6), round(budget, 6)}
    return sorted(marks)


def train_variant(
    args: argparse.Namespace, scene, variant, cache: DatasetCache, run_id: str, jsonl: Path
) -> dict[str, Any]:
    """Trains one variant on one scene for the budget; returns its summary record."""
    record: dict[str, Any] = {"scene": scene.name, "variant": variant.name, "spec": variant.describe()}
    resolved = resolve(scene, variant, args.set)
    if resolved.skip_reason is not None:
        print(f"[{scene.name} {variant.name}] skipped: {resolved.skip_reason}")
        return {**record, "status": "skipped", "reason": resolved.skip_reason, "points": []}
    fixed = [*data_dir_override(args.data_dir), f"data.max_test_views={args.eval_views}"]
    base = load(resolved, fixed)
    dataset, data_info = cache.get(base)
    calibration = None
    if args.max_steps:
        max_steps = args.max_steps
    else:
        calibration = calibrate_steps(base, dataset, args.budget_s, args.calibrate_steps)
        max_steps = calibration["estimated_steps"]
    explicit = override_keys([*scene.overrides, *args.set, *variant.overrides])
    schedule = schedule_overrides(base, max_steps, explicit)
    config = load(resolved, [*fixed, *schedule])
    run = TrainingRun(config, dataset)
    chunk = run.render_chunk(args.chunk)
    compile_s = run.compile()
    record.update(
        {
            "config_file": resolved.path,
            "overrides": [*resolved.overrides, *fixed, *schedule],
            "model": model_summary(config),
            "data": data_info,
            "calibration": calibration,
            "max_steps": max_steps,
            "compile_s": compile_s,
        }
    )
    print(
        f"[{scene.name} {variant.name}] {record['model']}, schedule {max_steps} steps"
        + (f" (estimated: {calibration['calibrate_step_s']:.4f} s/step)" if calibration else "")
        + f", compiled in {compile_s:.1f} s",
        flush=True,
    )
    marks = eval_marks(args.budget_s, args.eval_every_s, args.target_fraction)
    points: list[dict[str, Any]] = []
    train_s = 0.0
    started = time.perf_counter()

    def evaluate_now(mark: float) -> None:
        eval_started = time.perf_counter()
        skipping = run.skipping()
        means = mx.evaluate(run.model, dataset, chunk=chunk, with_lpips=False, skipping=skipping).means
        point = {
            "run_id": run_id,
            "scene": scene.name,
            "variant": variant.name,
            "step": run.step,
            "train_seconds": train_s,
            "mark_s": mark,
            "psnr": means["psnr"],
            "ssim": means["ssim"],
            "compile_s": compile_s,
            "eval_s": time.perf_counter() - eval_started,
            "max_steps": max_steps,
            "skipped_steps": run.skipped,
            "skipping_render": skipping is not None,
        }
        points.append(point)
        append_jsonl(jsonl, point)
        print(
            f"[{scene.name} {variant.name}] step {run.step:6d}  train {train_s:8.1f} s  "
            f"PSNR {point['psnr']:.3f}  SSIM {point['ssim']:.4f}  (eval {point['eval_s']:.1f} s)",
            flush=True,
        )

    status = "ok"
    next_mark = 0
    try:
        while train_s < args.budget_s:
            train_s += run.advance()
            passed = None
            while next_mark < len(marks) and train_s >= marks[next_mark]:
                passed = marks[next_mark]
                next_mark += 1
            if passed is not None:  # a slow step may pass several marks: evaluate once
                evaluate_now(passed)
    except mx.training.TrainingDiverged as error:
        status = f"diverged: {error}"
        print(f"[{scene.name} {variant.name}] {status}")
    if not points or points[-1]["step"] != run.step:
        evaluate_now(args.budget_s)
    final = points[-1]
    record.update(
        {
            "status": status,
            "steps": run.step,
            "train_s": train_s,
            "steps_per_s": run.step / max(train_s, 1e-9),
            "skipped_steps": run.skipped,
            "wall_s": time.perf_counter() - started,
            "final_psnr": final["psnr"],
            "final_ssim": final["ssim"],
            "points": points,
        }
    )
    return record


def judge_target(fast: dict, faithful: dict, budget: float, fraction: float) -> dict[str, Any]:
    """When `fast` first reaches `faithful`'s final PSNR, against `fraction` of the budget."""
    result: dict[str, Any] = {"fast": fast["variant"], "faithful": faithful["variant"], "fraction": fraction}
    if not fast.get("points") or not faithful.get("points"):
        return {**result, "met": None, "verdict": "no data (a variant was skipped)"}
    goal = faithful["final_psnr"]
    limit = fraction * budget + 1e-6
    quarter = [p for p in fast["points"] if p["mark_s"] <= limit]
    hit = next((p for p in fast["points"] if p["psnr"] >= goal), None)
    best = max(fast["points"], key=lambda p: p["psnr"])
    result.update(
        {
            "goal_psnr": goal,
            "reached_at_s": None if hit is None else hit["train_seconds"],
            "reached_at_step": None if hit is None else hit["step"],
            "ratio_to_budget": None if hit is None else hit["train_seconds"] / budget,
            "psnr_at_fraction": quarter[-1]["psnr"] if quarter else None,
            "best_psnr": best["psnr"],
            "best_at_s": best["train_seconds"],
        }
    )
    # Met when the evaluation belonging to a mark at or before fraction x budget reached
    # the goal (that evaluation comes after the first step past the mark: up to one step late).
    met = hit is not None and hit["mark_s"] <= limit
    result["met"] = met
    if met:
        verdict = (
            f"met: reached at {hit['train_seconds']:.1f} s = {result['ratio_to_budget']:.3f} of the budget"
        )
    elif hit is not None:
        ratio = result["ratio_to_budget"]
        verdict = (
            f"missed: reached at {hit['train_seconds']:.1f} s = {ratio:.3f} of the budget, "
            f"{ratio / fraction:.2f}x the allowed {fraction:g} ({ratio - fraction:+.3f} of the budget)"
        )
    else:
        short = goal - best["psnr"]
        verdict = f"missed: not reached within the budget (best {best['psnr']:.2f} dB, {short:.2f} dB short"
        if result["psnr_at_fraction"] is not None:
            verdict += f"; at {fraction:g} of the budget {goal - result['psnr_at_fraction']:.2f} dB short"
        verdict += ")"
    if quarter and result["psnr_at_fraction"] is not None and met:
        verdict += f"; PSNR at {fraction:g} of the budget {result['psnr_at_fraction']:.2f} vs goal {goal:.2f}"
    result["verdict"] = verdict
    return result


def plot_scene(
    scene: str, records: list[dict], targets: list[dict], path: Path, budget: float, fraction: float
):
    plt = pyplot("plots")
    if plt is None:
        return
    fig, (by_time, by_step) = plt.subplots(1, 2, figsize=(12, 4.5))
    colours = {}
    for index, record in enumerate(records):
        colours[record["variant"]] = f"C{index % 10}"
        if not record.get("points"):
            continue
        points = record["points"]
        psnrs = [p["psnr"] for p in points]
        style = {"marker": "o", "color": colours[record["variant"]], "label": record["variant"]}
        by_time.plot([p["train_seconds"] for p in points], psnrs, **style)
        by_step.plot([p["step"] for p in points], psnrs, **style)
    by_time.axvline(fraction * budget, color="grey", linestyle=":", label=f"{fraction:g} x budget")
    for target in targets:  # the goals: each faithful variant's final PSNR, in its colour
        if target.get("goal_psnr") is not None:
            for axis in (by_time, by_step):
                axis.axhline(
                    target["goal_psnr"],
                    color=colours[target["faithful"]],
                    linestyle="--",
                    linewidth=0.8,
                    label=f"{target['faithful']} final" if axis is by_time else None,
                )
    by_time.set_xlabel("training seconds (compilation and evaluation excluded)")
    by_step.set_xlabel("steps")
    for axis in (by_time, by_step):
        axis.set_ylabel("test PSNR (dB)")
        axis.grid(alpha=0.3)
    by_time.legend(fontsize=8)
    fig.suptitle(f"{scene}: test PSNR against training time and steps")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def main() -> None:
    args = parse_args()
    tag = args.tag or platform_tag()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / f"error_vs_time_{tag}.jsonl"
    run_id = time.strftime("%Y%m%dT%H%M%S")
    machine = machine_info()
    print(f"run {run_id} on {machine['device_kind']} ({machine['backend']}); evaluations appended to {jsonl}")
    cache = DatasetCache(args.eval_downscale)
    records: list[dict[str, Any]] = []
    targets: dict[str, list[dict[str, Any]]] = {}
    for scene in args.scene:
        scene_records = [
            train_variant(args, scene, variant, cache, run_id, jsonl) for variant in args.variant
        ]
        records += scene_records
        by_name = {record["variant"]: record for record in scene_records}
        targets[scene.name] = [
            judge_target(by_name[fast], by_name[faithful], args.budget_s, args.target_fraction)
            for fast, faithful in args.pairs
        ]
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", scene.name)
        plot_scene(
            scene.name,
            scene_records,
            targets[scene.name],
            out / f"error_vs_time_{tag}_{safe}.png",
            args.budget_s,
            args.target_fraction,
        )

    print(f"\nbudget {args.budget_s:g} training seconds per run (compilation and evaluation excluded)\n")
    header = (
        "scene",
        "variant",
        "MLP",
        "samples",
        "matmul",
        "grid",
        "steps",
        "steps/s",
        "compile s",
        "PSNR",
        "SSIM",
    )
    rows = []
    for record in records:
        if record["status"] == "skipped":
            rows.append((record["scene"], record["variant"], "skipped", "", "", "", "", "", "", None, None))
            continue
        model = record["model"]
        rows.append(
            (
                record["scene"],
                record["variant"],
                model["mlp"],
                "+".join(str(n) for n in model["samples"]),
                model["matmul_dtype"],
                "occupancy" if model["occupancy"] else "none",
                record["steps"],
                record["steps_per_s"],
                record["compile_s"],
                record["final_psnr"],
                record["final_ssim"],
            )
        )
    print_table(header, rows)
    print(
        "\ntarget: the fast variant reaches the faithful final PSNR within "
        f"{args.target_fraction:g} of the budget"
    )
    if not args.pairs:
        print("  (no FAST:FAITHFUL pair among the variants: give --target)")
    for scene_name, scene_targets in targets.items():
        for target in scene_targets:
            print(f"  {scene_name}: {target['fast']} vs {target['faithful']}: {target['verdict']}")
    summary = {
        "run_id": run_id,
        "machine": machine,
        "args": {key: value for key, value in vars(args).items() if key not in ("scene", "variant")},
        "scenes": {spec.name: spec.describe() for spec in args.scene},
        "variants": {spec.name: spec.describe() for spec in args.variant},
        "targets": targets,
        "runs": records,
    }
    write_json(out / f"error_vs_time_{tag}.json", summary)


if __name__ == "__main__":
    main()
