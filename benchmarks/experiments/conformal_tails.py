"""Central or equal-tailed split-conformal intervals, compared by leaving one validation view
out at a time (`../uncertainty.md`, "Central or equal-tailed conformal intervals").

For each run: the predictive distribution function at the true colour (PIT values, no quantile
solve) of `--pixels` pixels drawn from each validation and each test view, kept per view in
`--cache` (one `.npz` per run and checkpoint step, reused when present). Then, per run:

- leave one validation view out: both intervals calibrated on the other validation views'
  pixels, scored on the held-out view; the run's figure is the mean over its validation views
  and the levels of `|coverage - nominal|` (the three channels pooled);
- for the record, both calibrated on every validation view and scored on the test views
  pooled.

Both are written out here, so that the comparison stays reproducible whichever the library
ships: the central intervals (`central_levels`: the library's `conformal` until the commit
after e50ed61) take one score `|2u - 1|` per pixel and the `ceil((n + 1) m)`-th smallest as
the mass `q` of both ends; the equal-tailed ones (`equal_tailed_levels`, the library's
`conformal` since) bound each end by an order statistic of the calibration PIT values.
Printed: a table per run and the paired verdict of the rule.

    python benchmarks/experiments/conformal_tails.py --data-dir ../shared/data \\
        --runs runs/qs_ship3/builtin/seed_0 ... --cache runs/conformal_tails \\
        --out benchmarks/results/conformal_tails_cpu
"""

import argparse
import math
import sys
from pathlib import Path

import numpy as np

import mixnerf_eqx as mx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from fidelity import paired_from_diffs  # noqa: E402
from harness import write_json, write_markdown  # noqa: E402

MASSES = (0.5, 0.8, 0.9, 0.95)
METHODS = ("central", "equal-tailed")


def equal_tailed_levels(pit: np.ndarray, masses) -> tuple[np.ndarray, np.ndarray]:
    """Per mass and channel, the raw levels `(lower, upper)` of the equal-tailed split-conformal
    interval: the `floor((n + 1)(1 - m) / 2)`-th and `ceil((n + 1)(1 + m) / 2)`-th smallest of
    the `n` calibration PIT values (0 and 1, an end without bound, where that rank falls
    outside 1..n)."""
    values = np.sort(np.clip(pit, 0.0, 1.0), axis=0)
    count = values.shape[0]
    lower, upper = [], []
    for mass in masses:
        low = math.floor((count + 1) * (1.0 - mass) / 2.0 + 1e-9)
        high = math.ceil((count + 1) * (1.0 + mass) / 2.0 - 1e-9)
        lower.append(values[low - 1] if low >= 1 else np.zeros(values.shape[1]))
        upper.append(values[high - 1] if high <= count else np.ones(values.shape[1]))
    return np.stack(lower), np.stack(upper)


def central_levels(pit: np.ndarray, masses) -> tuple[np.ndarray, np.ndarray]:
    """Per mass and channel, the raw levels `(0.5 (1 - q), 0.5 (1 + q))` of the central
    split-conformal interval: `q` the `ceil((n + 1) m)`-th smallest score `|2u - 1|`."""
    scores = np.sort(np.abs(2.0 * np.clip(pit, 0.0, 1.0) - 1.0), axis=0)
    count = scores.shape[0]
    spread = np.stack([scores[math.ceil((count + 1) * mass - 1e-9) - 1] for mass in masses])
    return np.clip(0.5 * (1.0 - spread), 0.0, 1.0), np.clip(0.5 * (1.0 + spread), 0.0, 1.0)


LEVELS = {"central": central_levels, "equal-tailed": equal_tailed_levels}


def coverage(pit: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per mass, the fraction of `pit`'s values (pixels x channels, pooled) inside the levels.

    The values are clipped to [0, 1] first, as the levels are fitted: a float32 sum of
    coefficients may round a little past 1, and a level of 1 is an end without bound, which
    holds every value (until 2026-12-07 such values counted as misses)."""
    pit = np.clip(pit, 0.0, 1.0)
    return np.array([np.mean((pit >= lo) & (pit <= hi)) for lo, hi in zip(lower, upper, strict=True)])


def pit_per_view(run_dir: str, args) -> dict[str, list[np.ndarray]]:
    # The run's latest checkpoint names the model: a run trained again in the same folder
    # (a later step) is not read from an old cache.
    run = mx.runs.restore_run(run_dir, data_dir=args.data_dir)
    step = run.step
    cache = Path(args.cache) / (run_dir.strip("/").replace("/", "__") + f"_step{step}_{args.pixels}.npz")
    if cache.is_file():
        stored = np.load(cache)
        return {
            split: [stored[f"{split}_{i}"] for i in range(int(stored[f"{split}_count"]))]
            for split in ("val", "test")
        }
    dataset = run.dataset
    out = {}
    for split, views in (("val", dataset.split("val")), ("test", dataset.test)):
        out[split] = [
            mx.uncertainty.calibration_pit(
                run.model,
                views.select([i]),
                dataset.near,
                dataset.far,
                args.chunk,
                max_pixels=args.pixels,
                seed=i,
            )["colour_cdf"]
            for i in range(views.num_views)
        ]
        print(f"  {run_dir}: {split} {views.num_views} views", flush=True)
    cache.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"{split}_{i}": pit for split, views in out.items() for i, pit in enumerate(views)}
    np.savez(cache, val_count=len(out["val"]), test_count=len(out["test"]), **arrays)
    return out


def score_run(per_view: dict[str, list[np.ndarray]]) -> dict:
    val, test = per_view["val"], per_view["test"]
    nominal = np.asarray(MASSES)
    result = {}
    for method in METHODS:
        gaps = []
        for held in range(len(val)):
            rest = np.concatenate([pit for i, pit in enumerate(val) if i != held])
            gaps.append(coverage(val[held], *LEVELS[method](rest, MASSES)) - nominal)
        gaps = np.asarray(gaps)  # (views, masses)
        levels = LEVELS[method](np.concatenate(val), MASSES)
        result[method] = {
            "leave_one_out_gap": float(np.mean(np.abs(gaps))),
            "leave_one_out_by_view": gaps.tolist(),
            "test_pooled": coverage(np.concatenate(test), *levels).tolist(),
            "test_by_view": [coverage(pit, *levels).tolist() for pit in test],
        }
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--pixels", type=int, default=16384, help="pixels drawn from each view")
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--cache", default="runs/conformal_tails")
    parser.add_argument("--out", default=None, help="write OUT.json and OUT.md")
    args = parser.parse_args()

    runs = {}
    for run_dir in args.runs:
        runs[run_dir] = score_run(pit_per_view(run_dir, args))
    lines = [
        "| run | method | leave-one-view-out mean abs gap (val) | test coverage 50% | 80% | 90% | 95% |",
        "|---|---|---|---|---|---|---|",
    ]
    for run_dir, result in runs.items():
        for method in METHODS:
            entry = result[method]
            cover = " | ".join(f"{value:.3f}" for value in entry["test_pooled"])
            lines.append(f"| {run_dir} | {method} | {entry['leave_one_out_gap']:.4f} | {cover} |")
    difference = np.array(
        [r["central"]["leave_one_out_gap"] - r["equal-tailed"]["leave_one_out_gap"] for r in runs.values()]
    )
    # Lower is better for a gap, so equal-tailed is ahead when central - equal-tailed > 0.
    found = paired_from_diffs(list(range(len(difference))), difference.tolist(), higher_is_better=True)
    mean, half = found["mean"], found["half_width_95"]
    verdict = {"ahead": "equal-tailed ahead", "behind": "central ahead"}.get(
        found["verdict"], found["verdict"]
    )
    summary = (
        f"central - equal-tailed, leave-one-view-out mean abs gap, paired over {len(difference)} runs: "
        f"{mean:+.4f} ± {half:.4f} (Student-t 95%): {verdict}"
    )
    lines += ["", summary]
    print("\n".join(lines))
    if args.out:
        record = {
            "masses": MASSES,
            "runs": runs,
            "difference": difference.tolist(),
            "mean": mean,
            "half_width": half,
            "verdict": verdict,
        }
        write_json(Path(args.out + ".json"), record)
        write_markdown(Path(args.out + ".md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
