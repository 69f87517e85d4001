"""Datasets: one module per format, all producing the same typed `Dataset`.

- `procedural`: the built-in analytic scene (no files).
- `blender`: the NeRF synthetic scenes (`nerf_synthetic/<scene>/transforms_*.json`).
- `llff`: the LLFF forward-facing scenes (`nerf_llff_data/<scene>/poses_bounds.npy`, NDC rays).
- `dtu`: DTU scans in pixelNeRF's `rs_dtu_4` layout, with RegNeRF's object masks.
- `transforms`: a user's own scene in the nerfstudio / instant-ngp `transforms.json` convention.

`load_dataset(config.data)` finds the files under the dataset root (`--data-dir` or
`MIXNERF_DATA_DIR`) and picks the loader; `rays_for_views` builds the rays of any split.
"""

from ._dataset import Dataset as Dataset
from ._dataset import Views as Views
from ._dataset import rays_at_poses as rays_at_poses
from ._dataset import rays_for_views as rays_for_views
from ._errors import DatasetError as DatasetError
from ._errors import UnknownSceneError as UnknownSceneError
from ._format import ENV_DATA_DIR as ENV_DATA_DIR
from ._format import DatasetFormat as DatasetFormat
from ._format import data_root as data_root
from ._registry import DATASETS as DATASETS
from ._registry import FORMATS as FORMATS
from ._registry import find_scene as find_scene
from ._registry import load_dataset as load_dataset
from ._splits import evenly_spaced as evenly_spaced
from .blender import load_blender as load_blender
from .dtu import load_dtu as load_dtu
from .llff import load_llff as load_llff
from .procedural import builtin_views_at as builtin_views_at
from .transforms import load_transforms as load_transforms
