"""`benchmarks/quality_gap.py`: a trained run's validation views with other sample counts and
at each checkpoint it kept."""

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
