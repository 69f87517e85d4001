"""Configuration (re-exports only): the typed `Config`, the packaged configs, overrides and
warnings about settings. `Config`, `ConfigError` and `load_config` are also at the top level.

    import mixnerf_eqx as mx
    config = mx.load_config("llff3_grid", ["train.max_steps=500"])
    print(mx.config.config_names())
"""

from ._config import Config as Config
from ._config import ConfigError as ConfigError
from ._config import ScheduleSteps as ScheduleSteps
from ._config import SettingWarning as SettingWarning
from ._config import config_from_dict as config_from_dict
from ._config import config_names as config_names
from ._config import config_path as config_path
from ._config import config_to_dict as config_to_dict
from ._config import load_config as load_config
from ._config import loss_weight as loss_weight
from ._config import schedule_steps as schedule_steps
from ._config import setting_warnings as setting_warnings
