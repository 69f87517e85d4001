"""Where a trained run's held-out quality is lost: more samples at render time, and earlier
checkpoints, scored on the validation views (never the test views).

    python benchmarks/quality_gap.py runs/fern5/noramp/fern/seed_4 --data-dir ../shared/data \
        --samples 32,32 64,64 128,128 --out benchmarks/results/quality_gap_fern_noramp_seed4

For each run folder: the validation views rendered by the latest checkpoint with each
`COARSE,FINE` sample count of `--samples` (the field is the trained one; only the samplers
change, so a gain here says the run's sample counts cost quality), and by every checkpoint the
run kept with its own counts (a curve over training: a still-falling LPIPS says more steps
would help). PSNR, SSIM and LPIPS per setting, means over the views.

Output: `--out STEM` writes `STEM.json` and `STEM.md`.
"""

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import equinox as eqx

import mixnerf_eqx as mx


def with_samples(model: mx.MixNeRF, coarse: int, fine: int) -> mx.MixNeRF:
    """`model` with samplers of `coarse` and `fine` samples per ray, everything else as trained."""
    coarse_sampler = dataclasses.replace(model.coarse_sampler, num_samples=coarse)
    fine_sampler = dataclasses.replace(model.fine_sampler, num_samples=fine)
    model = eqx.tree_at(lambda m: m.coarse_sampler, model, coarse_sampler)
    return eqx.tree_at(lambda m: m.fine_sampler, model, fine_sampler)


def score(model: mx.MixNeRF, dataset, chunk: int) -> dict[str, Any]:
    result = mx.evaluate(model, dataset, chunk=chunk, split="val")
    metrics = {key: result.means[key] for key in ("psnr", "ssim", "lpips")}
    return {**metrics, "views": len(result.per_view), "seconds": result.seconds}


def probe(run_dir: Path, samples: list[tuple[int, int]], data_dir: str | None, chunk: int) -> dict[str, Any]:
    latest = mx.runs.restore_run(run_dir, data_dir=data_dir)
    dataset, model = latest.dataset, latest.state.model
    trained = (model.coarse_sampler.num_samples, model.fine_sampler.num_samples)
    by_samples = {}
    for coarse, fine in samples:
        by_samples[f"{coarse},{fine}"] = score(with_samples(model, coarse, fine), dataset, chunk)
        print(f"{run_dir} step {latest.step}, {coarse}+{fine} samples: {by_samples[f'{coarse},{fine}']}")
    # The latest checkpoint at its own counts is scored once.
    by_step = {str(latest.step): by_samples.get(f"{trained[0]},{trained[1]}")}
    for checkpoint in mx.runs.checkpoints(run_dir):
        try:
            run = mx.runs.restore_run(run_dir, checkpoint=checkpoint, data_dir=data_dir, dataset=dataset)
        except (mx.runs.CheckpointError, mx.ConfigError) as error:
            print(f"warning: {checkpoint} left out: {error}", file=sys.stderr)
            continue
        if by_step.get(str(run.step)) is None:
            by_step[str(run.step)] = score(run.state.model, dataset, chunk)
            print(f"{run_dir} step {run.step}, trained samples: {by_step[str(run.step)]}")
    return {
        "run": str(run_dir),
        "step": latest.step,
        "trained_samples": trained,
        "by_samples": by_samples,
        "by_step": dict(sorted(by_step.items(), key=lambda item: int(item[0]))),
    }


def _figures(metrics: dict[str, Any]) -> str:
    """PSNR, SSIM and LPIPS cells ("n/a" where a metric was not computed, e.g. LPIPS without
    its weights)."""
    cells = []
    for key, digits in (("psnr", 2), ("ssim", 3), ("lpips", 3)):
        value = metrics.get(key)
        cells.append("n/a" if value is None else f"{value:.{digits}f}")
    return " | ".join(cells)


def markdown(results: list[dict[str, Any]]) -> str:
    lines = ["| run | setting | val PSNR | val SSIM | val LPIPS |", "|---|---|---|---|---|"]
    for result in results:
        coarse, fine = result["trained_samples"]
        for name, metrics in result["by_samples"].items():
            label = f"step {result['step']}, {name.replace(',', ' + ')} samples"
            label += " (as trained)" if name == f"{coarse},{fine}" else ""
            lines.append(f"| {result['run']} | {label} | {_figures(metrics)} |")
        for step, metrics in result["by_step"].items():
            if step == str(result["step"]) and f"{coarse},{fine}" in result["by_samples"]:
                continue  # the row "as trained" above
            lines.append(
                f"| {result['run']} | step {step}, {coarse} + {fine} samples | {_figures(metrics)} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "runs", nargs="+", type=Path, help="run folders (each with config.json and checkpoints/)"
    )
    parser.add_argument("--data-dir", help="the dataset root, replacing the runs'")
    parser.add_argument(
        "--samples",
        nargs="+",
        default=["32,32", "64,64", "128,128"],
        help="COARSE,FINE sample counts to render with",
    )
    parser.add_argument("--chunk", type=int, default=4096, help="rays rendered at once")
    parser.add_argument("--out", type=Path, help="write STEM.json and STEM.md")
    args = parser.parse_args()
    samples = []
    for item in args.samples:
        try:
            coarse, fine = (int(x) for x in item.split(","))
        except ValueError:
            parser.error(f"--samples takes COARSE,FINE pairs of whole numbers, got {item!r}")
        if coarse < 1 or fine < 1:
            parser.error(f"--samples counts must be at least 1, got {item!r}")
        if (coarse, fine) not in samples:
            samples.append((coarse, fine))
    if args.chunk < 1:
        parser.error(f"--chunk must be at least 1, got {args.chunk}")
    results = []
    for run in args.runs:
        try:
            results.append(probe(run, samples, args.data_dir, args.chunk))
        except (mx.ConfigError, mx.runs.CheckpointError, ValueError) as error:
            raise SystemExit(f"error: {run}: {error}") from None
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    table = markdown(results)
    print(table)
    if args.out:
        args.out.with_suffix(".md").write_text(table)


if __name__ == "__main__":
    main()
