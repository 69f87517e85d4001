"""The sweep: its plan, its table's arithmetic, resuming, and runs on submitit's local executor."""

import json

import numpy as np
import pytest
from helpers import TINY_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx._runs.sweep import aggregate, format_markdown, plan_sweep, published_numbers
from mixnerf_eqx.cli import sweep
from mixnerf_eqx.data import llff

# A sweep of the tiny model that trains in seconds; its runs stop at 8 steps.
SWEEP_OVERRIDES = [o for o in TINY_OVERRIDES if not o.startswith("train.max_steps")] + [
    "train.max_steps=8",
    "data.num_test_views=2",
]


def test_the_plan_covers_the_benchmark_with_every_seed(tmp_path):
    config = mx.load_config("llff3")
    runs = plan_sweep(config, tmp_path, seeds=[0, 3])
    assert [(run.scene, run.seed) for run in runs] == [
        (scene, seed) for scene in llff.SCENES for seed in (0, 3)
    ]
    assert len({run.run_dir for run in runs}) == len(runs)
    assert all(run.config.data.scene == run.scene and run.config.train.seed == run.seed for run in runs)
    assert runs[-1].run_dir == tmp_path / "trex" / "seed_3"
    with pytest.raises(mx.ConfigError, match="listed more than once: fern"):
        plan_sweep(config, tmp_path, scenes=["fern", "fern"])


def test_published_numbers_are_read_from_the_reproduces_line():
    config = mx.load_config("llff3")
    assert published_numbers(config.reproduces) == {"psnr": 19.27, "ssim": 0.629, "lpips": 0.236}
    assert published_numbers("none (quick start)") == {}


def test_the_table_is_the_mean_over_scenes_and_its_spread_over_seeds(tmp_path):
    config = mx.load_config("llff3")
    runs = plan_sweep(config, tmp_path, scenes=["fern", "horns"], seeds=[0, 1, 2])
    psnr = {("fern", 0): 20.0, ("fern", 1): 21.0, ("fern", 2): 22.5, ("horns", 0): 18.0, ("horns", 1): 17.0}
    results = {
        key: {"step": 1, "scene": key[0], "test": {"psnr": value, "ssim": 0.5}, "val": {"psnr": value - 1}}
        for key, value in psnr.items()
    }
    results[("horns", 1)]["val"] = None  # a run without validation views
    table = aggregate(config, runs, results)
    # Per scene: mean and sample standard deviation over the seeds that finished it.
    assert table["per_scene"]["fern"]["psnr"]["mean"] == pytest.approx(21.166666666)
    assert table["per_scene"]["fern"]["psnr"]["std"] == pytest.approx(np.std([20.0, 21.0, 22.5], ddof=1))
    assert table["per_scene"]["horns"]["psnr"]["n"] == 2
    # Over scenes: the per-seed means of the seeds that finished every scene (0 and 1).
    assert table["complete_seeds"] == [0, 1]
    assert table["mean"]["psnr"]["per_seed"] == [19.0, 19.0]
    assert table["mean"]["psnr"]["std"] == 0.0
    assert table["mean"]["lpips"] is None
    assert table["missing"] == ["horns seed 2"]
    # The validation column: the seeds that have validation scores.
    assert table["per_scene"]["fern"]["val_psnr"]["mean"] == pytest.approx(20.166666666)
    assert table["per_scene"]["horns"]["val_psnr"]["n"] == 1
    markdown = format_markdown(table)
    assert "| fern | 21.17 ± 1.26 | 0.500 ± 0.000 | n/a | n/a | 20.17 ± 1.26 |" in markdown
    assert "| **mean of 2 scenes** | 19.00 ± 0.00 |" in markdown
    assert "| published | 19.27 | 0.629 | 0.236 |  | |" in markdown
    assert "Settings chosen on: the paper's published settings" in markdown
    assert "Only 2 of the benchmark's 8 scenes" in markdown and "Not finished: horns seed 2." in markdown


def _import_submitit(monkeypatch):
    # Importing submitit configures logging with `logging.config.dictConfig`, which closes the
    # handlers pytest captures logs with; NOCONFIG leaves logging as it is.
    monkeypatch.setenv("SUBMITIT_LOG_LEVEL", "NOCONFIG")
    return pytest.importorskip("submitit")


def _sweep_arguments(out, *extra):
    return [
        "--config",
        "builtin",
        "--seeds",
        "0,1",
        "--out",
        str(out),
        "--no-progress",
        *extra,
        *SWEEP_OVERRIDES,
    ]


def test_a_sweep_resumes_what_is_unfinished_and_reads_what_is_finished(tmp_path, capsys):
    out = tmp_path / "sweep"
    config = mx.load_config("builtin", SWEEP_OVERRIDES)
    seed_1 = plan_sweep(config, out, seeds=[0, 1])[1]
    # Seed 1 was stopped after 3 steps (a checkpoint, no metrics): the sweep continues it.
    mx.fit(seed_1.config, progress=False, stop_after=3)
    assert sweep.main(_sweep_arguments(out)) == 0
    log = [json.loads(line) for line in (seed_1.run_dir / "train_log.jsonl").read_text().splitlines()]
    assert [entry["step"] for entry in log if "loss" in entry] == [3, 8]
    table = json.loads((out / "table.json").read_text())
    assert [(run["scene"], run["seed"], run["step"]) for run in table["runs"]] == [
        ("builtin", 0, 8),
        ("builtin", 1, 8),
    ]
    metrics = [
        json.loads((out / "builtin" / f"seed_{s}" / "metrics.json").read_text())["test"] for s in (0, 1)
    ]
    assert table["mean"]["psnr"]["per_seed"] == [metrics[0]["psnr"], metrics[1]["psnr"]]
    assert table["mean"]["psnr"]["std"] == pytest.approx(np.std([m["psnr"] for m in metrics], ddof=1))
    assert (out / "table.md").read_text().startswith("# builtin")
    # Again: both runs are finished and only read (their checkpoints are not touched).
    stamps = {path: path.stat().st_mtime_ns for path in out.rglob("checkpoints/*/state.eqx")}
    capsys.readouterr()
    assert sweep.main(_sweep_arguments(out)) == 0
    printed = capsys.readouterr().out
    assert "[1/2] builtin, seed 0: finished" in printed and "[2/2] builtin, seed 1: finished" in printed
    assert stamps == {path: path.stat().st_mtime_ns for path in out.rglob("checkpoints/*/state.eqx")}
    # A sweep folder of other settings is refused as a whole, naming the run and the setting.
    assert sweep.main(_sweep_arguments(out, "loss.lambda_depth=0.5")) == 2
    error = capsys.readouterr().err
    assert "seed_0 was written with different settings (loss.lambda_depth: 0.001 -> 0.5)" in error


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--seeds", "a,b"], "--seeds must be comma-separated integers"),
        (["--seeds", "-1"], "--seeds must list integers in [0, 4294967295]"),
        # Seeds alias modulo 2^32: 4294967296 would train as seed 0.
        (["--seeds", "0,4294967296"], "--seeds must list integers in [0, 4294967295] (wider seeds alias)"),
        (["--seeds", "99999999999999999999"], "--seeds must list integers in [0, 4294967295]"),
        (["--config", "configs/nothing.toml"], "does not exist"),
        (["--config", "nothing"], "no packaged config named nothing"),
        (["--engine", "submitit", "--timeout-min", "0"], "--timeout-min must be positive"),
    ],
)
def test_the_sweep_refuses_meaningless_arguments(tmp_path, arguments, message, capsys, monkeypatch):
    if "submitit" in arguments:
        _import_submitit(monkeypatch)
    assert sweep.main(["--out", str(tmp_path), *arguments]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("error: ") and message in error and "\n" not in error
    if "--seeds" in arguments:
        assert not list(tmp_path.iterdir())  # refused before anything is written


def test_missing_scene_files_fail_that_run_only(tmp_path, capsys):
    arguments = [
        "--config",
        "llff3",
        "--scenes",
        "fern",
        "--data-dir",
        str(tmp_path),
        "--out",
        str(tmp_path / "s"),
    ]
    assert sweep.main(arguments) == 1
    table = json.loads((tmp_path / "s" / "table.json").read_text())
    assert "fern" in table["failed"]["fern seed 0"] and table["missing"] == ["fern seed 0"]
    # The note counts the scenes that finished, not the scenes asked for.
    assert "Only 0 of the benchmark's 8 scenes were run" in (tmp_path / "s" / "table.md").read_text()


def test_an_unknown_scene_is_refused_before_any_run(tmp_path, capsys):
    arguments = ["--config", "llff3", "--scenes", "fern,fernn", "--data-dir", str(tmp_path)]
    assert sweep.main([*arguments, "--out", str(tmp_path / "s")]) == 2
    error = capsys.readouterr().err
    assert "unknown llff scene 'fernn'" in error and "Fix --scenes" in error
    assert not (tmp_path / "s" / "fern").exists()
    # A folder of the dataset's root that is not a benchmark scene is a scene too.
    (tmp_path / "nerf_llff_data" / "garden_gnome").mkdir(parents=True)
    assert sweep.main([*arguments[:3], "garden_gnome", *arguments[4:], "--out", str(tmp_path / "t")]) == 1


def test_a_repeated_seed_or_scene_is_named(tmp_path, capsys):
    arguments = ["--config", "builtin", "--out", str(tmp_path), "--seeds", "0,1,0"]
    assert sweep.main([*arguments, *SWEEP_OVERRIDES]) == 2
    assert "listed more than once: 0" in capsys.readouterr().err


def test_resuming_an_unfinished_run_with_other_settings_names_the_sweep_folder(tmp_path):
    out = tmp_path / "sweep"
    config = mx.load_config("builtin", SWEEP_OVERRIDES)
    mx.fit(plan_sweep(config, out)[0].config, progress=False, stop_after=3)
    assert sweep.main(_sweep_arguments(out, "loss.lambda_depth=0.5")) == 1
    failed = json.loads((out / "table.json").read_text())["failed"]["builtin seed 0"]
    assert "loss.lambda_depth: 0.001 -> 0.5" in failed
    assert "choose another --out" in failed and "train.run_dir" not in failed


def test_a_sweep_on_submitits_local_executor(tmp_path, monkeypatch):
    _import_submitit(monkeypatch)
    out = tmp_path / "jobs_sweep"
    arguments = [
        "--config",
        "builtin",
        "--engine",
        "submitit",
        "--cluster",
        "local",
        "--seeds",
        "0",
        "--out",
        str(out),
        "--timeout-min",
        "10",
    ]
    assert sweep.main([*arguments, *SWEEP_OVERRIDES]) == 0
    table = json.loads((out / "table.json").read_text())
    # The job trained and evaluated the run in its own process, in the run's folder.
    run = table["runs"][0]
    assert run["step"] == 8
    assert json.loads((out / "builtin" / "seed_0" / "metrics.json").read_text())["test"] == run["test"]
    assert list((out / "jobs").glob("*_result.pkl"))
