"""Training (re-exports only): `fit`, the objective and its registry of loss terms, schedules,
the training state and its pure step, data-parallel training and sweeps.

    import mixnerf_eqx as mx
    result = mx.fit(config, dataset=scene)          # the whole loop (also mx.training.fit)
    state = mx.training.init_train_state(config, scene)
    step = mx.training.make_train_step(config)      # (state, batch) -> (state, metrics)
"""

from ._runs.loop import TrainResult as TrainResult
from ._runs.loop import TrainingDiverged as TrainingDiverged
from ._runs.loop import fit as fit
from ._train.loss import LossInputs as LossInputs
from ._train.loss import LossTerm as LossTerm
from ._train.loss import LossTerms as LossTerms
from ._train.loss import LossWeights as LossWeights
from ._train.loss import loss_fn as loss_fn
from ._train.loss import loss_term_names as loss_term_names
from ._train.loss import loss_terms as loss_terms
from ._train.loss import register_loss_term as register_loss_term
from ._train.loss import unregister_loss_term as unregister_loss_term
from ._train.schedule import anneal_sample_space as anneal_sample_space
from ._train.schedule import learning_rate_schedule as learning_rate_schedule
from ._train.schedule import linear_ramp as linear_ramp
from ._train.sharding import DataParallel as DataParallel
from ._train.sharding import data_parallel_mesh as data_parallel_mesh
from ._train.sharding import initialize_distributed as initialize_distributed
from ._train.state import Batch as Batch
from ._train.state import StepMetrics as StepMetrics
from ._train.state import TrainState as TrainState
from ._train.state import TrainingRays as TrainingRays
from ._train.state import draw_batch as draw_batch
from ._train.state import init_key as init_key
from ._train.state import init_train_state as init_train_state
from ._train.state import make_occupancy_grid as make_occupancy_grid
from ._train.state import make_optimizer as make_optimizer
from ._train.state import make_train_step as make_train_step
from ._train.state import occupancy_key as occupancy_key
from ._train.state import scene_box as scene_box
from ._train.state import training_rays as training_rays
from ._train.state import update_grid as update_grid
from ._runs.sweep import plan_sweep as plan_sweep
