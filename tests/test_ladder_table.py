"""`benchmarks/ladder_table.py`: the MLP capacity ladder's table on synthetic rungs whose
figures are worked out by hand, the parameter count of real configs, and the committed table
is the one the committed runs make."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import fidelity  # noqa: E402
import ladder_table  # noqa: E402

RESULTS = Path(ladder_table.__file__).resolve().parent / "results"


def _entry(step: int, val: float, test: float, train: float, depth: float = 0.1) -> dict:
    return {
        "step": step,
        "val": {"psnr": val},
        "test": {"psnr": test, "depth_mae": depth},
        "train_psnr": train,
    }


def _run(method: str, seed: int, curve: list[dict], depth: int, width: int) -> dict:
    return {
        "key": f"builtin/{method}/seed{seed}",
        "scene": "builtin",
        "method": method,
        "seed": seed,
        "epochs": 500.0,
        "base_config": "configs/builtin.toml",
        "overrides": [f"mlp.depth={depth}", f"mlp.width={width}", f"train.seed={seed}"],
        "curve": curve,
        "final": curve[-1] if curve else None,
    }


def _write(path: Path, runs: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in runs))


def test_rungs_side_by_side_with_hand_worked_figures(tmp_path):
    # Rung 4x64. Baseline: seed 0 is best at step 1 (test 22, train 25) and ends at test 20
    # with train 28, so it overfits and falls by 2; seed 2 ends at 15, more than 3 dB below
    # the baseline's median 20, so it failed. MixNeRF ends at 21, 22, 20: differences +1, +1,
    # +5, mean 2.33, standard error 1.33, 95% half-width 4.303 x 1.33 = 5.74, so "level".
    base = [
        _run("mipnerf", 0, [_entry(1, 21.0, 22.0, 25.0), _entry(2, 19.0, 20.0, 28.0, 0.3)], 4, 64),
        _run("mipnerf", 1, [_entry(1, 19.0, 20.0, 24.0), _entry(2, 20.0, 21.0, 26.0, 0.3)], 4, 64),
        _run("mipnerf", 2, [_entry(1, 14.0, 15.0, 20.0), _entry(2, 14.0, 15.0, 21.0, 0.5)], 4, 64),
    ]
    mix = [
        _run("mixnerf", s, [_entry(1, e - 2, e - 1, 22.0), _entry(2, e - 1, e, 23.0, 0.2)], 4, 64)
        for s, e in zip((0, 1, 2), (21.0, 22.0, 20.0), strict=True)
    ]
    _write(tmp_path / "fidelity_cpu_ladder_4x64.jsonl", base + mix)
    # Rung 8x128 has only the baseline's seed 0, rung 4x128 only MixNeRF's; by size they come
    # after 4x64, which by name sorts last. A GPU rung and a file of another kind are not read.
    _write(tmp_path / "fidelity_cpu_ladder_8x128.jsonl", [base[0]])
    _write(tmp_path / "fidelity_cpu_ladder_4x128.jsonl", [mix[0]])
    _write(tmp_path / "fidelity_gpu_ladder_2x16.jsonl", [base[1]])
    (tmp_path / "fidelity_cpu_ladder_notes.jsonl").write_text("")

    found = ladder_table.ladder(tmp_path, "cpu", count_parameters=False)
    assert [r["mlp"] for r in found["rungs"]] == ["4x64", "4x128", "8x128"]
    rung = found["rungs"][0]
    baseline = rung["methods"]["mipnerf"]
    assert baseline["overfit_seeds"] == [0]
    assert baseline["failed_seeds"] == [2]
    assert rung["methods"]["mixnerf"]["failed_seeds"] == []
    assert baseline["fall"] == [-2.0, 0.0, 0.0]
    assert baseline["gap"] == [8.0, 5.0, 6.0]
    psnr = rung["verdict_psnr"]
    assert psnr["diffs"] == [1.0, 1.0, 5.0]
    assert abs(psnr["stderr"] - 4 / 3) < 1e-12 and psnr["verdict"] == "level"
    # Depth: MixNeRF 0.2 against 0.3, 0.3, 0.5: -0.1, -0.1, -0.3 (lower is better), mean
    # -0.167, standard error 0.0667, half-width 0.287: "level" (two standard errors said ahead).
    depth = rung["verdict_depth_mae"]
    assert abs(depth["mean"] + 0.5 / 3) < 1e-12 and abs(depth["stderr"] - 0.2 / 3) < 1e-12
    assert depth["verdict"] == "level"

    lines = ladder_table.markdown(found).splitlines()
    baseline_row = next(line for line in lines if line.startswith("| 4x64 | n/a | 500 | baseline"))
    # Ends 20, 21, 15 (mean 18.67, sd 3.21); best points by validation 22, 21 (step 2 of seed
    # 1), 15 (the first of seed 2's tie) (mean 19.33, sd 3.79); falls -2, 0, 0 (mean -0.67, sd
    # 1.15); training 28, 26, 21 (mean 25, sd 3.61); gaps 8, 5, 6 (mean 6.33, sd 1.53).
    assert (
        "| 3 | 18.67 ± 3.21 | 19.33 ± 3.79 (val) | -0.67 ± 1.15 | 25.00 ± 3.61 | 6.33 ± 1.53 |"
        in baseline_row
    )
    assert baseline_row.endswith("| 1 of 3 | 1 of 3 |")
    assert "| 8x128 | | | MixNeRF | 0 | not made |" in "\n".join(lines)
    assert "| 4x128 | | | baseline | 0 | not made |" in "\n".join(lines)
    assert "| 4x64 | 3 | +2.33 ± 5.74: level | -0.1667 ± 0.2868: level |" in lines
    assert "| 8x128 | 0 | n/a | n/a |" in lines

    # A run whose record says it trained another MLP than its file's is refused.
    _write(tmp_path / "fidelity_cpu_ladder_8x128.jsonl", [{**base[0], "model": {"mlp": "4x64"}}])
    with pytest.raises(SystemExit, match="not the rung's 8x128 MLP"):
        ladder_table.ladder(tmp_path, "cpu", count_parameters=False)


def _protocol_run(method: str, seed: int, depth: int, width: int, curve: list[dict]) -> dict:
    """A record as `fidelity.py --set mlp.*` writes it: the protocol's overrides, then the MLP's."""
    run = _run(method, seed, curve, depth, width)
    run["overrides"] = [
        *fidelity.protocol_overrides("builtin", method, seed, None),
        f"mlp.depth={depth}",
        f"mlp.width={width}",
        f"mlp.skip_layer={depth // 2}",
        f"mlp.view_width={width // 2}",
    ]
    run["model"] = {"mlp": f"{depth}x{width}"}
    return run


def _mlp_parameters(depth: int, width: int, skip: int, view: int) -> int:
    """The baseline's field counted by hand: one shared MLP whose trunk takes the 60 integrated
    position features, and takes them again after every trunk layer i > 0 with i % skip == 0
    (mip-NeRF's rule: the layer after it, or the heads after the last one, read width + 60); a
    density output and a bottleneck on the trunk's features, a view layer on the bottleneck
    and the 27 direction features, and an RGB output."""
    total, features = 0, 60
    for i in range(depth):
        total += features * width + width
        features = width + (60 if i > 0 and i % skip == 0 else 0)
    density, bottleneck = features + 1, features * width + width
    view_layer, rgb = (width + 27) * view + view, view * 3 + 3
    return total + density + bottleneck + view_layer + rgb


def test_parameter_count_against_a_count_by_hand():
    for depth, width in ((4, 64), (4, 128), (8, 64)):
        expected = _mlp_parameters(depth, width, depth // 2, width // 2)
        assert ladder_table.parameter_count(_protocol_run("mipnerf", 0, depth, width, [])) == expected
        # MixNeRF adds two heads on the view layer, 3 outputs each (the colour's and the
        # depth's mixture scales and weights are read from there).
        mix = ladder_table.parameter_count(_protocol_run("mixnerf", 0, depth, width, []))
        assert mix == expected + 2 * (3 * (width // 2) + 3)
    assert _mlp_parameters(4, 64, 2, 32) == 27_492  # the protocol's MLP


def test_main_writes_the_table_the_summary_and_the_plot(tmp_path):
    curve = [_entry(1, 10.0, 11.0, 12.0), _entry(2, 11.0, 12.0, 13.0)]
    runs = [_protocol_run(m, s, 2, 16, curve) for m in ("mixnerf", "mipnerf") for s in (0, 1)]
    _write(tmp_path / "fidelity_cpu_ladder_2x16.jsonl", runs)
    assert ladder_table.main(["--results", str(tmp_path)]) == 0
    table = (tmp_path / "ladder_cpu.md").read_text()
    expected = _mlp_parameters(2, 16, 1, 8)
    assert f"| 2x16 | {expected:,} | 500 | baseline | 2 | 12.00 ± 0.00 |" in table
    summary = json.loads((tmp_path / "ladder_cpu_summary.json").read_text())
    assert summary["rungs"][0]["parameters"]["mipnerf"] == expected
    assert (tmp_path / "ladder_cpu.png").is_file() or "matplotlib" not in sys.modules
    assert ladder_table.main(["--results", str(tmp_path), "--backend", "gpu"]) == 1  # no GPU rungs


def test_without_matplotlib_the_table_is_written_and_the_plot_skipped(tmp_path, capsys, monkeypatch):
    curve = [_entry(1, 10.0, 11.0, 12.0), _entry(2, 11.0, 12.0, 13.0)]
    runs = [_protocol_run(m, s, 2, 16, curve) for m in ("mixnerf", "mipnerf") for s in (0, 1)]
    _write(tmp_path / "fidelity_cpu_ladder_2x16.jsonl", runs)
    for name in ("matplotlib", "matplotlib.pyplot"):
        monkeypatch.setitem(sys.modules, name, None)  # `import` now raises ImportError
    assert ladder_table.main(["--results", str(tmp_path)]) == 0
    assert "no plot: matplotlib is not installed" in capsys.readouterr().out
    assert (tmp_path / "ladder_cpu.md").is_file() and not (tmp_path / "ladder_cpu.png").exists()


def _committed_rungs() -> list[Path]:
    """The rung files git tracks (all that are there outside a git checkout): a training that
    is appending runs to a rung file does not change what the committed table must be."""
    files = [path for *_, path in ladder_table.rung_files(RESULTS, "cpu")]
    try:
        listed = subprocess.run(
            ["git", "ls-files", "--", *map(str, files)],
            cwd=RESULTS,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        return files
    tracked = {Path(name).name for name in listed}
    return [path for path in files if path.name in tracked]


def test_committed_ladder_is_what_the_committed_runs_make(tmp_path):
    rungs = _committed_rungs()
    committed = RESULTS / "ladder_cpu.md"
    if not committed.is_file():
        assert not rungs, "rungs without their table"
        return
    for path in rungs:
        shutil.copy(path, tmp_path / path.name)
    found = ladder_table.ladder(tmp_path, "cpu")
    body = committed.read_text().split("\n", 2)[2]  # after the "made by" line and a blank one
    assert body == ladder_table.markdown(found)
