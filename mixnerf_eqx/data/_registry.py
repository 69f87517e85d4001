from .._config import DataConfig
from ._dataset import Dataset

SCENES = ("builtin",)


def load_dataset(config: DataConfig) -> Dataset:
    """Loads the dataset that `config` names."""
    if config.scene == "builtin":
        from .procedural import make_builtin_scene

        return make_builtin_scene(
            resolution=config.resolution,
            num_train_views=config.num_train_views,
            num_test_views=config.num_test_views,
        )
    raise ValueError(f"unknown scene {config.scene!r}; available: {', '.join(SCENES)}")
