"""What a dataset format is to the rest of the package: `DatasetFormat`, and the dataset root.

A format is one module of `mixnerf_eqx.data` that defines `FORMAT = DatasetFormat(...)` (its
folder layouts under the dataset root, its benchmark's scenes, what to download, and how a
scene's folder loads with a config's data section) plus its line in `_registry.FORMATS`.
Nothing else names the formats: config validation, the registry's errors, `find_scene` and
sweeps read this record.
"""

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

from .._config import DataConfig
from ._dataset import Dataset
from ._errors import DatasetError

ENV_DATA_DIR = "MIXNERF_DATA_DIR"


@dataclasses.dataclass(frozen=True)
class DatasetFormat:
    """One dataset format.

    **Fields:**

    - `name`: the value of `data.dataset` that picks it.
    - `layouts`: folders under the dataset root that hold its scenes, most usual first (a scene
      folder directly under the root is found as well).
    - `scenes`: its benchmark's scenes (what a sweep runs, and what an unknown scene's error
      lists); empty for a format without a benchmark.
    - `release`: what to download where a scene is missing, in a few words.
    - `load`: `(scene folder, data section) -> Dataset`; every problem with the files is a
      `DatasetError` that names the file.
    """

    name: str
    layouts: tuple[str, ...]
    scenes: tuple[str, ...]
    release: str
    load: Callable[[Path, DataConfig], Dataset]


def data_root(config: DataConfig) -> Path:
    """The dataset root: `config.data_dir`, else `$MIXNERF_DATA_DIR`; it must be a folder."""
    raw = config.data_dir or os.environ.get(ENV_DATA_DIR, "")
    if not raw:
        raise DatasetError(
            f"no dataset root for the {config.dataset} scene {config.scene!r}: pass --data-dir DIR, set "
            f"data.data_dir in the config, or set the environment variable {ENV_DATA_DIR}."
        )
    root = Path(raw).expanduser()
    source = "data.data_dir (--data-dir)" if config.data_dir else ENV_DATA_DIR
    if not root.is_dir():
        raise DatasetError(f"dataset root not found: {root} (from {source}) is not a folder. Fix the path.")
    return root
