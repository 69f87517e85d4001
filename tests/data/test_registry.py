"""Finding scenes under the dataset root: `load_dataset(DataConfig(...))`, `--data-dir`,
`MIXNERF_DATA_DIR`, and the command line's one-line errors."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _writers import write_blender, write_dtu, write_llff, write_transforms

from mixnerf_eqx import ConfigError, load_config
from mixnerf_eqx._config import DataConfig
from mixnerf_eqx.data import ENV_DATA_DIR, DatasetError, load_dataset
from mixnerf_eqx.data.dtu import protocol_ids

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """A dataset root with one tiny scene of each format in its usual layout."""
    root = tmp_path_factory.mktemp("datasets")
    write_blender(root / "nerf_synthetic" / "lego")
    write_llff(root / "nerf_llff_data" / "fern")
    write_dtu(root, "scan8")
    write_transforms(root / "kitchen")
    return root


@pytest.fixture(autouse=True)
def no_env_root(monkeypatch):
    monkeypatch.delenv(ENV_DATA_DIR, raising=False)


def test_data_dir(root):
    dataset = load_dataset(DataConfig(dataset="blender", scene="lego", data_dir=str(root), num_train_views=2))
    assert dataset.name == "lego" and dataset.train.ids == (0, 1) and dataset.test.num_views == 9
    llff = load_dataset(DataConfig(dataset="llff", scene="fern", data_dir=str(root), num_train_views=3))
    # 20 views: test 0, 8, 16; train round(linspace(0, 16, 3)) of the 17 others -> 1, 10, 19.
    assert llff.train.ids == (1, 10, 19) and llff.test.ids == (0, 8, 16) and llff.train.ndc
    dtu = load_dataset(
        DataConfig(dataset="dtu", scene="scan8", data_dir=str(root), num_train_views=3, max_test_views=4)
    )
    # The masks are found in <root>/idrmasks/scan8/mask/.
    assert dtu.train.ids == (25, 22, 28) and dtu.test.masks.shape == (4, 12, 16)
    own = load_dataset(
        DataConfig(dataset="transforms", scene="kitchen", data_dir=str(root), num_train_views=2)
    )
    assert own.name == "kitchen" and own.test.ids == (0, 8) and own.train.num_views == 2


def test_environment_variable(root, monkeypatch):
    monkeypatch.setenv(ENV_DATA_DIR, str(root))
    dataset = load_dataset(DataConfig(dataset="blender", scene="lego", num_train_views=1, max_test_views=2))
    assert dataset.train.ids == (0,) and dataset.test.ids == (0, 8)
    # data_dir wins over the environment variable, both when it is good and when it is wrong.
    with pytest.raises(DatasetError, match=r"dataset root not found: .*elsewhere \(from data\.data_dir"):
        load_dataset(DataConfig(dataset="blender", scene="lego", data_dir=str(root / "elsewhere")))
    monkeypatch.setenv(ENV_DATA_DIR, str(root / "nowhere"))
    llff = load_dataset(DataConfig(dataset="llff", scene="fern", data_dir=str(root), num_train_views=3))
    assert llff.test.ids == (0, 8, 16)


def test_root_may_be_the_format_folder_itself(root):
    config = DataConfig(
        dataset="blender", scene="lego", data_dir=str(root / "nerf_synthetic"), num_train_views=1
    )
    assert load_dataset(config).name == "lego"


def test_config_bounds_replace_the_dataset_bounds(root):
    config = DataConfig(
        dataset="blender", scene="lego", data_dir=str(root), num_train_views=1, near=1.5, far=7.0
    )
    dataset = load_dataset(config)
    assert (dataset.near, dataset.far) == (1.5, 7.0)


def test_transforms_scene_by_absolute_path(root):
    config = DataConfig(dataset="transforms", scene=str(root / "kitchen"), num_train_views=1)
    assert load_dataset(config).train.ids == (1,)
    with pytest.raises(
        DatasetError, match=r"transforms\.json scene not found: .*nothing_here is not a folder"
    ):
        load_dataset(DataConfig(dataset="transforms", scene=str(root / "nothing_here")))


def test_image_downscale_reaches_every_loader(root):
    shapes = {"blender": (2, 1), "llff": (4, 3), "dtu": (8, 6), "transforms": (4, 3)}
    scenes = {"blender": "lego", "llff": "fern", "dtu": "scan8", "transforms": "kitchen"}
    for dataset_format, (width, height) in shapes.items():
        config = DataConfig(
            dataset=dataset_format,
            scene=scenes[dataset_format],
            data_dir=str(root),
            num_train_views=2,
            max_test_views=2,
            image_downscale=2,
        )
        dataset = load_dataset(config)
        assert dataset.train.images.shape[1:3] == dataset.test.images.shape[1:3] == (height, width)
        if dataset_format == "dtu":
            assert dataset.test.masks.shape == (2, height, width)


def test_dtu_masks_found_under_the_root(tmp_path):
    # Masks directly in <root>/idrmasks/scan8/ (no mask/ subfolder), some pixels nearly white.
    _, written = write_dtu(tmp_path, "scan8", mask_layout="flat")
    test_ids = protocol_ids(3)[1]
    dataset = load_dataset(
        DataConfig(dataset="dtu", scene="scan8", data_dir=str(tmp_path), num_train_views=3)
    )
    assert dataset.train.ids == (25, 22, 28) and dataset.test.ids == tuple(test_ids)
    expected = np.stack([written["masks"][view] for view in test_ids])
    np.testing.assert_array_equal(dataset.test.masks, expected)
    with pytest.raises(DatasetError, match=r"DTU object masks not found: .*nomasks.scan8 is not a folder"):
        load_dataset(
            DataConfig(
                dataset="dtu", scene="scan8", data_dir=str(tmp_path), dtu_mask_dir=str(tmp_path / "nomasks")
            )
        )


# --- Bad input -------------------------------------------------------------------------------


def test_no_dataset_root():
    with pytest.raises(DatasetError, match=rf"no dataset root for the blender scene 'lego'.*{ENV_DATA_DIR}"):
        load_dataset(DataConfig(dataset="blender", scene="lego"))


def test_missing_data_dir(tmp_path):
    with pytest.raises(
        DatasetError, match=r"dataset root not found: .*missing \(from data\.data_dir \(--data-dir\)\)"
    ):
        load_dataset(DataConfig(dataset="llff", scene="fern", data_dir=str(tmp_path / "missing")))


def test_missing_environment_root(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_DATA_DIR, str(tmp_path / "gone"))
    with pytest.raises(DatasetError, match=rf"dataset root not found: .*gone \(from {ENV_DATA_DIR}\)"):
        load_dataset(DataConfig(dataset="llff", scene="fern"))


def test_unknown_scene(root):
    with pytest.raises(
        DatasetError, match=r"unknown blender scene 'lgo': there is no .*nerf_synthetic.lgo.*lego"
    ):
        load_dataset(DataConfig(dataset="blender", scene="lgo", data_dir=str(root)))


def test_benchmark_scene_not_downloaded(root):
    with pytest.raises(
        DatasetError, match=r"llff scene 'horns' not found: there is no .*nerf_llff_data.horns.*Download"
    ):
        load_dataset(DataConfig(dataset="llff", scene="horns", data_dir=str(root)))


def test_protocol_of_another_format(root):
    with pytest.raises(DatasetError, match=r"data\.protocol = 'dietnerf' is a Blender protocol"):
        load_dataset(DataConfig(dataset="llff", scene="fern", data_dir=str(root), protocol="dietnerf"))


def test_unknown_protocol_in_a_config():
    with pytest.raises(ConfigError, match=r"protocol.*'infonerf' is not one of"):
        load_config(REPO / "configs" / "blender4.toml", ['data.protocol="infonerf"'])


def test_unknown_builtin_scene():
    with pytest.raises(DatasetError, match=r"unknown scene 'lego' for data\.dataset = \"builtin\""):
        load_dataset(DataConfig(dataset="builtin", scene="lego"))


@pytest.mark.parametrize("dataset_format", ["builtin", "blender", "llff", "dtu", "transforms"])
def test_image_downscale_below_one(root, dataset_format):
    scene = {"blender": "lego", "llff": "fern", "dtu": "scan8", "transforms": "kitchen"}.get(
        dataset_format, "builtin"
    )
    config = DataConfig(dataset=dataset_format, scene=scene, data_dir=str(root), image_downscale=0)
    with pytest.raises(DatasetError, match=r"data\.image_downscale must be at least 1, got 0"):
        load_dataset(config)


def test_image_downscale_of_the_builtin_scene():
    with pytest.raises(DatasetError, match=r"image_downscale = 2 .*built-in scene.*set data\.resolution"):
        load_dataset(DataConfig(image_downscale=2))


def test_bad_view_count_and_bounds(root):
    with pytest.raises(DatasetError, match=r"data\.num_train_views must be at least 1"):
        load_dataset(DataConfig(dataset="blender", scene="lego", data_dir=str(root), num_train_views=0))
    with pytest.raises(DatasetError, match=r"need 0 <= data\.near < data\.far"):
        load_dataset(DataConfig(dataset="blender", scene="lego", data_dir=str(root), near=3.0, far=2.0))


def test_more_training_views_than_exist(root):
    with pytest.raises(DatasetError, match=r"fern.images_8: 18 training views asked for, but only 17"):
        load_dataset(DataConfig(dataset="llff", scene="fern", data_dir=str(root), num_train_views=18))


def _unchecked(config, **changes):
    """`config` with values its type hints forbid, as a run with --no-typecheck could hold."""
    for name, value in changes.items():
        object.__setattr__(config, name, value)
    return config


def test_unknown_protocol_and_format(root):
    config = _unchecked(DataConfig(dataset="blender", scene="lego", data_dir=str(root)), protocol="regnerf")
    with pytest.raises(DatasetError, match="unknown Blender protocol 'regnerf'"):
        load_dataset(config)
    config = _unchecked(DataConfig(scene="fern", data_dir=str(root)), dataset="colmap")
    with pytest.raises(DatasetError, match="unknown dataset format 'colmap'"):
        load_dataset(config)


def test_command_line_reports_one_error_line(tmp_path):
    missing = tmp_path / "no_such_root"
    env = {key: value for key, value in os.environ.items() if key != ENV_DATA_DIR}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "mixnerf_eqx.train",
            "--config",
            "blender4",
            "--data-dir",
            str(missing),
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr
    output = result.stdout + result.stderr
    assert "Traceback" not in output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1
    assert str(missing) in errors[0] and "not a folder" in errors[0]


@pytest.mark.parametrize("bounds", [{"near": 1.0, "far": 7.0}, {"far": 9.0}])
def test_bounds_set_for_the_built_in_scene_are_refused_not_ignored(bounds):
    # They were ignored (the metrics were identical), while data.image_downscale was refused.
    with pytest.raises(DatasetError, match="apply to scenes on disk; the built-in scene samples between its own bounds"):
        load_dataset(DataConfig(**bounds))


def test_a_resumed_run_refuses_a_scene_whose_files_changed(tmp_path):
    import dataclasses

    from _writers import random_pixels, write_png
    from helpers import TINY_SHARED_OVERRIDES

    from mixnerf_eqx import fit

    write_blender(tmp_path / "nerf_synthetic" / "toy", num_train=5, num_test=9, height=8, width=8)
    overrides = [o for o in TINY_SHARED_OVERRIDES if not o.startswith("data.")]
    config = load_config(
        "blender4_grid",
        [*overrides, "grid.coarse_to_fine_steps=0", "data.scene=toy", f"data.data_dir={str(tmp_path)!r}", f"train.run_dir={str(tmp_path / 'run')!r}"],
    )
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, max_steps=4, eval_every=0))
    fit(config, progress=False, write_renders=False, stop_after=1)
    # The same scene again resumes; a training image rewritten does not.
    fit(config, progress=False, write_renders=False, stop_after=2)
    write_png(tmp_path / "nerf_synthetic" / "toy" / "train" / "r_0.png", random_pixels(np.random.default_rng(9), 8, 8, 4))
    with pytest.raises(ConfigError, match="holds other data"):
        fit(config, progress=False, write_renders=False, stop_after=3)
