"""Finding a scene's files under the dataset root and loading them with their format's loader.

The dataset root is `data.data_dir` (which `--data-dir` sets), else the environment variable
`MIXNERF_DATA_DIR`. Under it each format keeps its usual layout:

- Blender: `nerf_synthetic/<scene>/`
- LLFF: `nerf_llff_data/<scene>/`
- DTU: `rs_dtu_4/DTU/<scan>/` (or `rs_dtu_4/<scan>/`), with RegNeRF's masks in `idrmasks/<scan>/`
  (or `submission_data/idrmasks/<scan>/`, or `data.dtu_mask_dir`)
- transforms.json: `<scene>/` (a path relative to the root, or an absolute path)

A scene folder directly under the root (`<root>/<scene>/`) is found too, so the root may also
be the `nerf_synthetic/` (or `nerf_llff_data/`, `rs_dtu_4/DTU/`) folder itself.
"""

import dataclasses
from pathlib import Path

from .._config import DataConfig
from . import blender, dtu, llff, transforms
from ._dataset import Dataset
from ._errors import DatasetError, UnknownSceneError
from ._format import ENV_DATA_DIR, DatasetFormat, data_root

__all__ = ["DATASETS", "ENV_DATA_DIR", "FORMATS", "data_root", "find_scene", "load_dataset"]

# The formats of scenes on disk, one entry each (a format is its module and its line here).
FORMATS: dict[str, DatasetFormat] = {
    format.name: format for format in (blender.FORMAT, llff.FORMAT, dtu.FORMAT, transforms.FORMAT)
}


def dataset_names() -> tuple[str, ...]:
    """Every value `data.dataset` may take: the built-in scene, then the formats on disk."""
    return ("builtin", *FORMATS)


DATASETS = dataset_names()  # at import; `dataset_names()` sees formats added since


def _subfolders(folder: Path, limit: int = 20) -> str:
    if not folder.is_dir():
        return "none"
    names = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not names:
        return "none"
    return ", ".join(names[:limit]) + (", ..." if len(names) > limit else "")


def find_scene(root: Path, dataset: str, scene: str) -> Path:
    """The folder of `scene` under `root` in `dataset`'s layout (see the module docstring).

    A scene that is not there is a `DatasetError` that lists where it looked, the benchmark's
    scenes and the folders that do exist.
    """
    if not scene or scene in (".", ".."):
        raise DatasetError(f"data.scene is {scene!r}; name the scene's folder (for example lego or fern).")
    layouts = FORMATS[dataset].layouts
    candidates = [root / layout / scene for layout in layouts] + [root / scene]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    looked = " or ".join(str(c) for c in candidates)
    known = FORMATS[dataset].scenes
    found = "; ".join(
        f"folders in {folder}: {_subfolders(folder)}"
        for folder in [root / layout for layout in layouts] + [root]
        if folder.is_dir()
    )
    if known and scene not in known:
        raise UnknownSceneError(
            f"unknown {dataset} scene {scene!r}: there is no {looked}. The benchmark's scenes are "
            f"{', '.join(known)}; {found}. Fix data.scene."
        )
    raise DatasetError(
        f"{dataset} scene {scene!r} not found: there is no {looked} ({found}). Download "
        f"{FORMATS[dataset].release} and point --data-dir (or {ENV_DATA_DIR}) at the folder that holds it."
    )


def _load_builtin(config: DataConfig) -> Dataset:
    """The procedural scene, after checking that `config` asks for nothing it cannot do."""
    if config.scene != "builtin":
        raise DatasetError(
            f'unknown scene {config.scene!r} for data.dataset = "builtin" (whose only scene is '
            f'"builtin"); for a scene on disk set data.dataset to one of {", ".join(FORMATS)}.'
        )
    if config.image_downscale != 1:
        raise DatasetError(
            f"data.image_downscale = {config.image_downscale} applies to scenes on disk; the built-in "
            f"scene is rendered at data.resolution (now {config.resolution}): set data.resolution "
            "instead and leave data.image_downscale at 1."
        )
    if config.near != DataConfig.near or config.far != DataConfig.far:
        raise DatasetError(
            f"data.near = {config.near:g} and data.far = {config.far:g} apply to scenes on disk; the built-in "
            "scene samples between its own bounds, 2 and 6 (its cameras are 4 from the origin): leave them unset."
        )
    from .procedural import make_builtin_scene

    return make_builtin_scene(
        resolution=config.resolution,
        num_train_views=config.num_train_views,
        num_test_views=config.num_test_views,
        num_val_views=config.num_val_views,
    )


def _check_scene_config(config: DataConfig) -> None:
    """Checks the settings of a scene on disk that no format's loader checks first."""
    if config.dataset not in FORMATS:
        raise DatasetError(
            f"unknown dataset format {config.dataset!r} (data.dataset); choose one of {', '.join(dataset_names())}."
        )
    # Checked here, not left to blender.split_ids: with type checking on, an unknown protocol
    # would fail load_blender's Literal annotation with a TypeCheckError instead.
    if config.protocol not in ("mixnerf", "dietnerf"):
        raise DatasetError(
            f'unknown Blender protocol {config.protocol!r}; choose "mixnerf" or "dietnerf" (data.protocol)'
        )
    if config.protocol != "mixnerf" and config.dataset != "blender":
        raise DatasetError(
            f"data.protocol = {config.protocol!r} is a Blender protocol; the {config.dataset} scenes "
            'have one protocol. Set data.protocol = "mixnerf".'
        )
    if config.num_train_views < 1:
        raise DatasetError(f"data.num_train_views must be at least 1, got {config.num_train_views}.")
    if config.far > 0 and not 0 <= config.near < config.far:
        raise DatasetError(f"need 0 <= data.near < data.far, got near={config.near}, far={config.far}.")


def _scene_dir(config: DataConfig) -> Path:
    """The scene's folder: an absolute transforms.json path as given, else found under the root."""
    if config.dataset == "transforms" and Path(config.scene).expanduser().is_absolute():
        scene_dir = Path(config.scene).expanduser()
        if not scene_dir.is_dir():
            raise DatasetError(
                f"transforms.json scene not found: {scene_dir} is not a folder. Fix data.scene."
            )
        return scene_dir
    return find_scene(data_root(config), config.dataset, config.scene)


def load_dataset(config: DataConfig) -> Dataset:
    """Loads the dataset that `config` names.

    **Arguments:**

    - `config`: the data section of a run's config.

    **Returns:**

    The `Dataset`, with the protocol's training and test views. Every problem with the files
    is a `DatasetError` (a `ValueError`) whose message names the file and what to do.
    """
    if config.image_downscale < 1:
        raise DatasetError(f"data.image_downscale must be at least 1, got {config.image_downscale}.")
    if config.dataset == "builtin":
        return _load_builtin(config)
    _check_scene_config(config)
    scene_dir = _scene_dir(config)
    dataset = FORMATS[config.dataset].load(scene_dir, config)
    if config.far > 0:  # bounds given in the config replace the format's own
        dataset = dataclasses.replace(dataset, near=config.near, far=config.far)
    return dataset
