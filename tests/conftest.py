import dataclasses
import os

import pytest
from hypothesis import settings

from mixnerf_eqx import load_config
from mixnerf_eqx.data import load_dataset

# CI runs the property tests on a fixed sequence of examples, so that a red run can be
# reproduced exactly; elsewhere every run explores new examples.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

# A model and scene small enough that a training run takes seconds on two CPU cores.
TINY_OVERRIDES = [
    "data.resolution=32",
    "data.num_train_views=4",
    "data.num_test_views=3",
    "model.width=32",
    "model.depth=2",
    "model.skip_layer=1",
    "model.view_width=16",
    "model.max_deg=8",
    "model.num_coarse_samples=16",
    "model.num_fine_samples=16",
    "optim.lr_init=5e-3",
    "optim.lr_final=5e-4",
    "optim.warmup_steps=20",
    "loss.lambda_colour_steps=20",
    "train.batch_size=256",
    "train.anneal_steps=20",
    "train.max_steps=150",
    "train.checkpoint_every=0",
]


@pytest.fixture
def tiny_config(tmp_path):
    config = load_config("configs/builtin.toml", TINY_OVERRIDES)
    return dataclasses.replace(config, train=dataclasses.replace(config.train, run_dir=str(tmp_path / "run")))


@pytest.fixture(scope="session")
def tiny_scene():
    config = load_config("configs/builtin.toml", TINY_OVERRIDES)
    return load_dataset(config.data)
