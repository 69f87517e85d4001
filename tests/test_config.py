import dataclasses
import importlib
import json
import re
from pathlib import Path

import jax
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx import ConfigError, build_model, load_config

# Files are found relative to the repository (and the package), not the working directory.
REPO = Path(__file__).resolve().parents[1]
CONFIGS = [mx.config.config_path(name) for name in mx.config.config_names()]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))


def test_the_checkouts_configs_folder_is_the_packages():
    # `configs/` at the top of a checkout links to the package data (the wheel test checks
    # that an install carries them).
    assert (REPO / "configs").resolve() == (REPO / "mixnerf_eqx" / "configs").resolve()
    assert len(CONFIGS) >= 30 and all(
        path.parent.resolve() == (REPO / "configs").resolve() for path in CONFIGS
    )
    assert len(NOTEBOOKS) >= 2


def test_a_config_is_named_or_given_as_a_path(tmp_path, monkeypatch):
    by_name = load_config("llff3_grid")
    assert load_config("llff3_grid.toml") == by_name == load_config(REPO / "configs" / "llff3_grid.toml")
    # A file in the working directory comes before a packaged config of the same name.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "llff3_grid.toml").write_text('name = "mine"\nreproduces = "none"\n')
    assert load_config("llff3_grid.toml").name == "mine" and load_config("llff3_grid").name == by_name.name
    with pytest.raises(ConfigError, match=r"no packaged config named llff3_gird .*llff3_grid"):
        load_config("llff3_gird")
    with pytest.raises(ConfigError, match="config file elsewhere/llff3_grid.toml does not exist"):
        load_config("elsewhere/llff3_grid.toml")


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_loads(path):
    config = load_config(path)
    assert config.name
    assert config.reproduces, f"{path} must say which table cell it reproduces (or 'none')"


def test_recommended_configs_take_their_familys_choice_and_paper_configs_stay_the_papers():
    # LLFF's validation views chose training without the lambda_C ramp (5 seeds on fern at
    # 504x378, benchmarks/fidelity.md); DTU follows LLFF. Blender's recommended config (no ramp
    # level on lego's validation views over 5 seeds) and every paper config keep the paper's ramp
    # from 4 down to 1e-3.
    # They also chose mip-NeRF 360's distortion loss at 0.01 (5 seeds, the same views); the
    # paper configs, the Blender family and the baselines train without it.
    for name in ("llff3_grid", "dtu3_grid"):
        config = load_config(name)
        assert config.loss.lambda_colour_start == config.loss.lambda_colour_end == 1e-3, name
        assert config.loss.distortion_weight == 0.01, name
        assert "validation views" in config.chosen_on and "distortion" in config.chosen_on, name
    for name in ("llff3", "dtu3", "blender4", "llff6", "blender4_grid", "builtin_grid"):
        config = load_config(name)
        assert (config.loss.lambda_colour_start, config.loss.lambda_colour_end) == (4.0, 1e-3), name
    every = sorted(path.stem for path in (REPO / "configs").glob("*.toml"))
    adds_it = {"llff3_grid", "dtu3_grid"}
    for name in every:
        expected = 0.01 if name in adds_it else 0.0
        assert load_config(name).loss.distortion_weight == expected, name
    assert "validation views" in load_config("blender4_grid").chosen_on


def test_unknown_key_names_key_and_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[model]\nwidht = 3\n")
    with pytest.raises(ConfigError, match=r"unknown key 'widht' in \[model\]") as error:
        load_config(path)
    assert "bad.toml" in str(error.value)


def test_an_unknown_override_is_named_first_on_its_own_line():
    overrides = ["train.max_steps=10", "mlp.width=5", "train.bogus=3"]
    with pytest.raises(ConfigError) as error:
        load_config(None, overrides)
    first, *rest = str(error.value).splitlines()
    assert first == "unknown key 'bogus' in [train] (train.bogus)"
    assert any("train.max_steps=10" in line for line in rest)
    with pytest.raises(ConfigError, match=r"^train\.max_steps \(given in"):
        load_config(None, ["train.max_steps=ten"])


def test_unknown_section_names_key_and_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[modle]\nwidth = 3\n")
    with pytest.raises(ConfigError, match=r"bad\.toml.*'modle'"):
        load_config(path)


def test_wrong_type_is_an_error(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[train]\nmax_steps = "many"\n')
    with pytest.raises(ConfigError, match="max_steps"):
        load_config(path)


def test_bad_literal_and_bad_value(tmp_path):
    with pytest.raises(ConfigError, match="depth_scale"):
        load_config(None, ["loss.depth_scale=both"])
    with pytest.raises(ConfigError, match="train.batch_size must be positive"):
        load_config(None, ["train.batch_size=0"])


@pytest.mark.parametrize("seed", ["-1", "4294967296", "9223372036854775807", "99999999999999999999"])
def test_a_seed_outside_32_bits_is_refused_not_aliased(seed):
    # JAX's keys take seeds modulo 2^32: 4294967296 would have trained as seed 0.
    with pytest.raises(ConfigError, match=r"train.seed must lie in \[0, 4294967295\] \(wider seeds alias\)"):
        load_config(None, [f"train.seed={seed}"])
    assert load_config(None, ["train.seed=4294967295"]).train.seed == 4294967295


@pytest.mark.parametrize(
    "override", ["optim.lr_init=inf", "loss.lambda_depth=inf", "data.far=inf", "model.density_bias=nan", "grid.tv_weight=-inf"]
)
def test_every_float_setting_must_be_finite(override):
    key = override.split("=")[0]
    with pytest.raises(ConfigError, match=f"{key} must be a finite number"):
        load_config("builtin_grid", [override])


@pytest.mark.parametrize("resolution", [8, 30, 31])
def test_a_built_in_scene_too_small_to_score_is_refused_before_training(resolution):
    with pytest.raises(ConfigError, match="data.resolution must be at least 32"):
        load_config(None, [f"data.resolution={resolution}"])
    assert load_config(None, ["data.resolution=32"]).data.resolution == 32


def test_a_config_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "latin.toml"
    path.write_bytes("name = 'caf\u00e9'\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="latin.toml: not a UTF-8 text file"):
        load_config(str(path))


def test_an_override_that_sets_a_section_is_the_one_blamed():
    # `train=3` made `train` a value; the later `train.max_steps=3` is not at fault.
    with pytest.raises(ConfigError, match=r"override 'train=3': train is a section, not a value"):
        load_config(None, ["train=3", "train.max_steps=3"])


def test_overrides_parse_toml_values():
    config = load_config(
        None, ["train.max_steps=12", "loss.lambda_depth=0.5", "model.lindisp=true", "train.run_dir=somewhere"]
    )
    assert config.train.max_steps == 12
    assert config.loss.lambda_depth == 0.5
    assert config.model.lindisp is True
    assert config.train.run_dir == "somewhere"
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(None, ["no_equals_sign"])


def test_config_is_frozen():
    config = load_config(None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.train.max_steps = 3  # type: ignore[misc]


def test_baseline_has_no_mixture_parts():
    baseline = load_config(None, ["method=mipnerf"])
    model = build_model(baseline, key=jax.random.key(0))
    assert model.mixture is None
    assert not model.field.has_mixture_heads
    mixnerf = build_model(load_config(None), key=jax.random.key(0))
    assert isinstance(mixnerf.mixture, mx.nn.LaplaceMixture)
    assert mixnerf.field.has_mixture_heads


def test_background_component_follows_the_scene_and_the_option():
    on = load_config(None, ["loss.background_component=true", "loss.background_scale=0.02"])
    mixture = build_model(on, key=jax.random.key(0), white_background=True).mixture
    assert mixture.background == (1.0, 1.0, 1.0) and mixture.background_scale == 0.02
    # A scene without a background colour (LLFF) has no background component to add.
    assert build_model(on, key=jax.random.key(0), white_background=False).mixture.background is None
    # Off by default: the paper's normalised weights.
    assert build_model(load_config(None), key=jax.random.key(0)).mixture.background is None
    with pytest.raises(ConfigError, match="background_scale"):
        load_config(None, ["loss.background_scale=0"])


def test_method_is_chosen_not_inferred():
    """Zero mixture weights no longer make a baseline: the config says so, and says what to do."""
    zeros = [
        "loss.lambda_colour_start=0",
        "loss.lambda_colour_end=0",
        "loss.lambda_depth=0",
        "loss.lambda_regen=0",
    ]
    with pytest.raises(ConfigError, match='method = "mipnerf"'):
        load_config(None, zeros)
    assert load_config(None, [*zeros, "method=mipnerf"]).method == "mipnerf"
    with pytest.raises(ConfigError, match="method"):
        load_config(None, ["method=nerf"])


def test_removed_keys_of_older_runs_warn_and_are_ignored():
    stored = mx.config.config_from_dict({"train": {"max_steps": 5}})
    with pytest.warns(DeprecationWarning, match="typecheck is no longer a setting.*--no-typecheck"):
        old = mx.config.config_from_dict({"train": {"max_steps": 5, "typecheck": False}})
    assert old == stored


def test_renamed_keys_of_older_runs_warn_and_are_read_as_the_new_key():
    """The occupancy threshold's keys lost the word "calibrate": an old run folder's config or
    an old command line still reads, with a warning that names the new key."""
    with pytest.warns(FutureWarning) as record:
        old = mx.config.config_from_dict({"occupancy": {"calibrate": False, "calibrate_rays": 512}})
    assert [str(w.message) for w in record] == [
        "<dict>: occupancy.calibrate is now occupancy.choose_threshold; read as that",
        "<dict>: occupancy.calibrate_rays is now occupancy.threshold_rays; read as that",
    ]
    assert old.occupancy.choose_threshold is False and old.occupancy.threshold_rays == 512
    assert old == mx.config.config_from_dict({"occupancy": {"choose_threshold": False, "threshold_rays": 512}})
    with pytest.warns(FutureWarning, match="occupancy.calibrate is now occupancy.choose_threshold"):
        assert load_config(None, ["occupancy.calibrate=false"]).occupancy.choose_threshold is False
    with pytest.raises(ConfigError, match="calibrate_doublings and occupancy.threshold_doublings both given"):
        mx.config.config_from_dict({"occupancy": {"calibrate_doublings": 3, "threshold_doublings": 4}})


def test_each_field_reads_its_own_section_and_a_key_of_another_field_is_an_error(tmp_path):
    """[model] holds what every field shares, [mlp] and [grid] each field's own keys; a key set
    in the section of a field the config does not use is an error that names it."""
    grid = load_config("builtin_grid")
    # A config that switches the field starts the section it leaves from its defaults.
    assert load_config("builtin").mlp.width == 64 and grid.mlp == mx.config.config_from_dict({}).mlp
    assert load_config("builtin", ["model.field=grid"]).mlp == grid.mlp
    with pytest.raises(ConfigError, match=r"mlp.width = 64: \[mlp\] does not apply to model.field = 'grid'"):
        load_config("builtin_grid", ["mlp.width=64"])
    with pytest.raises(ConfigError, match=r"grid.levels = 2, grid.features = 4: \[grid\] does not apply"):
        load_config("builtin", ["grid.levels=2", "grid.features=4"])
    (tmp_path / "mixed.toml").write_text('[model]\nfield = "grid"\n[mlp]\ndepth = 3\n')
    with pytest.raises(ConfigError, match="mlp.depth = 3"):
        load_config(tmp_path / "mixed.toml")
    # A grid key that the chosen encoding does not read is an error too.
    with pytest.raises(ConfigError, match=r"grid.tv_weight = 0.5 applies to grid.encoding = 'triplane' only"):
        load_config("builtin_grid", ['grid.encoding="hash"'])
    with pytest.raises(ConfigError, match=r"grid.hash_table_log2 = 12 applies to grid.encoding = 'hash' only"):
        load_config("builtin_grid", ["grid.hash_table_log2=12"])
    hashed = load_config("builtin_grid", ['grid.encoding="hash"', "grid.tv_weight=0", "grid.hash_table_log2=12"])
    assert hashed.grid.hash_table_log2 == 12


def test_old_model_keys_of_a_field_name_their_new_section():
    """Files, command lines and run folders from before [mlp] still load, with a warning that
    names the new key; an old grid run's MLP keys, which it never read, are dropped."""
    with pytest.warns(FutureWarning, match=r"model\.width is now mlp\.width; read as that"):
        old = mx.config.config_from_dict({"model": {"width": 48, "num_coarse_samples": 8}})
    assert (old.mlp.width, old.model.num_coarse_samples) == (48, 8)
    with pytest.warns(FutureWarning, match="model.matmul_dtype is now mlp.matmul_dtype"):
        assert load_config(None, ['model.matmul_dtype="bfloat16"']).mlp.matmul_dtype == "bfloat16"
    # Typed by a user, an old key of the field a config does not use is an error as the new one is.
    with pytest.warns(FutureWarning, match="model.width is now mlp.width"):
        with pytest.raises(
            ConfigError, match=r"mlp.width = 32: \[mlp\] does not apply .* or set model.field = 'mlp'"
        ):
            load_config("builtin_grid", ["model.width=32"])
    # Written by a run: read silently, and the unused field's section ignored, whatever older
    # versions kept there (an old grid run's MLP keys; an old MLP run's grid keys).
    old_grid_run = {"model": {"field": "grid", "width": 64, "depth": 4}, "grid": {"levels": 3}}
    restored = mx.config.config_from_dict(old_grid_run, written_by_a_run=True)
    assert restored.mlp == mx.config.config_from_dict({}).mlp and restored.grid.levels == 3
    old_mlp_run = {"model": {"field": "mlp", "width": 32}, "grid": {"levels": 3, "tv_weight": 0.5}}
    restored = mx.config.config_from_dict(old_mlp_run, written_by_a_run=True)
    assert restored.mlp.width == 32 and restored.grid == mx.config.config_from_dict({}).grid
    with pytest.raises(ConfigError, match="model.depth and mlp.depth both given"):
        mx.config.config_from_dict({"model": {"depth": 3}, "mlp": {"depth": 4}})


def test_moved_public_names_say_where_they_went():
    """Run-folder helpers live in `mx.runs`; the threshold's functions lost "calibrate"."""
    for old, new in [
        ("restore_run", "mixnerf_eqx.runs.restore_run"),
        ("save_checkpoint", "mixnerf_eqx.runs.save_checkpoint"),
        ("calibrate_threshold", "mixnerf_eqx.inference.choose_threshold"),
        ("calibration_rays", "mixnerf_eqx.inference.threshold_rays"),
    ]:
        with pytest.raises(AttributeError, match=f"mixnerf_eqx.{old} has moved: use {new}"):
            getattr(mx, old)
        module, _, name = new.rpartition(".")
        assert callable(getattr(importlib.import_module(module), name))
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        mx.no_such_name  # noqa: B018
    assert not hasattr(mx, "hold_folder")
    with pytest.warns(DeprecationWarning, match="use mixnerf_eqx.runs.FolderBusyError"):
        assert mx.FolderBusyError is mx.runs.FolderBusyError


def test_schema_imports_no_model():
    """Loading a config or a scene must not import the model: `_config` is the bottom layer."""
    import subprocess
    import sys

    code = (
        "import sys, importlib.util;"
        "spec = importlib.util.find_spec('mixnerf_eqx');"
        "import mixnerf_eqx._config as c, ast, inspect;"
        "tree = ast.parse(inspect.getsource(c));"
        "names = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level];"
        "print(names)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_paper_architecture_sizes():
    model = build_model(load_config(None), key=jax.random.key(0))
    field = model.field
    assert len(field.trunk) == 8
    assert field.trunk[0].in_features == 96  # 2 * 3 * 16 IPE frequencies
    assert field.trunk[5].in_features == 256 + 96  # input concatenated after layer 4
    assert field.view_layer.in_features == 256 + 27  # bottleneck + encoded view direction
    assert field.heads.beta_head.in_features == 128 and field.heads.depth_head.in_features == 128
    assert model.coarse_sampler.num_samples == 128 and model.fine_sampler.num_samples == 128


def test_extends_inherits_and_overrides(tmp_path):
    (tmp_path / "base.toml").write_text(
        'name = "base"\nreproduces = "x"\n[mlp]\nwidth = 48\ndepth = 3\nskip_layer = 2\n'
    )
    (tmp_path / "child.toml").write_text('extends = "base.toml"\nname = "child"\n[mlp]\ndepth = 5\n')
    config = load_config(tmp_path / "child.toml")
    assert (config.name, config.mlp.width, config.mlp.depth) == ("child", 48, 5)
    (tmp_path / "loop.toml").write_text('extends = "loop.toml"\n')
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "loop.toml")


def test_baseline_config_is_builtin_without_nlls():
    mixnerf = load_config("builtin")
    baseline = load_config("builtin_mipnerf")
    assert baseline.method == "mipnerf" and mixnerf.method == "mixnerf"
    assert (
        baseline.model == mixnerf.model and baseline.data == mixnerf.data and baseline.optim == mixnerf.optim
    )


def test_notebooks_are_valid_python():
    import json

    for path in NOTEBOOKS:
        notebook = json.loads(path.read_text())
        for index, cell in enumerate(notebook["cells"]):
            if cell["cell_type"] == "code":
                compile("".join(cell["source"]), f"{path}:cell{index}", "exec")


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_config_is_mapped_in_the_configs_readme(path):
    readme = (REPO / "configs" / "README.md").read_text()
    assert f"`{path.name}`" in readme
    config = load_config(path)
    # Each paper cell's published PSNR stands both in the file and in the table.
    for number in re.findall(r"PSNR (\d+\.\d+)", config.reproduces)[:1]:
        row = next(line for line in readme.splitlines() if f"`{path.name}`" in line)
        assert number in row, (path.name, number, row)


@pytest.mark.parametrize(
    ("name", "lambda_depth", "lambda_regen", "max_steps", "lr_init"),
    [
        ("llff3.toml", 1e-4, 1e-5, 69768, 2e-3),
        ("llff9.toml", 1e-6, 1e-7, 209303, 2e-3),
        ("dtu6.toml", 1e-4, 1e-5, 87891, 2e-3),
        ("blender8.toml", 1e-4, 1e-5, 156250, 1e-3),
    ],
)
def test_paper_configs_hold_the_published_hyperparameters(
    name, lambda_depth, lambda_regen, max_steps, lr_init
):
    config = load_config(name)
    assert config.loss.lambda_depth == lambda_depth
    assert config.loss.lambda_regen == lambda_regen
    assert config.train.max_steps == max_steps
    assert config.optim.lr_init == lr_init
    assert (config.mlp.width, config.model.num_coarse_samples, config.train.batch_size) == (256, 128, 4096)


def test_an_old_mlp_run_whose_config_kept_grid_keys_still_restores(tiny_config, tiny_scene, tmp_path):
    """Before [mlp], an MLP run kept whatever [grid] its config had (`--config builtin_grid
    model.field=mlp`); its folder still evaluates and resumes."""
    run_dir = tmp_path / "run"
    config = dataclasses.replace(
        tiny_config, train=dataclasses.replace(tiny_config.train, max_steps=2, run_dir=str(run_dir))
    )
    mx.fit(config, dataset=tiny_scene, progress=False, write_renders=False)
    stored = json.loads((run_dir / "config.json").read_text())
    stored["grid"] = {**stored["grid"], "levels": 3, "tv_weight": 0.5}  # what an older version wrote
    stored["model"] = {**stored["model"], **stored.pop("mlp")}  # under the old names
    (run_dir / "config.json").write_text(json.dumps(stored))
    meta = next((run_dir / "checkpoints").iterdir()) / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "config": stored}))
    run = mx.runs.restore_run(run_dir, dataset=tiny_scene)
    assert run.config.mlp == config.mlp and run.step == 2
    longer = dataclasses.replace(config, train=dataclasses.replace(config.train, max_steps=3))
    assert mx.fit(longer, dataset=tiny_scene, progress=False, write_renders=False).metrics["step"] == 3
