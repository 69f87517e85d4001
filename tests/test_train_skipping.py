"""Training that skips: the budgeted render against the dense one, the samples it keeps and
drops, the coarse transmittance it stops on, its buckets, and a training step that equals the
dense step when nothing can be skipped."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY_SHARED_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx import ConfigError
from mixnerf_eqx._nn.budget import AbstractOccupancy, SampleBudget, budget_capacity, evaluate_live, transmittance_before
from mixnerf_eqx._nn.field import FieldOutputs
from mixnerf_eqx._runs.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from mixnerf_eqx._runs.loop import _Steps
from mixnerf_eqx._train.state import budget_bucket, make_train_step, training_cells
from mixnerf_eqx.data import load_dataset


class HalfSpace(AbstractOccupancy):
    """Occupied where x <= 0."""

    def occupied(self, points):
        return points[..., 0] <= 0.0


@pytest.fixture(scope="module")
def grid_setup():
    config = mx.load_config("builtin_grid", [*TINY_SHARED_OVERRIDES, "occupancy.enabled=true", "occupancy.resolution=16"])
    dataset = load_dataset(config.data)
    state = mx.training.init_train_state(config, dataset)
    data = mx.training.training_rays(dataset, config.loss)
    batch = mx.training.draw_batch(data, state, 48)
    return config, dataset, state, batch


def _leaves_equal(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_budget_of_every_sample_renders_as_the_dense_render(grid_setup):
    _, _, state, batch = grid_setup
    key = jax.random.key(7)
    dense = state.model(batch.rays, key=key)
    within, report = state.model.render_within(batch.rays, SampleBudget(), key=key)
    _leaves_equal(dense, within)
    assert report.evaluations == report.dense == 48 * state.model.samples_per_ray
    assert int(report.dropped) == 0
    # Deterministic renders too.
    _leaves_equal(state.model(batch.rays), state.model.render_within(batch.rays, SampleBudget())[0])


def test_empty_samples_are_not_evaluated_and_the_rest_are_the_dense_values(grid_setup):
    _, _, state, batch = grid_setup
    within, report = state.model.render_within(batch.rays, SampleBudget(occupancy=HalfSpace()))
    dense_field = state.model.query_field(state.model.sample_coarse(batch.rays), batch.rays)
    coarse = within.coarse.field
    means = state.model.sample_coarse(batch.rays).means
    live = np.asarray(means[..., 0] <= 0.0)
    assert 0 < live.sum() < live.size
    np.testing.assert_array_equal(np.asarray(coarse.density)[~live], 0.0)
    np.testing.assert_array_equal(np.asarray(coarse.beta)[~live], 1.0)
    np.testing.assert_allclose(np.asarray(coarse.density)[live], np.asarray(dense_field.density)[live], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(coarse.rgb)[live], np.asarray(dense_field.rgb)[live], rtol=1e-6)
    # Unevaluated samples have zero weight: the mixture is over the samples kept.
    np.testing.assert_array_equal(np.asarray(within.coarse.weights)[~live], 0.0)
    assert int(report.coarse_live) == live.sum() and int(report.dropped) == 0


def test_chunks_past_the_live_samples_are_not_evaluated():
    # The chunked buffer the skipping render uses: only chunks holding a live sample run.
    calls = []

    def query(means, covs, viewdirs, keys):
        del covs, viewdirs, keys
        jax.debug.callback(lambda n: calls.append(int(n)), means.shape[0])
        return FieldOutputs(density=jnp.sum(means**2, axis=-1), rgb=means, beta=None, ray_depth=None)

    means = jax.random.normal(jax.random.key(0), (10, 8, 3))
    live = jnp.zeros((10, 8), bool).at[:, 5:].set(True).at[3, 0].set(True)  # 31 of 80

    def density_sum(means):
        outputs, dropped, made = evaluate_live(
            query, means, jnp.ones_like(means), jnp.ones((10, 3)), None, live, 80, with_mixture_heads=False, chunk=16
        )
        return jnp.sum(outputs.density), (outputs, dropped, made)

    (total, (outputs, dropped, made)), grad = jax.jit(jax.value_and_grad(density_sum, has_aux=True))(means)
    jax.effects_barrier()
    # 31 live samples: 2 chunks of 16 evaluated, the other 3 of the 5 skipped.
    assert calls == [16, 16] and int(made) == 32 and int(dropped) == 0
    expected = np.where(np.asarray(live), np.sum(np.asarray(means, np.float64) ** 2, axis=-1), 0.0)
    np.testing.assert_allclose(np.asarray(outputs.density), expected, rtol=1e-6)
    np.testing.assert_allclose(float(total), expected.sum(), rtol=1e-6)
    # The values (and their gradient) are those of the live samples only.
    np.testing.assert_allclose(np.asarray(grad), 2 * np.asarray(means) * np.asarray(live)[..., None], rtol=1e-6)
    # A chunk longer than the buffer is cut to it; a buffer of every sample evaluates them all.
    calls.clear()
    everything = jnp.ones((10, 8), bool)
    _, _, made = jax.jit(
        lambda m: evaluate_live(query, m, m, jnp.ones((10, 3)), None, everything, 80, with_mixture_heads=False, chunk=500)
    )(means)
    jax.effects_barrier()
    assert calls == [80] and int(made) == 80
    # A chunked buffer holds every sample: a smaller capacity would drop samples unreported.
    with pytest.raises(ValueError, match="chunked buffer holds every sample"):
        evaluate_live(query, means, means, jnp.ones((10, 3)), None, everything, 40, with_mixture_heads=False, chunk=16)


def test_a_buffer_too_small_drops_the_farthest_samples_of_every_ray(grid_setup):
    _, _, state, batch = grid_setup
    num_coarse = state.model.coarse_sampler.num_samples
    budget = SampleBudget(coarse_fraction=0.5, fine_fraction=1.0)
    within, report = state.model.render_within(batch.rays, budget)
    density = np.asarray(within.coarse.field.density)
    dense = np.asarray(state.model.query_field(state.model.sample_coarse(batch.rays), batch.rays).density)
    # Half the buffer: every ray keeps its first half of samples (sample-major order).
    assert (density[:, num_coarse // 2 :] == 0).all()
    np.testing.assert_allclose(density[:, : num_coarse // 2], dense[:, : num_coarse // 2], rtol=1e-6)
    assert int(report.dropped) == 48 * num_coarse // 2
    assert report.evaluations == 48 * num_coarse // 2 + 48 * state.model.fine_sampler.num_samples


def test_the_coarse_transmittance_in_front_of_each_point_against_numpy():
    rng = np.random.default_rng(1)
    weights = rng.uniform(0, 0.2, (3, 5))
    edges = np.sort(rng.uniform(2, 6, (3, 6)), axis=1)
    t = rng.uniform(1.5, 6.5, (3, 7))
    found = np.asarray(transmittance_before(jnp.asarray(edges), jnp.asarray(weights), jnp.asarray(t)))
    for ray in range(3):
        for j, point in enumerate(t[ray]):
            # Intervals wholly before the point: those whose right edge is at most... the
            # interval holding the point is the last one whose left edge is <= point.
            holding = np.searchsorted(edges[ray], point, side="right") - 1
            before = weights[ray, : max(holding, 0)].sum() if holding < 5 else weights[ray].sum()
            assert found[ray, j] == pytest.approx(1.0 - before, abs=1e-6)


def test_finished_rays_stop_on_the_fine_level(grid_setup):
    config, _, state, batch = grid_setup
    # A dense fog: rays finish early.
    fog = dataclasses.replace(config, model=dataclasses.replace(config.model, density_bias=6.0))
    opaque = mx.build_model(fog, key=jax.random.key(0))
    plain, _ = opaque.render_within(batch.rays, SampleBudget())
    stopped, report = opaque.render_within(batch.rays, SampleBudget(stop_transmittance=1e-3))
    fine_dense = 48 * opaque.fine_sampler.num_samples
    assert int(report.fine_live) < fine_dense
    # What the stopped samples could add is below the threshold: the colours barely move.
    np.testing.assert_allclose(np.asarray(stopped.fine.rgb), np.asarray(plain.fine.rgb), atol=5e-3)


def test_buckets_and_capacities():
    rung = 2.0**-0.5
    assert budget_bucket(0.3, 0.1) == 0.5  # 0.4: the rung above is 1/2
    assert budget_bucket(0.25, 0.0) == 0.25 and budget_bucket(0.95, 0.1) == 1.0
    assert budget_bucket(0.65, 0.1) == 1.0 and budget_bucket(0.5, 0.1) == rung
    assert budget_bucket(1e-6, 0.0) == 2.0**-7  # the bottom rung
    # Hysteresis: a smaller rung is taken at once; a larger one only when the current rung
    # leaves less than half the headroom.
    assert budget_bucket(0.2, 0.1, current=rung) == 2.0**-1.5  # 0.3: the rung above is 0.35
    assert budget_bucket(0.42, 0.1, current=0.5) == 0.5  # 0.52 wanted; 0.47 <= 0.5 kept
    assert budget_bucket(0.46, 0.1, current=0.5) == rung  # 0.51 > 0.5: grows
    assert budget_bucket(0.8, 0.1, current=0.5) == 1.0  # live beyond the buffer: grows
    assert budget_capacity(0.5, 10, 3) == 15 and budget_capacity(0.01, 10, 3) == 1
    with pytest.raises(ValueError, match="coarse_fraction must lie in"):
        SampleBudget(coarse_fraction=0.0)
    with pytest.raises(ValueError, match="stop_transmittance"):
        SampleBudget(stop_transmittance=1.0)


def test_a_skipping_step_with_nothing_to_skip_equals_the_dense_step(grid_setup):
    config, dataset, state, batch = grid_setup
    # Every cell evaluated and occupied: the budgeted branch runs, and keeps every sample.
    grid = eqx.tree_at(lambda g: g.density, state.grid, jnp.full_like(state.grid.density, 1e3))
    state = eqx.tree_at(lambda s: s.grid, state, grid)
    occupancy = dataclasses.replace(config.occupancy, train_skipping=True, train_stop_transmittance=0.0)
    skipping = dataclasses.replace(config, occupancy=occupancy)
    state = training_cells(state, occupancy)
    assert state.cells is not None
    dense_state, dense_metrics = make_train_step(config)(state, batch)
    skip_step = make_train_step(skipping, max_traces=1)
    skip_state, skip_metrics = skip_step(state, batch)
    # The loss is bit-identical; the updated parameters agree to float32 rounding (XLA compiles
    # the masked step as another program, and the grid's scatter-add gradient may sum in
    # another order: 1 ulp on about 0.1% of the entries).
    assert float(dense_metrics.terms.total) == float(skip_metrics.terms.total)
    for x, y in zip(
        jax.tree_util.tree_leaves(eqx.filter(dense_state.model, eqx.is_array)),
        jax.tree_util.tree_leaves(eqx.filter(skip_state.model, eqx.is_array)),
        strict=True,
    ):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2.5e-7, atol=1e-9)
    assert dense_metrics.terms.samples is None
    evaluations, coarse, fine, dropped, coarse_dense, fine_dense = np.asarray(skip_metrics.terms.samples)
    assert evaluations == coarse + fine == coarse_dense + fine_dense and dropped == 0
    # The same bucket again: no second trace (max_traces=1 would raise).
    skip_step(skip_state, batch)


def test_before_the_grid_has_looked_everywhere_steps_are_dense(grid_setup):
    config, _, state, batch = grid_setup
    occupancy = dataclasses.replace(config.occupancy, train_skipping=True)
    assert not bool(state.grid.fully_evaluated())  # a new grid: every cell unevaluated
    assert training_cells(state, occupancy).cells is None  # so no cells to skip
    step = make_train_step(dataclasses.replace(config, occupancy=occupancy), budget=(0.125, 0.125))
    _, metrics = step(state, batch)
    assert metrics.terms.samples is None  # the dense render
    # One cell still unevaluated is enough to keep the steps dense.
    almost = eqx.tree_at(lambda g: g.density, state.grid, jnp.zeros_like(state.grid.density).at[0, 0, 0].set(jnp.inf))
    assert training_cells(dataclasses.replace(state, grid=almost), occupancy).cells is None
    complete = eqx.tree_at(lambda g: g.density, state.grid, jnp.zeros_like(state.grid.density))
    assert training_cells(dataclasses.replace(state, grid=complete), occupancy).cells is not None


def test_checkpoints_leave_the_cells_out_and_resuming_recomputes_them(grid_setup, tmp_path):
    config, _, state, _ = grid_setup
    occupancy = dataclasses.replace(config.occupancy, train_skipping=True)
    grid = eqx.tree_at(lambda g: g.density, state.grid, jnp.zeros_like(state.grid.density).at[1, 2, 3].set(5.0))
    state = training_cells(dataclasses.replace(state, grid=grid), occupancy)
    save_checkpoint(tmp_path, state, config={})
    like = dataclasses.replace(state, cells=None)
    loaded = load_checkpoint(latest_checkpoint(tmp_path), like)
    assert loaded.cells is None
    again = training_cells(loaded, occupancy)
    np.testing.assert_array_equal(np.asarray(again.cells.mask), np.asarray(state.cells.mask))
    # The mask is the grid's dilated one: the cell and its 26 neighbours.
    assert int(np.asarray(again.cells.mask).sum()) == 27


def test_training_skipping_needs_the_grid():
    with pytest.raises(ConfigError, match="occupancy.train_skipping needs occupancy.enabled"):
        mx.load_config("builtin_grid", ["occupancy.train_skipping=true"])
    with pytest.raises(ConfigError, match="occupancy.train_headroom"):
        mx.load_config("builtin_grid", ["occupancy.enabled=true", "occupancy.train_headroom=2.0"])


def test_a_grid_that_empties_every_sample_falls_back_to_dense_steps(tiny_config, tiny_scene):
    # A box of radius 0.01 around the origin: every sample lies outside it, so the grid calls
    # every sample empty once it has looked at its cells (after the first update).
    occupancy = dataclasses.replace(
        tiny_config.occupancy,
        enabled=True,
        train_skipping=True,
        box_radius=0.01,
        resolution=4,
        update_every=1,
        update_fraction=1.0,
        train_budget_every=1,
    )
    config = dataclasses.replace(
        tiny_config,
        occupancy=occupancy,
        train=dataclasses.replace(tiny_config.train, max_steps=4, eval_every=0),
    )
    with pytest.warns(mx.config.SettingWarning, match="training goes on with dense steps"):
        result = mx.fit(config, dataset=tiny_scene, progress=False, write_renders=False, log_every=1)
    assert "box_radius" in result.metrics["skipping_fallback"]
    log = [json.loads(line) for line in (result.run_dir / "train_log.jsonl").read_text().splitlines()]
    assert any("warning" in entry for entry in log)
    # The grid is complete after the first step's update; the next measurement (a probe of
    # the dense step's batch, since full buffers run the dense step) finds no live sample and
    # warns. No skipping step ever ran (they alone log sample counts).
    warned = next(entry["step"] for entry in log if "warning" in entry)
    assert warned == 2
    assert [entry["step"] for entry in log if "psnr" in entry and entry["step"] > warned]
    assert not [entry for entry in log if "field_evaluations" in entry]


def _steps_for(config, max_steps=1000):
    occupancy = dataclasses.replace(config.occupancy, train_skipping=True)
    train = dataclasses.replace(config.train, max_steps=max_steps)
    return _Steps(dataclasses.replace(config, occupancy=occupancy, train=train), lambda step: step)


def test_a_smaller_buffer_is_compiled_only_when_the_seconds_it_saves_exceed_a_compilation(grid_setup):
    config, _, _, _ = grid_setup
    steps = _steps_for(config, max_steps=1000)
    counts = (100.0, 100.0)  # coarse and fine samples per batch
    steps.compile_seconds, steps.windows = 5.0, [0.04, 0.04, 9.0]  # a window with an evaluation
    # Dense (cost 1) to half buffers (cost 0.2 + 0.8 * 0.5 = 0.6) saves 0.4 of 0.04 s a step:
    # with 900 steps left 14.4 s > 5 s; with 200 left 3.2 s < 5 s.
    assert steps._pays((0.5, 0.5), counts, done=100)
    assert not steps._pays((0.5, 0.5), counts, done=800)
    # Break-even at 5 / (0.04 * 0.4) = 312.5 steps left.
    assert steps._pays((0.5, 0.5), counts, done=1000 - 313)
    assert not steps._pays((0.5, 0.5), counts, done=1000 - 312)
    # The levels weigh by their sample counts.
    saved = 200 * 0.04 * (1 - (0.2 + 0.8 * (0.25 * 300 + 100) / 400))
    assert steps._pays((0.25, 1.0), (300.0, 100.0), done=800) is (saved > 5.0)
    # A program already compiled always pays; none is compiled before a compilation and a
    # step have been timed (a resumed run's first windows).
    steps.steps[(0.5, 0.5)] = object()
    assert steps._pays((0.5, 0.5), counts, done=999)
    assert not _steps_for(config)._pays((0.5, 0.5), counts, done=0)


def test_full_buffers_run_the_dense_step_and_the_count_is_the_skipping_steps_own(grid_setup):
    config, _, state, batch = grid_setup
    assert batch.patches is None  # the step renders exactly the batch's rays
    grid = eqx.tree_at(lambda g: g.density, state.grid, jnp.zeros_like(state.grid.density).at[:8].set(1e3))
    occupancy = dataclasses.replace(config.occupancy, train_skipping=True)
    cells_state = training_cells(dataclasses.replace(state, grid=grid), occupancy)
    assert cells_state.cells is not None
    steps = _steps_for(config)
    new_state, metrics = steps(cells_state, batch)
    # Full buffers: the dense step (no sample counts), compiled without cells; cells kept.
    assert metrics.terms.samples is None and list(steps.steps) == ["dense"]
    assert new_state.cells is cells_state.cells
    assert steps.compile_seconds is not None and steps.compile_seconds > 0
    counts = np.asarray(steps._count(*steps._last))
    # The count is what a skipping step at full buffers counts on the same rays and state
    # (its randomness, annealing and field levels), to the sample.
    skipping = dataclasses.replace(config, occupancy=occupancy)
    _, skip_metrics = make_train_step(skipping, budget=(1.0, 1.0))(cells_state, batch)
    _, coarse, fine, dropped, coarse_dense, fine_dense = np.asarray(skip_metrics.terms.samples)
    assert counts.tolist() == [coarse, fine, 0.0, coarse_dense, fine_dense] and dropped == 0
    assert 0 < coarse < coarse_dense  # some coarse samples lie in the empty cells
