"""The MLP capacity ladder: from which MLP size on does the baseline overfit or collapse, and
does MixNeRF hold there?

    python benchmarks/ladder_table.py                # the CPU's rungs (results/fidelity_cpu_ladder_*)
    python benchmarks/ladder_table.py --backend gpu  # the rungs `gpu_ladder.sh` made

Each rung is one `fidelity.py` result file, `fidelity_<backend>_ladder_<depth>x<width>.jsonl`:
the fidelity protocol on the built-in scene at 500 epochs, MixNeRF and its baseline, with the
MLP set by `--set mlp.depth=... mlp.width=...` (`gpu_ladder.sh` and `benchmarks/fidelity.md` give
the commands). This script puts the rungs side by side, smallest MLP first:

- per rung and method: the test PSNR at the end, the test PSNR at the curve's best point by
  validation PSNR and how far the end falls below it, the training views' PSNR at the end and
  its gap to the test views', the runs that overfit (from the best point to the end held-out
  PSNR falls by more than 0.1 dB while training PSNR rises: `fidelity.summarise`'s rule) and
  the runs that failed (test PSNR more than 3 dB below the median of the baseline's runs on
  the rung);
- per rung: MixNeRF - baseline paired by seed on the test views at the end (PSNR, depth MAE),
  mean ± the half-width of its Student-t 95% interval, "ahead"/"behind" only when the
  interval excludes zero.

Writes `results/ladder_<backend>.md`, `results/ladder_<backend>_summary.json` and
`results/ladder_<backend>.png` (end test and training PSNR against the MLP's parameter count).
"""

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fidelity import (  # noqa: E402
    FAIL_DB,
    PROTOCOL,
    _best_entry,
    failed,
    paired_verdict,
    read_runs,
    verdict_cell,
)
from harness import REPO, RESULTS, pyplot, save_figure, write_json, write_markdown  # noqa: E402

SCENE = "builtin"
METHOD_NAMES = {"mipnerf": "baseline", "mixnerf": "MixNeRF"}
RUNG_FILE = re.compile(r"fidelity_(?P<backend>[a-z]+)_ladder_(?P<depth>\d+)x(?P<width>\d+)\.jsonl")


def rung_files(results: Path, backend: str) -> list[tuple[int, int, Path]]:
    """(depth, width, path) of every rung of `backend` in `results`, smallest MLP first."""
    found = []
    for path in results.glob(f"fidelity_{backend}_ladder_*.jsonl"):
        match = RUNG_FILE.fullmatch(path.name)
        if match is not None:
            found.append((int(match["depth"]), int(match["width"]), path))
    return sorted(found, key=lambda rung: (rung[1] * rung[1] * rung[0], rung[0]))


def parameter_count(run: dict[str, Any]) -> int:
    """The number of trained parameters of a run's model, built from its config and overrides."""
    import equinox as eqx
    import jax

    import mixnerf_eqx as mx

    config = mx.load_config(str(REPO / run["base_config"]), run["overrides"])
    model = mx.build_model(config, key=jax.random.key(0))
    return int(sum(leaf.size for leaf in jax.tree.leaves(eqx.filter(model, eqx.is_array))))


def _mean_sd(values: list[float]) -> tuple[float, float]:
    array = np.asarray(values, np.float64)
    return float(array.mean()), float(array.std(ddof=1)) if array.size > 1 else float("nan")


def _fmt(stats: tuple[float, float], digits: int = 2, sign: bool = False) -> str:
    mean, sd = stats
    head = f"{mean:+.{digits}f}" if sign else f"{mean:.{digits}f}"
    return head if np.isnan(sd) else f"{head} ± {sd:.{digits}f}"


def method_row(runs: list[dict[str, Any]], baseline: dict[int, float]) -> dict[str, Any]:
    """One method's figures on one rung, per seed and as mean and sample standard deviation;
    `baseline` holds the baseline's end test PSNR per seed, the line for failed runs."""
    runs = sorted(runs, key=lambda r: r["seed"])
    ends = [r["final"]["test"]["psnr"] for r in runs]
    chosen = [_best_entry(r) for r in runs]
    bests = [entry for entry, _ in chosen]
    best = [b["test"]["psnr"] for b in bests]
    train = [r["final"]["train_psnr"] for r in runs]
    overfit = [
        end < b["test"]["psnr"] - 0.1 and r["final"]["train_psnr"] > b["train_psnr"]
        for r, b, end in zip(runs, bests, ends, strict=True)
    ]
    return {
        "seeds": [r["seed"] for r in runs],
        "end_test_psnr": ends,
        "best_test_psnr": best,
        "best_steps": [b["step"] for b in bests],
        "best_chosen_on": sorted({how for _, how in chosen}),
        "fall": [e - b for e, b in zip(ends, best, strict=True)],
        "end_train_psnr": train,
        "gap": [t - e for t, e in zip(train, ends, strict=True)],
        "overfit_seeds": [r["seed"] for r, o in zip(runs, overfit, strict=True) if o],
        "failed_seeds": failed({r["seed"]: e for r, e in zip(runs, ends, strict=True)}, baseline),
    }


def ladder(results: Path, backend: str, count_parameters: bool = True) -> dict[str, Any]:
    """Every rung's figures (see the module's docstring)."""
    rungs = []
    for depth, width, path in rung_files(results, backend):
        runs = [r for r in read_runs(path) if r["scene"] == SCENE]
        for run in runs:
            mlp = run.get("model", {}).get("mlp", f"{depth}x{width}")
            if mlp != f"{depth}x{width}" or run.get("field", "mlp") != "mlp":
                raise SystemExit(
                    f"{path.name}: run {run['key']} trained a {run.get('field', 'mlp')} field with "
                    f"MLP {mlp}, not the rung's {depth}x{width} MLP"
                )
        by_method = {m: [r for r in runs if r["method"] == m] for m in METHOD_NAMES}
        if not any(by_method.values()):
            continue
        rung: dict[str, Any] = {
            "mlp": f"{depth}x{width}",
            "file": path.name,
            "epochs": sorted({r["epochs"] for r in runs}),
            "parameters": {m: parameter_count(g[0]) for m, g in by_method.items() if g and count_parameters},
            "methods": {
                m: method_row(g, {r["seed"]: r["final"]["test"]["psnr"] for r in by_method["mipnerf"]})
                for m, g in by_method.items()
                if g
            },
        }
        for key, higher in (("psnr", True), ("depth_mae", False)):
            mix = {r["seed"]: r["final"]["test"].get(key) for r in by_method["mixnerf"]}
            base = {r["seed"]: r["final"]["test"].get(key) for r in by_method["mipnerf"]}
            rung[f"verdict_{key}"] = paired_verdict(
                {s: v for s, v in mix.items() if v is not None},
                {s: v for s, v in base.items() if v is not None},
                higher,
            )
        rungs.append(rung)
    if count_parameters:  # the file names' order by width^2 x depth, made exact
        rungs.sort(key=lambda rung: min(rung["parameters"].values()))
    return {"backend": backend, "scene": SCENE, "rungs": rungs}


def markdown(found: dict[str, Any]) -> str:
    size = PROTOCOL[SCENE][1]
    lines = [
        f"# MLP capacity ladder ({found['backend']}; built-in scene, 4 views at 32x32, "
        f"the fidelity protocol: {', '.join(size)})",
        "",
        "Settings fixed in advance (the protocol's), nothing chosen on these runs; the best point "
        "of a curve is chosen on the validation views (a run without them says so), every score "
        "is on the test views. Mean ± sample standard deviation over seeds; per-seed figures are "
        "in the summary JSON.",
        "",
        "| MLP | parameters | epochs | method | seeds | end test PSNR | test PSNR at the best point "
        "(chosen on) | end - best | end train PSNR | train - test | overfit runs | failed runs |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for rung in found["rungs"]:
        for method, name in (("mipnerf", "baseline"), ("mixnerf", "MixNeRF")):
            row = rung["methods"].get(method)
            if row is None:
                lines.append(f"| {rung['mlp']} | | | {name} | 0 | not made | | | | | | |")
                continue
            params = rung["parameters"].get(method)
            n = len(row["seeds"])
            cells = [
                rung["mlp"],
                f"{params:,}" if params is not None else "n/a",
                ", ".join(f"{e:g}" for e in rung["epochs"]),
                name,
                str(n),
                _fmt(_mean_sd(row["end_test_psnr"])),
                f"{_fmt(_mean_sd(row['best_test_psnr']))} ({', '.join(row['best_chosen_on'])})",
                _fmt(_mean_sd(row["fall"]), sign=True),
                _fmt(_mean_sd(row["end_train_psnr"])),
                _fmt(_mean_sd(row["gap"])),
                f"{len(row['overfit_seeds'])} of {n}",
                f"{len(row['failed_seeds'])} of {n}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "| MLP | seeds | test PSNR, MixNeRF - baseline | test depth MAE, MixNeRF - baseline |",
        "|---|---|---|---|",
    ]
    for rung in found["rungs"]:
        psnr, depth = rung["verdict_psnr"], rung["verdict_depth_mae"]
        seeds = len(psnr["seeds"]) if psnr else 0
        lines.append(f"| {rung['mlp']} | {seeds} | {verdict_cell(psnr)} | {verdict_cell(depth, 4)} |")
    lines += [
        "",
        f"A run overfits when, from its best point to the end, its test PSNR falls by more than "
        f"0.1 dB while its training PSNR rises; it failed when its end test PSNR lies more than "
        f"{FAIL_DB:g} dB below the median of the baseline's runs on the rung. MixNeRF - baseline: "
        "mean ± the half-width of its Student-t 95% interval (n - 1 degrees of freedom); 'ahead' or "
        "'behind' only when the interval excludes zero.",
    ]
    return "\n".join(lines) + "\n"


def plot(found: dict[str, Any], path: Path) -> None:
    plt = pyplot("plot")
    if plt is None:
        return
    figure, (held_out, training) = plt.subplots(1, 2, figsize=(11, 4))
    colours = {"mipnerf": "tab:blue", "mixnerf": "tab:red"}
    for method, name in METHOD_NAMES.items():
        xs, ends, bests, trains = [], [], [], []
        for rung in found["rungs"]:
            row = rung["methods"].get(method)
            if row is None or method not in rung["parameters"]:
                continue
            x = rung["parameters"][method]
            for end, train in zip(row["end_test_psnr"], row["end_train_psnr"], strict=True):
                held_out.scatter(x, end, color=colours[method], s=12)
                training.scatter(x, train, color=colours[method], s=12)
            xs.append(x)
            ends.append(np.mean(row["end_test_psnr"]))
            bests.append(np.mean(row["best_test_psnr"]))
            trains.append(np.mean(row["end_train_psnr"]))
        if xs:
            held_out.plot(xs, ends, color=colours[method], label=f"{name}: end")
            held_out.plot(
                xs,
                bests,
                color=colours[method],
                ls="--",
                lw=0.8,
                label=f"{name}: at the best validation point",
            )
            training.plot(xs, trains, color=colours[method], label=name)
    for axis, title in ((held_out, "test views"), (training, "training views")):
        axis.set(xscale="log", xlabel="parameters", ylabel="PSNR (dB)", title=f"built-in: {title}")
        axis.legend(fontsize=7)
    for rung in found["rungs"]:
        if rung["parameters"]:
            x = min(rung["parameters"].values())
            held_out.annotate(rung["mlp"], (x, held_out.get_ylim()[0]), fontsize=7)
    figure.tight_layout()
    save_figure(figure, path, dpi=90)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--backend", default="cpu", help="the rungs' backend tag (cpu, gpu)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the result files' folder")
    args = parser.parse_args(argv)
    found = ladder(args.results, args.backend)
    if not found["rungs"]:
        print(f"no rungs: no fidelity_{args.backend}_ladder_<D>x<W>.jsonl in {args.results}")
        return 1
    text = markdown(found)
    print(text, end="")
    stem = args.results / f"ladder_{args.backend}"
    write_markdown(stem.with_suffix(".md"), text)
    write_json(stem.with_name(stem.name + "_summary.json"), found)
    plot(found, stem.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
