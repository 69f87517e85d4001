# The public names of `mixnerf_eqx`: what `__init__.py` loads on first use, and what type
# checkers and editors read. One line per name; the rest of the API is in the namespaces.
from . import config as config
from . import data as data
from . import inference as inference
from . import metrics as metrics
from . import nn as nn
from . import runs as runs
from . import runtime as runtime
from . import training as training
from . import uncertainty as uncertainty
from ._config import Config as Config
from ._config import ConfigError as ConfigError
from ._config import load_config as load_config
from ._inference.evaluation import Evaluation as Evaluation
from ._inference.evaluation import evaluate as evaluate
from ._inference.rendering import render_views as render_views
from ._inference.video import render_video as render_video
from ._inference.viewer import Viewer as Viewer
from ._nn.model import MixNeRF as MixNeRF
from ._nn.model import build_model as build_model
from ._predictive.distribution import predictive as predictive
from ._predictive.next_view import next_view as next_view
from ._runs.loop import TrainResult as TrainResult
from ._runs.loop import fit as fit
from ._runs.sweep import plan_sweep as plan_sweep
from ._util.typecheck import set_typecheck as set_typecheck
