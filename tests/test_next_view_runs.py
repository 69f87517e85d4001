"""`benchmarks/next_view_runs.py`: its candidates are no training, validation or test view,
and its table's paired differences are the runs' own."""

import dataclasses
import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
sys.path.insert(0, str(HERE / "data"))

import next_view_runs  # noqa: E402
from _writers import write_llff  # noqa: E402


def test_candidates_are_the_images_no_split_uses(tmp_path):
    write_llff(tmp_path / "nerf_llff_data" / "fern")
    overrides = [f'data.data_dir="{tmp_path}"', 'data.scene="fern"', "data.max_val_views=4"]
    config = mx.load_config("llff3", overrides)
    dataset = load_dataset(config.data)
    run = types.SimpleNamespace(config=config, dataset=dataset)
    pool = next_view_runs.candidates_of(run)
    # 20 images: test 0, 8, 16; train 1, 10, 19; image 6 lies near a test camera; of the 13
    # left, 4 evenly spaced are the run's validation views and the other 9 the candidates.
    assert dataset.val.ids == (2, 7, 13, 18)
    assert pool.ids == (3, 4, 5, 9, 11, 12, 14, 15, 17)
    taken = set(dataset.train.ids) | set(dataset.test.ids) | set(dataset.val.ids) | {6}
    assert not taken & set(pool.ids)
    # A candidate keeps its own image and pose.
    wide = load_dataset(dataclasses.replace(config.data, max_val_views=0))
    at = wide.val.ids.index(pool.ids[0])
    np.testing.assert_array_equal(pool.images[0], wide.val.images[at])
    np.testing.assert_array_equal(pool.camtoworlds[0], wide.val.camtoworlds[at])
    joined = next_view_runs.joined(dataset.train, pool.select([2, 0]))
    assert joined.ids == (1, 10, 19, 5, 3)
    np.testing.assert_array_equal(joined.images[3], pool.images[2])
    np.testing.assert_array_equal(joined.camtoworlds[4], pool.camtoworlds[0])


def _curve(psnrs):
    return [{"views": [], "psnr": p, "ssim": 0.5, "lpips": 0.3} for p in psnrs]


def test_table_pairs_each_strategy_with_random_and_farthest_run_by_run():
    results = {}
    # Random's results differ run by run: only a pairing by run gives the differences below.
    for number, (shift, level) in enumerate([(0.4, 21.0), (0.6, 19.0), (0.5, 23.0)]):
        results[f"run_{number}"] = {
            "base": {"psnr": 20.0, "ssim": 0.5, "lpips": 0.3},
            "curves": {
                "depth": _curve([level + shift, level]),
                "farthest": _curve([level, level + number]),
                "random": _curve([level, level]),
                "none": _curve([level - 0.1 * number]),
            },
        }
    text = next_view_runs.table(results, [1, 2])
    rows = {tuple(cell.strip() for cell in line.split("|")[1:3]): line for line in text.splitlines()[2:]}
    # depth - random at 1 view: +0.4, +0.6, +0.5: mean 0.5, half-width t(2) * 0.1 / sqrt(3).
    half = 4.302653 * 0.1 / np.sqrt(3)
    assert f"+0.50 ± {half:.2f}: ahead" in rows[("1", "depth")]
    # farthest - random at 2 views: 0, 1, 2 (mean 1.00, half-width 2.48): level.
    assert "+1.00 ± 2.48: level" in rows[("2", "farthest")]
    assert "-1.00 ± 2.48: level" in rows[("2", "depth")]
    # Against the control at one added view: +0.4, +0.7, +0.7 (mean 0.60, half-width 0.43).
    assert rows[("1", "depth")].rstrip().endswith("+0.60 ± 0.43: ahead |")
    # The control has one row, at one added view, and no differences of its own.
    assert ("1", "none") in rows and ("2", "none") not in rows
    assert rows[("1", "none")].rstrip().endswith("|  |  |  |")
    assert rows[("2", "depth")].rstrip().endswith("|  |")
    assert rows[("0", "(the run as trained)")].split("|")[3].strip() == "20.00"


def _merge(tmp_path, monkeypatch, parts, *extra):
    files = []
    for number, part in enumerate(parts):
        files.append(str(tmp_path / f"part_{number}.json"))
        Path(files[-1]).write_text(json.dumps({"budgets": [1, 2], "seconds": 1.0, **part}))
    monkeypatch.setattr(
        sys, "argv", ["next_view_runs.py", "--merge", *files, *extra, "--out", str(tmp_path / "x")]
    )
    next_view_runs.main()


def test_merge_joins_runs_and_refuses_what_cannot_be_joined(tmp_path, monkeypatch):
    run = {
        "base": {"psnr": 20.0, "ssim": 0.5, "lpips": 0.3},
        "curves": {
            name: _curve([21.0, 22.0][: 1 if name == "none" else 2]) for name in next_view_runs.STRATEGIES
        },
    }
    _merge(tmp_path, monkeypatch, [{"steps": 9, "runs": {"a": run}}, {"steps": 9, "runs": {"b": run}}])
    joined = json.loads((tmp_path / "x.json").read_text())
    assert list(joined["runs"]) == ["a", "b"] and joined["steps"] == 9 and joined["budgets"] == [1, 2]
    assert "| 2 | depth | 22.00 |" in (tmp_path / "x.md").read_text()
    with pytest.raises(SystemExit, match="different --steps"):
        _merge(tmp_path, monkeypatch, [{"steps": 9, "runs": {"a": run}}, {"steps": 5, "runs": {"b": run}}])
    with pytest.raises(SystemExit, match="more than one"):
        _merge(tmp_path, monkeypatch, [{"steps": 9, "runs": {"a": run}}, {"steps": 9, "runs": {"a": run}}])
    with pytest.raises(SystemExit, match="one at a time"):
        _merge(tmp_path, monkeypatch, [{"steps": 9, "runs": {"a": run}}], "--budgets", "1", "3")
