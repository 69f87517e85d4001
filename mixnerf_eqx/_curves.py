"""A run's training curves as one figure (`curves.png`), read from its `train_log.jsonl`.

Needs matplotlib (the `plots` extra); without it `plot_curves` says so and writes nothing.
"""

import json
from pathlib import Path
from typing import Any

# Entries that are not loss terms: plotted in their own panels, or not at all.
_NOT_TERMS = {"step", "loss", "psnr", "lr", "lambda_colour", "skipped_steps", "steps_per_s"}


def read_log(path: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The step entries and the evaluation entries of a `train_log.jsonl`."""
    steps, evaluations = [], []
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        entry = json.loads(line)
        (evaluations if "eval" in entry else steps).append(entry)
    return steps, evaluations


def plot_curves(run_dir: str | Path, out: str | Path | None = None) -> Path | None:
    """Writes `curves.png` for the run in `run_dir`: training PSNR and the periodic evaluations'
    PSNR, every loss term that is ever non-zero (log scale), the total loss, and the learning
    rate and lambda_C, each against the step. Returns the file, or `None` (with the reason
    printed) where there is no log or no matplotlib."""
    run_dir = Path(run_dir)
    log = run_dir / "train_log.jsonl"
    if not log.is_file():
        print(f"no curves: {log} does not exist")
        return None
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("no curves: matplotlib is not installed (pip install 'mixnerf_eqx[plots]')")
        return None
    steps, evaluations = read_log(log)
    if not steps:
        print(f"no curves: {log} holds no training steps yet")
        return None
    x = [entry["step"] for entry in steps]
    figure, axes = plt.subplots(1, 3, figsize=(15, 4), constrained_layout=True)
    psnr_axis, terms_axis, schedule_axis = axes
    psnr_axis.plot(x, [entry["psnr"] for entry in steps], label="training batch", lw=1)
    for split in sorted({entry.get("split", "val") for entry in evaluations}):
        points = [(e["step"], e["eval"].get("psnr")) for e in evaluations if e.get("split", "val") == split]
        points = [(s, p) for s, p in points if p is not None]
        if points:
            psnr_axis.plot(*zip(*points, strict=True), "o-", label=f"{split} views")
    psnr_axis.set(xlabel="step", ylabel="PSNR (dB)", title="PSNR")
    psnr_axis.legend()
    terms = [name for name in steps[0] if name not in _NOT_TERMS]
    terms_axis.plot(x, [abs(entry["loss"]) for entry in steps], label="|total|", color="black", lw=1.5)
    for name in terms:
        values = [entry.get(name, 0.0) for entry in steps]
        if any(value not in (0.0, None) for value in values):
            terms_axis.plot(x, [abs(value) if value else float("nan") for value in values], label=name, lw=1)
    terms_axis.set(xlabel="step", yscale="log", title="loss terms (absolute value, unweighted)")
    terms_axis.legend(fontsize="small")
    schedule_axis.plot(x, [entry["lr"] for entry in steps], label="learning rate")
    if any(entry.get("lambda_colour", 0.0) for entry in steps):
        schedule_axis.plot(x, [entry["lambda_colour"] for entry in steps], label="lambda_C")
    schedule_axis.set(xlabel="step", yscale="log", title="schedules")
    schedule_axis.legend()
    figure.suptitle("/".join(run_dir.resolve().parts[-2:]))
    path = Path(out) if out is not None else run_dir / "curves.png"
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path
