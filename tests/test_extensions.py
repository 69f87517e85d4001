"""Each extension point takes a new part in the places `docs/architecture.md` ("How to add ...")
lists, and a run trains with it. (A loss term: `tests/test_loss.py`; a field: every field's
contract in `tests/test_field_contract.py`.)"""

import dataclasses
import json
from pathlib import Path

import pytest
from helpers import TINY_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx._config import DataConfig
from mixnerf_eqx.data import FORMATS, DatasetError, DatasetFormat, procedural


def _load_toy(scene_dir: Path, config: DataConfig) -> mx.data.Dataset:
    """A format whose scene folder holds `scene.json` with the resolution of the built-in scene
    to render: what a real loader would read from its files."""
    settings = json.loads((scene_dir / "scene.json").read_text())
    LOADED.append(scene_dir)
    return procedural.make_builtin_scene(
        resolution=settings["resolution"], num_train_views=config.num_train_views, num_test_views=2
    )


LOADED: list[Path] = []


TOY = DatasetFormat(
    name="toy",
    layouts=("toy_scenes",),
    scenes=("mine", "yours"),
    release="the toy release (toy_scenes/)",
    load=_load_toy,
)


def test_a_new_dataset_format_is_one_record_and_one_registry_entry(monkeypatch, tmp_path):
    monkeypatch.setitem(FORMATS, "toy", TOY)  # the one line a new format adds to `FORMATS`
    root = tmp_path / "datasets"
    (root / "toy_scenes" / "mine").mkdir(parents=True)
    (root / "toy_scenes" / "mine" / "scene.json").write_text(json.dumps({"resolution": 32}))
    overrides = [
        *TINY_OVERRIDES,
        'data.dataset="toy"',
        'data.scene="mine"',
        f"data.data_dir={json.dumps(str(root))}",
        "train.max_steps=2",
        f"train.run_dir={json.dumps(str(tmp_path / 'run'))}",
    ]
    config = mx.load_config("builtin", overrides)
    result = mx.fit(config, progress=False, write_renders=False)
    assert int(result.state.step) == 2
    assert LOADED == [root / "toy_scenes" / "mine"]  # found in the format's layout, loaded by it
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]["psnr"] > 0
    # The registry's own errors speak of the new format from its record.
    with pytest.raises(DatasetError, match="unknown toy scene 'theirs'.*mine, yours"):
        mx.data.load_dataset(dataclasses.replace(config.data, scene="theirs"))
    with pytest.raises(DatasetError, match=r"toy scene 'yours' not found.*the toy release \(toy_scenes/\)"):
        mx.data.load_dataset(dataclasses.replace(config.data, scene="yours"))
    # A name that is no format is one error listing them all, the new one included.
    with pytest.raises(DatasetError, match="unknown dataset format 'toys'.*transforms, toy"):
        mx.data.load_dataset(dataclasses.replace(config.data, dataset="toys"))
