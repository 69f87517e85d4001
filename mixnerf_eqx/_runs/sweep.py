"""A config over every scene of its benchmark and several seeds, and the table it makes.

A sweep is a list of ordinary runs, one folder each (`<out>/<scene>/seed_<seed>`), so the
resume machinery of `fit` is the sweep's: a finished run (its `metrics.json` written for these
settings) is read, not trained again; an unfinished one continues from its newest checkpoint.
The runs go one after another in this process, or as jobs of submitit (`engine="submitit"`:
Slurm, or its local executor), each job calling `run_one` on one run's config.
"""

import dataclasses
import json
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._config import Config, ConfigError, config_from_dict
from .._nn.model import check_model_names
from .._util import json_io as strict_json
from ..data import FORMATS
from .checkpoint import CheckpointError, latest_checkpoint, read_checkpoint_meta
from .run_folder import check_resumable, continued_config


def _known_scenes(dataset: str) -> tuple[str, ...]:
    """The scenes whose mean a paper's table reports for `dataset` (its format's own list, read
    when asked, so that a format registered later counts); an unknown format is an error."""
    if dataset == "builtin":
        return ("builtin",)
    if dataset not in FORMATS:
        raise ConfigError(f"unknown data.dataset {dataset!r}; choose one of builtin, {', '.join(FORMATS)}")
    return FORMATS[dataset].scenes

METRICS = ("psnr", "ssim", "lpips", "depth_mae")
_PUBLISHED = re.compile(r"\b(PSNR|SSIM|LPIPS)\s+([0-9]*\.?[0-9]+)")


@dataclasses.dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: its scene, seed and full config (whose `train.run_dir` is its folder)."""

    scene: str
    seed: int
    config: Config

    @property
    def run_dir(self) -> Path:
        return Path(self.config.train.run_dir)


def benchmark_scenes(config: Config) -> tuple[str, ...]:
    """The scenes of `config`'s benchmark (`data.dataset`)."""
    scenes = _known_scenes(config.data.dataset)
    if not scenes:
        raise ConfigError(
            f"data.dataset = {config.data.dataset!r} has no benchmark scenes; name them with --scenes"
        )
    return scenes


SWEEP_REMEDY = "the sweep folder holds runs of other settings: choose another --out"


def _check_scene_names(config: Config, scenes: Sequence[str]) -> None:
    """Refuses, before any run, a scene that is neither its benchmark's nor a folder of the
    dataset's root (a scene whose files are missing still fails only its own runs)."""
    from ..data import DatasetError, UnknownSceneError, data_root, find_scene

    known = _known_scenes(config.data.dataset)
    if not known or all(scene in known for scene in scenes):
        return
    try:
        root = data_root(config.data)
    except DatasetError:
        root = None
    for scene in scenes:
        if scene in known:
            continue
        if root is None:
            raise ConfigError(
                f"unknown {config.data.dataset} scene {scene!r}: "
                f"the benchmark's scenes are {', '.join(known)}"
            )
        try:
            find_scene(root, config.data.dataset, scene)
        except UnknownSceneError as error:
            raise ConfigError(str(error).replace("Fix data.scene.", "Fix --scenes.")) from None
        except DatasetError:
            pass


def plan_sweep(
    config: Config, out: Path, *, scenes: Sequence[str] | None = None, seeds: Sequence[int] = (0,)
) -> list[SweepRun]:
    """The runs of a sweep: every scene (default: the benchmark's) with every seed."""
    check_model_names(config)  # before any run starts
    scenes = tuple(scenes) if scenes else benchmark_scenes(config)
    if not seeds:
        raise ConfigError("a sweep needs at least one seed")
    for what, values in (("seed", seeds), ("scene", scenes)):
        repeated = sorted({str(value) for value in values if list(values).count(value) > 1})
        if repeated:
            raise ConfigError(f"a sweep lists each {what} once; listed more than once: {', '.join(repeated)}")
    _check_scene_names(config, scenes)
    runs = []
    for scene in scenes:
        for seed in seeds:
            values = {
                "data": {"scene": scene},
                "train": {"seed": seed, "run_dir": str(out / Path(scene).name / f"seed_{seed}")},
            }
            runs.append(
                SweepRun(scene, seed, config_from_dict(values, f"sweep run {scene}, seed {seed}", config))
            )
    return runs


def finished_metrics(run: SweepRun) -> dict[str, Any] | None:
    """The run's final metrics if it has finished with these settings, else `None`.

    A `metrics.json` written by other settings is a `ConfigError` naming them (as resuming
    would be).
    """
    path = run.run_dir / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = json.loads(path.read_text())
    except json.JSONDecodeError:
        return None  # cut short: the run's final evaluation is made again
    if "test" not in metrics or metrics.get("step", 0) < run.config.train.max_steps:
        return None
    check_resumable(run.run_dir, metrics["config"], run.config, SWEEP_REMEDY)
    return metrics


def _kept(metrics: dict[str, Any]) -> dict[str, Any]:
    """What the table keeps of a run's `metrics.json`: its step, scene, test scores and
    validation scores (`None` for a scene without validation views or an older run)."""
    return {
        "step": metrics["step"],
        "scene": metrics["scene"],
        "test": metrics["test"],
        "val": metrics.get("val"),
    }


def _check_unfinished(config: Config) -> None:
    """Refuses, with the sweep's remedy, to resume a run whose checkpoint has other settings
    (`fit` would say the same, naming `train.run_dir`, which a sweep user does not choose)."""
    latest = latest_checkpoint(config.train.run_dir)
    if latest is None:
        return
    try:
        stored = read_checkpoint_meta(latest)["config"]
    except CheckpointError:
        return  # `fit` falls back to an older checkpoint, and checks that one
    check_resumable(latest, stored, continued_config(config, stored), SWEEP_REMEDY)


def run_one(config: Config, progress: bool = False) -> dict[str, Any]:
    """Trains (or resumes) and evaluates one run; returns its final metrics. What a job runs."""
    from .loop import fit

    metrics = finished_metrics(SweepRun(config.data.scene, config.train.seed, config))
    if metrics is None:
        _check_unfinished(config)
        metrics = fit(config, progress=progress).metrics
    return _kept(metrics)


def published_numbers(reproduces: str) -> dict[str, float]:
    """The published PSNR, SSIM and LPIPS named in a config's `reproduces` line (those present)."""
    return {name.lower(): float(value) for name, value in _PUBLISHED.findall(reproduces)}


def _mean_and_spread(values: Sequence[float]) -> dict[str, Any]:
    array = np.asarray(values, np.float64)
    spread = float(np.std(array, ddof=1)) if len(array) > 1 else None
    return {"mean": float(np.mean(array)), "std": spread, "n": len(array)}


def aggregate(
    config: Config, runs: Sequence[SweepRun], results: dict[tuple[str, int], dict[str, Any]]
) -> dict[str, Any]:
    """The sweep's table: each scene's mean and spread over seeds, and the mean over scenes
    with its spread over seeds (from the seeds that finished every scene), beside the
    published numbers.

    **Arguments:**

    - `config`: the sweep's config (its `name` and `reproduces` line).
    - `runs`: the planned runs.
    - `results`: the metrics of the finished runs by `(scene, seed)`.
    """
    scenes = list(dict.fromkeys(run.scene for run in runs))
    seeds = list(dict.fromkeys(run.seed for run in runs))

    def value(scene: str, seed: int, metric: str) -> float | None:
        found = results.get((scene, seed))
        return None if found is None else found["test"].get(metric)

    per_scene = {}
    for scene in scenes:
        per_scene[scene] = {}
        for metric in METRICS:
            values = [v for seed in seeds if (v := value(scene, seed, metric)) is not None]
            per_scene[scene][metric] = _mean_and_spread(values) if values else None
        val = [
            found["val"]["psnr"]
            for seed in seeds
            if (found := results.get((scene, seed))) is not None and found.get("val")
        ]
        per_scene[scene]["val_psnr"] = _mean_and_spread(val) if val else None
    complete_seeds = [seed for seed in seeds if all((scene, seed) in results for scene in scenes)]
    mean = {}
    for metric in METRICS:
        per_seed = [[value(scene, seed, metric) for scene in scenes] for seed in complete_seeds]
        per_seed_means = [float(np.mean(row)) for row in per_seed if row and None not in row]
        mean[metric] = (
            {**_mean_and_spread(per_seed_means), "per_seed": per_seed_means} if per_seed_means else None
        )
    return {
        "config": config.name,
        "reproduces": config.reproduces,
        "chosen_on": config.chosen_on,
        "scenes": scenes,
        "seeds": seeds,
        "benchmark_scenes": list(_known_scenes(config.data.dataset)),
        "complete_seeds": complete_seeds,
        "missing": [f"{run.scene} seed {run.seed}" for run in runs if (run.scene, run.seed) not in results],
        "per_scene": per_scene,
        "mean": mean,
        "published": published_numbers(config.reproduces),
        "runs": [
            {
                "scene": run.scene,
                "seed": run.seed,
                "run_dir": str(run.run_dir),
                **results[(run.scene, run.seed)],
            }
            for run in runs
            if (run.scene, run.seed) in results
        ],
    }


def _cell(entry: dict[str, Any] | None, digits: int) -> str:
    if entry is None:
        return "n/a"
    text = f"{entry['mean']:.{digits}f}"
    if entry["std"] is not None and not math.isnan(entry["std"]):
        text += f" ± {entry['std']:.{digits}f}"
    return text


def format_markdown(table: dict[str, Any]) -> str:
    """The table as markdown: one row per scene (mean ± std over seeds), the mean over scenes
    (± std over seeds) and the published numbers."""
    digits = {"psnr": 2, "ssim": 3, "lpips": 3, "depth_mae": 3}
    names = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "depth_mae": "depth MAE"}
    header = "| scene | " + " | ".join(f"test {names[m]}" for m in METRICS) + " | validation PSNR |"
    lines = [
        f"# {table['config']}",
        "",
        f"Reproduces: {table['reproduces'] or 'none'}",
        "",
        f"Settings chosen on: {table.get('chosen_on') or 'not stated in the config'}",
        "",
        f"Seeds {', '.join(map(str, table['seeds']))}; each cell is the mean ± the standard deviation over "
        "seeds (the mean over scenes: of the per-seed means). Compare settings on the validation "
        "column; the test columns are the record.",
        "",
        header,
        "|" + "---|" * (len(METRICS) + 2),
    ]
    for scene, row in table["per_scene"].items():
        cells = [_cell(row[m], digits[m]) for m in METRICS] + [_cell(row.get("val_psnr"), 2)]
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    lines.append(
        f"| **mean of {len(table['scenes'])} scene{'s' if len(table['scenes']) > 1 else ''}** | "
        + " | ".join(_cell(table["mean"][m], digits[m]) for m in METRICS)
        + " | |"
    )
    published = table["published"]
    if published:
        lines.append(
            "| published | "
            + " | ".join(f"{published[m]:g}" if m in published else "" for m in METRICS)
            + " | |"
        )
    notes = []
    benchmark = table["benchmark_scenes"]
    if benchmark and sorted(table["scenes"]) != sorted(benchmark):
        # A scene counts as run when at least one of its seeds finished.
        ran = [
            scene
            for scene in table["scenes"]
            if scene in benchmark
            and sum(missing.startswith(f"{scene} seed ") for missing in table["missing"])
            < len(table["seeds"])
        ]
        notes.append(
            f"Only {len(ran)} of the benchmark's {len(benchmark)} scenes were run: the mean "
            "is not comparable with the published number."
        )
    if table["missing"]:
        notes.append(f"Not finished: {', '.join(table['missing'])}.")
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def write_table(table: dict[str, Any], out: Path) -> tuple[Path, Path]:
    """Writes `table.md` and `table.json` into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    markdown, data = out / "table.md", out / "table.json"
    markdown.write_text(format_markdown(table))
    data.write_text(strict_json.dumps(table, indent=2))
    return markdown, data


def run_local(
    runs: Sequence[SweepRun], *, progress: bool, on_run: Callable[[int, SweepRun, str], None]
) -> tuple[dict[tuple[str, int], dict[str, Any]], dict[tuple[str, int], str]]:
    """Runs the sweep here, one run after another. A run that cannot start (its scene's
    files are missing, its folder holds another run) is recorded and the others go on."""
    from ..data import DatasetError

    results, failures = {}, {}
    for index, run in enumerate(runs):
        done = finished_metrics(run)
        on_run(index, run, "finished" if done is not None else "running")
        try:
            results[(run.scene, run.seed)] = run_one(run.config, progress) if done is None else _kept(done)
        except (ConfigError, DatasetError, FileNotFoundError) as error:
            failures[(run.scene, run.seed)] = str(error)
            on_run(index, run, f"failed: {error}")
    return results, failures


def run_submitit(
    runs: Sequence[SweepRun],
    folder: Path,
    *,
    cluster: str | None,
    parameters: dict[str, Any],
    on_run: Callable[[int, SweepRun, str], None],
) -> tuple[dict[tuple[str, int], dict[str, Any]], dict[tuple[str, int], str]]:
    """Runs the unfinished runs as submitit jobs (Slurm, or local processes with
    `cluster="local"`) and waits for them; finished runs are read, not submitted."""
    import submitit

    executor = submitit.AutoExecutor(folder=folder, cluster=cluster)
    executor.update_parameters(**parameters)
    results, failures, jobs = {}, {}, []
    for index, run in enumerate(runs):
        done = finished_metrics(run)
        if done is not None:
            on_run(index, run, "finished")
            results[(run.scene, run.seed)] = _kept(done)
            continue
        executor.update_parameters(name=f"{run.config.name}-{run.scene}-{run.seed}")
        job = executor.submit(run_one, run.config)
        on_run(index, run, f"submitted as job {job.job_id}")
        jobs.append((index, run, job))
    for index, run, job in jobs:
        try:
            results[(run.scene, run.seed)] = job.result()
            on_run(index, run, "done")
        except Exception as error:  # a job's failure, with the remote traceback in its logs
            message = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
            failures[(run.scene, run.seed)] = f"{message} (logs: {job.paths.stderr})"
            on_run(index, run, f"failed: {failures[(run.scene, run.seed)]}")
    return results, failures
