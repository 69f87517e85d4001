"""`benchmarks/quality_gap.py`: a trained run's validation views with other sample counts and
at each checkpoint it kept."""

import subprocess
import sys
from pathlib import Path

import equinox as eqx
import numpy as np

import mixnerf_eqx as mx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import quality_gap  # noqa: E402


def test_other_sample_counts_change_only_the_samplers_and_the_probe_scores_validation_views(
    short_run, tiny_scene
):
    run_dir, model = short_run
    trained = (model.coarse_sampler.num_samples, model.fine_sampler.num_samples)
    other = quality_gap.with_samples(model, 3, 5)
    assert (other.coarse_sampler.num_samples, other.fine_sampler.num_samples) == (3, 5)
    assert bool(eqx.tree_equal(other.field, model.field))
    assert other.coarse_sampler.frustum == model.coarse_sampler.frustum

    result = quality_gap.probe(run_dir, [trained, (3, 5)], None, chunk=1024)
    as_trained = result["by_samples"][f"{trained[0]},{trained[1]}"]
    # The validation views (never the test views), scored as `evaluate` scores them.
    reference = mx.evaluate(model, tiny_scene, split="val", chunk=1024)
    assert as_trained["views"] == tiny_scene.split("val").num_views == len(reference.per_view)
    np.testing.assert_allclose(as_trained["psnr"], reference.means["psnr"], rtol=1e-6)
    assert result["by_samples"]["3,5"]["psnr"] != as_trained["psnr"]
    # Every checkpoint the run kept, the last one the run's own model.
    assert list(result["by_step"]) == ["60"]
    np.testing.assert_allclose(result["by_step"]["60"]["psnr"], as_trained["psnr"], rtol=1e-6)
    table = quality_gap.markdown([result])
    assert f"step 60, {trained[0]} + {trained[1]} samples (as trained)" in table
    assert "step 60, 3 + 5 samples |" in table


def test_only_complete_checkpoints_are_read_and_missing_lpips_is_shown_as_such(tmp_path):
    for name, files in (
        ("step_00000010", ("state.eqx", "meta.json")),
        ("step_00000200", ("state.eqx", "meta.json")),
        ("step_00000030", ("state.eqx",)),  # a write cut short: no description
        (".step_00000040.tmp-123", ("state.eqx", "meta.json")),  # a write still staging
        ("step_final", ("state.eqx", "meta.json")),
    ):
        folder = tmp_path / "checkpoints" / name
        folder.mkdir(parents=True)
        for file in files:
            (folder / file).write_text("")
    kept = mx.runs.checkpoints(tmp_path)
    assert [path.name for path in kept] == ["step_00000010", "step_00000200"]  # by step, not by name

    result = {
        "run": "runs/x",
        "step": 200,
        "trained_samples": (8, 8),
        "by_samples": {"16,16": {"psnr": 20.0, "ssim": 0.5, "lpips": None}},
        "by_step": {
            "10": {"psnr": 18.0, "ssim": 0.4, "lpips": None},
            "200": {"psnr": 21.0, "ssim": 0.6, "lpips": None},
        },
    }
    table = quality_gap.markdown([result])
    assert "| runs/x | step 200, 16 + 16 samples | 20.00 | 0.500 | n/a |" in table
    # Without the trained counts among the sample counts, the latest checkpoint keeps its row.
    assert "| runs/x | step 200, 8 + 8 samples | 21.00 | 0.600 | n/a |" in table
    assert "| runs/x | step 10, 8 + 8 samples | 18.00 | 0.400 | n/a |" in table


def test_a_folder_that_is_not_a_run_is_one_line_and_status_1(tmp_path):
    script = Path(__file__).resolve().parent.parent / "benchmarks" / "quality_gap.py"
    finished = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True)
    assert finished.returncode == 1
    assert finished.stderr.strip().startswith(f"error: {tmp_path}: ")
    assert "config.json" in finished.stderr and "Traceback" not in finished.stderr
