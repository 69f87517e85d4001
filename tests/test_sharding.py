"""Data-parallel training (`mixnerf_eqx._train.sharding`) against the single-device step.

JAX fixes its device count when it starts, so the checks with four devices run in a fresh
interpreter with `--xla_force_host_platform_device_count=4` (four CPU devices).
"""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import pytest
from helpers import TINY_OVERRIDES

from mixnerf_eqx import ConfigError
from mixnerf_eqx._train.sharding import data_parallel_mesh

ROOT = Path(__file__).resolve().parent.parent

# Runs with four forced CPU devices; prints one JSON line of results.
_FOUR_DEVICES = textwrap.dedent(
    """
    import dataclasses, json, sys, time
    import equinox as eqx
    import jax
    import numpy as np
    import mixnerf_eqx as mx
    from mixnerf_eqx._train.sharding import DataParallel, data_parallel_mesh
    from mixnerf_eqx.data import load_dataset

    overrides, run_root = json.loads(sys.argv[1]), sys.argv[2]
    # The runs below compile the same two steps again: let them find the programs compiled here.
    jax.config.update("jax_compilation_cache_dir", f"{run_root}/xla-cache")
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    config = mx.load_config("builtin", overrides)
    scene = load_dataset(config.data)
    batch_size = config.train.batch_size

    state = mx.training.init_train_state(config, scene)
    data = mx.training.training_rays(scene)
    step = mx.training.make_train_step(config, max_traces=1)
    draw = eqx.filter_jit(mx.training.draw_batch)
    parallel = DataParallel(data_parallel_mesh("auto", batch_size))
    sharded_step = parallel.step(mx.training.make_train_step(config, max_traces=1))
    sharded_draw = parallel.draw(mx.training.draw_batch)
    sharded_state, sharded_data = parallel.replicate(state), parallel.replicate(data)

    def params(s):
        return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(eqx.filter(s.model, eqx.is_array))]

    # Five steps each way, from the same state.
    single, split = state, sharded_state
    loss_diffs, param_diffs = [], []
    for _ in range(5):
        single, single_metrics = step(single, draw(data, single, batch_size))
        batch = sharded_draw(sharded_data, split, batch_size)
        split, split_metrics = sharded_step(split, batch)
        loss_diffs.append(abs(float(single_metrics.terms.total) - float(split_metrics.terms.total)))
        param_diffs.append(max(float(np.max(np.abs(a - b))) for a, b in zip(params(single), params(split))))
    arrays = jax.tree_util.tree_leaves(eqx.filter(split, eqx.is_array))
    layouts = sorted({str(leaf.sharding.spec) for leaf in arrays})

    def seconds_per_step(take, s, d):
        batch = (draw if take is step else sharded_draw)(d, s, batch_size)
        for _ in range(3):
            s, _ = take(s, batch)
        jax.block_until_ready(s)
        started = time.perf_counter()
        for _ in range(20):
            s, _ = take(s, batch)
        jax.block_until_ready(s)
        return (time.perf_counter() - started) / 20

    timing = {
        "single": seconds_per_step(step, state, data),
        "sharded": seconds_per_step(sharded_step, sharded_state, sharded_data),
    }

    runs = {}
    for mode in ("off", "auto"):
        settings = [f"train.data_parallel={mode}", f'train.run_dir="{run_root}/{mode}"']
        run_config = mx.load_config("builtin", [*overrides, *settings])
        # Stopped before the end, so the held-out check is the periodic evaluation's (no LPIPS).
        result = mx.fit(run_config, dataset=scene, progress=False, log_every=5, stop_after=20)
        log = [json.loads(line) for line in open(f"{run_root}/{mode}/train_log.jsonl")]
        runs[mode] = {
            "test": next(entry["eval"] for entry in log if "eval" in entry),
            "losses": [entry["loss"] for entry in result.history],
        }
    print(json.dumps({
        "devices": len(jax.devices()),
        "batch_layout": str(batch.rgb.sharding.spec),
        "state_layouts": layouts,
        "loss_diffs": loss_diffs,
        "param_diffs": param_diffs,
        "loss": float(single_metrics.terms.total),
        "timing": timing,
        "runs": runs,
    }))
    """
)


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory):
    overrides = [
        *(o for o in TINY_OVERRIDES if not o.startswith("train.max_steps")),
        "train.max_steps=30",
        "train.eval_every=20",
        "train.num_eval_views=2",
    ]
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4", "JAX_PLATFORMS": "cpu"}
    completed = subprocess.run(
        [sys.executable, "-c", _FOUR_DEVICES, json.dumps(overrides), str(tmp_path_factory.mktemp("runs"))],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    result = json.loads(completed.stdout.strip().splitlines()[-1])
    print(json.dumps(result["timing"]), result["loss_diffs"], result["param_diffs"])
    return result


def test_the_sharded_step_equals_the_single_device_step(four_devices):
    assert four_devices["devices"] == 4
    # The batch is split over the data axis; everything the state carries is replicated.
    assert four_devices["batch_layout"] in ("PartitionSpec('data',)", "P('data',)")
    assert four_devices["state_layouts"] in (["PartitionSpec()"], ["P()"])
    # Float32 sums in another order: the loss (about 9) to a few ulps, the parameters after
    # five Adam steps to far below the learning rate (5e-3 at most).
    for loss_diff in four_devices["loss_diffs"]:
        assert loss_diff <= 1e-5 * abs(four_devices["loss"]) + 1e-6
    for param_diff in four_devices["param_diffs"]:
        assert param_diff <= 1e-5


def test_a_short_sharded_run_matches_the_single_device_run(four_devices):
    single, sharded = four_devices["runs"]["off"], four_devices["runs"]["auto"]
    assert len(single["losses"]) == len(sharded["losses"]) == 4
    for a, b in zip(single["losses"], sharded["losses"], strict=True):
        assert b == pytest.approx(a, rel=1e-3)
    assert sharded["test"]["psnr"] == pytest.approx(single["test"]["psnr"], abs=0.01)
    assert sharded["test"]["ssim"] == pytest.approx(single["test"]["ssim"], abs=1e-3)


def test_one_device_trains_as_before():
    assert data_parallel_mesh("auto", 256, jax.devices()[:1]) is None
    assert data_parallel_mesh("off", 256, jax.devices()) is None
    assert data_parallel_mesh("on", 256, jax.devices()[:1]).shape == {"data": 1}


def test_a_batch_that_does_not_split_over_the_devices_is_one_clear_error():
    devices = [jax.devices()[0]] * 3
    message = r"train.batch_size = 256 does not split over 3 devices.*multiple of 3"
    with pytest.raises(ConfigError, match=message):
        data_parallel_mesh("auto", 256, devices)
