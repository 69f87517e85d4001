"""Each extension point takes a new part in the places `docs/architecture.md` ("How to add ...")
lists, and a run trains with it: a dataset format, a field, a grid encoding and a command here
(a loss term: `tests/test_loss.py`; every field's contract: `tests/test_field_contract.py`)."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx._config import DataConfig
from mixnerf_eqx._util import allocator
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


# The tiny run without the MLP's section (a config whose field is not the MLP may not set it).
_TINY_WITHOUT_MLP = [o for o in TINY_OVERRIDES if not o.startswith("mlp.")]


class ToyField(mx.nn.AbstractField):
    """The smallest field that trains: a raw density and view features linear in the
    Gaussian's mean, ending in the shared heads."""

    trunk: eqx.nn.Linear
    heads: mx.nn.MixtureHeads

    def __init__(self, *, width: int, mixture_heads: bool, key):
        trunk_key, *head_keys = jax.random.split(key, 4)
        self.trunk = eqx.nn.Linear(3, 1 + width, key=trunk_key)
        self.heads = mx.nn.MixtureHeads(
            width + 3, mixture=mixture_heads, density_noise=0.0, rgb_padding=0.001, keys=tuple(head_keys)
        )

    @property
    def has_mixture_heads(self) -> bool:
        return self.heads.has_mixture

    def regulariser(self):
        return jnp.zeros(())

    def at_step(self, step):
        return self

    def density(self, mean, cov):
        return self.heads.density(self.trunk(mean)[0])

    def density_batch(self, means, covs):
        return mx.nn.vmap_density(self, means, covs)

    def __call__(self, mean, cov, viewdir, *, key=None):
        raw = self.trunk(mean)
        return self.heads(raw[0], jnp.concatenate([jnp.tanh(raw[1:]), viewdir]), key)

    def evaluate_batch(self, means, covs, viewdirs, keys=None):
        return mx.nn.vmap_field(self, means, covs, viewdirs, keys)


def _build_toy_field(config, *, mixture_heads, key, scene_box):
    del scene_box
    return ToyField(width=8, mixture_heads=mixture_heads, key=key)


def test_a_new_field_is_its_class_and_one_builder_entry(monkeypatch, tmp_path):
    monkeypatch.setitem(mx.nn.FIELD_BUILDERS, "toy", _build_toy_field)  # the one entry a field adds
    overrides = [
        *_TINY_WITHOUT_MLP,
        'model.field="toy"',
        "train.max_steps=2",
        f"train.run_dir={json.dumps(str(tmp_path))}",
    ]
    config = mx.load_config("builtin", overrides)
    result = mx.fit(config, progress=False, write_renders=False)
    assert int(result.state.step) == 2 and isinstance(result.model.field, ToyField)
    assert result.model.field.has_mixture_heads  # MixNeRF's heads, so its NLLs trained it
    assert np.isfinite(json.loads((tmp_path / "metrics.json").read_text())["test"]["psnr"])
    # The sections of fields it does not use keep their defaults, as for the built-in ones.
    with pytest.raises(mx.ConfigError, match=r"\[mlp\] does not apply to model.field = 'toy'"):
        mx.load_config("builtin", ['model.field="toy"', "mlp.width=32"])
    # A name no builder has is one error listing them, the new one included.
    bad_run = f"train.run_dir={json.dumps(str(tmp_path / 'bad'))}"
    bad = mx.load_config("builtin", [*_TINY_WITHOUT_MLP, 'model.field="toys"', bad_run])
    named = r"model.field = 'toys' is none of grid, mlp, toy \(did you mean 'toy'\?\)"
    with pytest.raises(mx.ConfigError, match=named):
        mx.build_model(bad, key=jax.random.key(0))
    # fit and sweeps refuse it before they load or write anything.
    with pytest.raises(mx.ConfigError, match=named):
        mx.fit(bad, progress=False)
    assert not (tmp_path / "bad").exists()
    with pytest.raises(mx.ConfigError, match=named):
        mx.plan_sweep(bad, tmp_path / "sweep", seeds=(0, 1))


class ToyEncoding(mx.nn.AbstractGridEncoding):
    """A grid encoding without a grid: each level's features are sines of learned projections of
    the point, at the level's resolution."""

    resolutions: tuple[int, ...] = eqx.field(static=True)
    projections: tuple[jax.Array, ...]

    def __init__(self, resolutions, features: int, *, key):
        self.resolutions = tuple(resolutions)
        keys = jax.random.split(key, len(self.resolutions))
        self.projections = tuple(jax.random.normal(k, (features, 3)) for k in keys)

    @property
    def features_per_level(self) -> int:
        return self.projections[0].shape[0]

    @property
    def cell_sizes(self) -> tuple[float, ...]:
        return tuple(2.0 / (res - 1) for res in self.resolutions)

    def __call__(self, point):
        point = jnp.clip(point, -1.0, 1.0)
        levels = zip(self.resolutions, self.projections, strict=True)
        return jnp.stack([jnp.sin(res * (w @ point)) for res, w in levels])

    def encode_batch(self, points):
        return jax.vmap(self)(points)

    def total_variation(self):
        return jnp.zeros(())


def test_a_new_grid_encoding_is_its_class_and_one_builder_entry(monkeypatch, tmp_path):
    # The one entry an encoding adds: its constructor from the [grid] section, the levels'
    # resolutions and a key.
    def build_toy(grid, resolutions, key):
        return ToyEncoding(resolutions, grid.features, key=key)

    monkeypatch.setitem(mx.nn.ENCODING_BUILDERS, "toy", build_toy)
    overrides = [
        *_TINY_WITHOUT_MLP,
        'grid.encoding="toy"',
        "grid.tv_weight=0",  # the built-in grid's TV weight is the tri-plane encoding's key
        "grid.levels=2",
        "grid.min_resolution=4",
        "grid.max_resolution=8",
        "grid.features=4",
        "grid.coarse_to_fine_steps=0",
        "train.max_steps=2",
        f"train.run_dir={json.dumps(str(tmp_path))}",
    ]
    config = mx.load_config("builtin_grid", overrides)
    result = mx.fit(config, progress=False, write_renders=False)
    encoding = result.model.field.encoding
    assert int(result.state.step) == 2 and isinstance(encoding, ToyEncoding)
    assert encoding.resolutions == (4, 8) and encoding.features_per_level == 4
    assert np.isfinite(json.loads((tmp_path / "metrics.json").read_text())["test"]["psnr"])
    # A key that only another encoding reads is an error, as between the built-in ones.
    only_hash = "grid.hash_table_log2 = 12 applies to grid.encoding = 'hash' only"
    with pytest.raises(mx.ConfigError, match=only_hash):
        mx.load_config("builtin_grid", ['grid.encoding="toy"', "grid.hash_table_log2=12"])
    bad = mx.load_config("builtin_grid", [*_TINY_WITHOUT_MLP, 'grid.encoding="toys"', "grid.tv_weight=0"])
    named = r"grid.encoding = 'toys' is none of hash, toy, triplane \(did you mean 'toy'\?\)"
    with pytest.raises(mx.ConfigError, match=named):
        mx.build_model(bad, key=jax.random.key(0))


_TOY_COMMAND = """\
\"\"\"`python -m mixnerf_eqx.toy OUT`: trains the built-in scene two steps into OUT.\"\"\"

import argparse

import mixnerf_eqx as mx
from .._util.compilation_cache import add_compilation_cache_argument
from .._util.typecheck import add_typecheck_argument
from .common import run_command

TINY = {tiny!r}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mixnerf_eqx.toy")
    parser.add_argument("out")
    parser.add_argument("--steps", type=int, default=2)
    add_compilation_cache_argument(parser)
    add_typecheck_argument(parser)
    args = parser.parse_args(argv)

    def body():
        if args.steps < 1:
            raise ValueError(f"--steps must be at least 1, got {{args.steps}}")
        overrides = [*TINY, f"train.max_steps={{args.steps}}", f"train.run_dir={{args.out!r}}"]
        config = mx.load_config("builtin", overrides)
        result = mx.fit(config, progress=False, write_renders=False)
        print("steps", int(result.state.step))

    return run_command(args, body, interrupted="toy stopped")
"""

_TOY_ENTRY = """\
from ._util.entry import command_main

main = command_main("toy", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
"""

# Puts the toy's two modules where the package looks for them, names it in `COMMANDS`, and
# runs it as `python -m mixnerf_eqx.toy` runs an entry module.
_RUN_TOY = """\
import runpy, sys
import mixnerf_eqx, mixnerf_eqx.cli
from mixnerf_eqx._util import allocator
mixnerf_eqx.__path__.append(sys.argv[1])
mixnerf_eqx.cli.__path__.append(sys.argv[1] + "/cli")
allocator.COMMANDS = (*allocator.COMMANDS, "toy")
assert allocator._started_as_command(["python", "-m", "mixnerf_eqx.toy"])
sys.argv = ["toy", *sys.argv[2:]]
runpy.run_module("mixnerf_eqx.toy", run_name="__main__", alter_sys=True)
"""


def test_a_new_command_is_its_module_its_entry_and_its_name(tmp_path):
    extra = tmp_path / "extra"
    (extra / "cli").mkdir(parents=True)
    (extra / "cli" / "toy.py").write_text(_TOY_COMMAND.format(tiny=[*TINY_OVERRIDES]))
    (extra / "toy.py").write_text(_TOY_ENTRY)
    assert not allocator._started_as_command(["python", "-m", "mixnerf_eqx.toy"])  # not named yet

    def toy(*argv):
        return subprocess.run(
            [sys.executable, "-c", _RUN_TOY, str(extra), *argv],
            capture_output=True,
            text=True,
            timeout=600,
            env={**os.environ, "JAX_PLATFORMS": "cpu"},
        )

    done = toy(str(tmp_path / "run"))
    assert done.returncode == 0, done.stderr
    assert "steps 2" in done.stdout
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]["psnr"] > 0
    # The shared runner makes bad input one line and status 2.
    refused = toy(str(tmp_path / "other"), "--steps", "0")
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == ["error: --steps must be at least 1, got 0"]


def test_a_misspelt_field_or_encoding_is_one_line_before_anything_is_written(tmp_path, capsys):
    """The config cannot list the model's names; the train command checks them right after
    loading it, with the closest name, and creates nothing."""
    from mixnerf_eqx.cli.train import main as train_main

    run_dir = tmp_path / "run"
    for config, overrides, said in (
        (
            "builtin_grid",
            ['model.field="gird"'],
            "model.field = 'gird' is none of grid, mlp (did you mean 'grid'?)",
        ),
        (
            "builtin",
            ['model.field="grid"', 'grid.encoding="tripane"'],
            "grid.encoding = 'tripane' is none of hash, triplane (did you mean 'triplane'?)",
        ),
        # A key of the encoding it was meant to be is refused first, when the config loads,
        # with the same hint.
        (
            "builtin_grid",
            ['grid.encoding="tripane"'],
            "override 'grid.encoding=\"tripane\"': grid.tv_weight = 0.5 applies to grid.encoding = "
            "'triplane' only, and this config uses 'tripane' (did you mean 'triplane'?): remove it (or set "
            "it to 0.0)",
        ),
    ):
        code = train_main(["--config", config, "--run-dir", str(run_dir), "--no-progress", *overrides])
        assert code == 2
        assert capsys.readouterr().err.strip().splitlines() == [f"error: {said}"]
        assert not run_dir.exists()
