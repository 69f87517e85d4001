"""The training guard: non-finite steps are not applied, counted, and stop a diverging run."""

import dataclasses
import hashlib

import equinox as eqx
import jax
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx import fit
from mixnerf_eqx.training import TrainingDiverged, draw_batch, init_train_state, make_train_step, training_rays


def _poisoned(scene, image_ids):
    images = scene.train.images.copy()
    images[list(image_ids)] = np.nan
    return dataclasses.replace(scene, train=dataclasses.replace(scene.train, images=images))


def _arrays(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))]


def test_non_finite_step_leaves_model_and_optimiser_untouched(tiny_config, tiny_scene):
    poisoned = _poisoned(tiny_scene, range(tiny_scene.train.num_views))
    state = init_train_state(tiny_config, tiny_scene)
    step_fn = make_train_step(tiny_config)
    batch_size = tiny_config.train.batch_size
    new_state, metrics = step_fn(state, draw_batch(training_rays(poisoned), state, batch_size))
    assert bool(metrics.skipped)
    assert not np.isfinite(float(metrics.terms.total))
    kept = (state.model, state.opt_state)
    for before, after in zip(_arrays(kept), _arrays((new_state.model, new_state.opt_state)), strict=True):
        np.testing.assert_array_equal(before, after)
    # The step still counts, so that the next one draws another batch.
    assert int(new_state.step) == 1
    # The same step on clean data is applied.
    clean, clean_metrics = step_fn(state, draw_batch(training_rays(tiny_scene), state, batch_size))
    assert not bool(clean_metrics.skipped)
    changed = zip(_arrays(state.model), _arrays(clean.model), strict=True)
    assert any(not np.array_equal(a, b) for a, b in changed)


@pytest.mark.slow
def test_occasional_nan_batches_are_skipped_and_training_goes_on(tiny_config, tiny_scene):
    config = dataclasses.replace(tiny_config, train=dataclasses.replace(tiny_config.train, max_steps=40))
    result = fit(config, dataset=_poisoned(tiny_scene, [1]), progress=False, write_renders=False, log_every=5)
    skipped = result.metrics["skipped_steps"]
    # One of the four training images is all NaN: about a quarter of the 40 steps draw it.
    assert 3 <= skipped <= 20, skipped
    assert all(np.all(np.isfinite(a)) for a in _arrays(result.model))
    assert np.isfinite(result.metrics["test"]["psnr"])


def _tree_digest(path):
    digest = hashlib.sha256()
    for file in sorted(path.rglob("*")):
        if file.is_file():
            digest.update(file.name.encode() + file.read_bytes())
    return digest.hexdigest()


def test_diverging_run_stops_and_keeps_the_last_good_checkpoint(tiny_config, tiny_scene):
    train = dataclasses.replace(tiny_config.train, max_steps=30, checkpoint_every=4, max_nonfinite_steps=5)
    config = dataclasses.replace(tiny_config, train=train)
    fit(config, dataset=tiny_scene, progress=False, write_renders=False, stop_after=4)
    good = mx.runs.latest_checkpoint(config.train.run_dir)
    digest = _tree_digest(good)
    with pytest.raises(TrainingDiverged, match=r"step 9: 5 consecutive steps.*step_00000004"):
        fit(config, dataset=_poisoned(tiny_scene, range(4)), progress=False, write_renders=False)
    assert mx.runs.latest_checkpoint(config.train.run_dir) == good
    assert _tree_digest(good) == digest


@pytest.mark.slow
@pytest.mark.parametrize(
    "overrides, far",
    [
        (
            ["data.num_train_views=2", "optim.lr_init=5e-2", "optim.lr_final=5e-3", "optim.warmup_steps=0"],
            None,
        ),
        ([], 30.0),
    ],
    ids=["aggressive_lr_2_views", "far_bound_30"],
)
def test_stress_runs_stay_finite(tiny_config, tiny_scene, overrides, far):
    from helpers import TINY_OVERRIDES

    from mixnerf_eqx import load_config, render_views
    from mixnerf_eqx.data import load_dataset

    config = load_config("builtin", [*TINY_OVERRIDES, *overrides, "train.max_steps=60"])
    config = dataclasses.replace(
        config, train=dataclasses.replace(config.train, run_dir=tiny_config.train.run_dir)
    )
    dataset = load_dataset(config.data) if overrides else tiny_scene
    if far is not None:
        dataset = dataclasses.replace(dataset, far=far)
    result = fit(config, dataset=dataset, progress=False, write_renders=False, log_every=1)
    assert result.metrics["skipped_steps"] == 0
    for entry in result.history:
        assert all(np.isfinite(v) for v in entry.values()), entry
    assert all(np.all(np.isfinite(a)) for a in _arrays(result.model))
    rendered = render_views(result.model, dataset.test, dataset.near, dataset.far)
    assert all(np.all(np.isfinite(x)) for x in (rendered.rgb, rendered.depth, rendered.acc))
