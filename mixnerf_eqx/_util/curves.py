"""A run's training curves as one figure (`curves.png`), read from its `train_log.jsonl`.

Needs matplotlib (the `plots` extra); without it `plot_curves` says so and writes nothing.
"""

import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

# Entries that are not loss terms: plotted in their own panels, or not at all.
_NOT_TERMS = {"step", "loss", "psnr", "lr", "lambda_colour", "skipped_steps", "steps_per_s"}


def read_log(path: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The step entries and the evaluation entries of a `train_log.jsonl` (a line cut short
    by a kill is left out)."""
    steps, evaluations = [], []
    for line in Path(path).read_text().splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(entry, dict) and "step" in entry:
            (evaluations if "eval" in entry else steps).append(entry)
    return steps, evaluations


def pyplot(what: str) -> ModuleType | None:
    """`matplotlib.pyplot` on the file-only Agg backend, or `None` where matplotlib is not
    installed, after printing that there are no `what` (e.g. "plots") and how to get them.
    The benchmarks, which use the public API only, have its twin (`benchmarks/harness.py`)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"no {what}: matplotlib is not installed (pip install 'mixnerf_eqx[plots]')")
        return None
    return plt


def _value(entry: dict[str, Any], name: str) -> float:
    """`entry[name]` as a number; NaN where it is missing or not finite (a skipped step logs
    `null`), which leaves a gap in its curve."""
    value = entry.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return math.nan
    return float(value)


def plot_curves(run_dir: str | Path, out: str | Path | None = None) -> Path | None:
    """Writes `curves.png` for the run in `run_dir`: training PSNR and the periodic evaluations'
    PSNR, every loss term that is ever non-zero (log scale), the total loss, and the learning
    rate and lambda_C, each against the step (a skipped step's missing values leave gaps).
    Returns the file, or `None` (with the reason printed) where there is no log, no
    matplotlib or no writable file."""
    run_dir = Path(run_dir)
    log = run_dir / "train_log.jsonl"
    if not log.is_file():
        print(f"no curves: {log} does not exist")
        return None
    plt = pyplot("curves")
    if plt is None:
        return None
    steps, evaluations = read_log(log)
    if not steps:
        print(f"no curves: {log} holds no training steps yet")
        return None
    x = [entry["step"] for entry in steps]
    figure, axes = plt.subplots(1, 3, figsize=(15, 4), constrained_layout=True)
    psnr_axis, terms_axis, schedule_axis = axes
    psnr_axis.plot(x, [_value(entry, "psnr") for entry in steps], label="training batch", lw=1)
    for split in sorted({entry.get("split", "val") for entry in evaluations}):
        chosen = [entry for entry in evaluations if entry.get("split", "val") == split]
        points = [(entry["step"], _value(entry["eval"], "psnr")) for entry in chosen]
        points = [(step, psnr) for step, psnr in points if math.isfinite(psnr)]
        if points:
            psnr_axis.plot(*zip(*points, strict=True), "o-", label=f"{split} views")
    psnr_axis.set(xlabel="step", ylabel="PSNR (dB)", title="PSNR")
    psnr_axis.legend()
    terms = [name for name in steps[0] if name not in _NOT_TERMS]
    terms_axis.plot(
        x, [abs(_value(entry, "loss")) for entry in steps], label="|total|", color="black", lw=1.5
    )
    for name in terms:
        values = [abs(_value(entry, name)) for entry in steps]
        if any(value > 0 for value in values):  # NaN compares false
            terms_axis.plot(x, [value if value > 0 else math.nan for value in values], label=name, lw=1)
    terms_axis.set(xlabel="step", yscale="log", title="loss terms (absolute value, unweighted)")
    terms_axis.legend(fontsize="small")
    schedule_axis.plot(x, [_value(entry, "lr") for entry in steps], label="learning rate")
    if any(_value(entry, "lambda_colour") > 0 for entry in steps):
        schedule_axis.plot(x, [_value(entry, "lambda_colour") for entry in steps], label="lambda_C")
    schedule_axis.set(xlabel="step", yscale="log", title="schedules")
    schedule_axis.legend()
    figure.suptitle("/".join(run_dir.resolve().parts[-2:]))
    path = Path(out) if out is not None else run_dir / "curves.png"
    try:
        figure.savefig(path, dpi=100)
    except OSError as error:
        print(f"no curves: {path}: {error.strerror or error}")
        return None
    finally:
        plt.close(figure)
    return path
