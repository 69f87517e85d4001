"""The training log as TensorBoard event files (`train.log_to = ["jsonl", "tensorboard"]`).

`train_log.jsonl` stays the source of truth: this writer mirrors what it holds (every scalar
of a step's entry under `train/`, every metric of a periodic evaluation under `val/`) and adds
the evaluation's images (colour, depth, error and, for MixNeRF, the predictive spread of one
validation view). `tensorboard --logdir RUN_DIR/tensorboard` shows one run; a sweep's root
shows one run per scene and seed. A resumed run appends a new event file to the same folder
and purges what the old ones hold past its checkpoint, as the JSONL drops those entries; a run
that switches TensorBoard on when it resumes mirrors the log from there on.
"""

import importlib.util
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._config import ConfigError

TENSORBOARD_DIR = "tensorboard"


class TensorBoardLog:
    """Writes scalars and images to `run_dir/tensorboard/` with tensorboardX."""

    def __init__(self, run_dir: Path, start: int = 0):
        check_tensorboard()
        from tensorboardX import SummaryWriter

        self.folder = Path(run_dir) / TENSORBOARD_DIR
        # Events past the step resumed from belong to steps the run redoes.
        purge = {"purge_step": start + 1} if start > 0 else {}
        self.writer = SummaryWriter(logdir=str(self.folder), flush_secs=10, **purge)

    def step(self, entry: dict[str, Any]) -> None:
        """One entry of the loss history: each number but the step, as `train/<name>`."""
        step = int(entry["step"])
        for name, value in entry.items():
            if name != "step" and _is_number(value):
                self.writer.add_scalar(f"train/{name}", float(value), step)

    def evaluation(self, step: int, means: dict[str, Any], images: dict[str, np.ndarray]) -> None:
        """A periodic evaluation: its metrics as `val/<name>` and its images (height x width
        x 3, values in [0, 1]) as `val/<name>`."""
        for name, value in means.items():
            if _is_number(value):
                self.writer.add_scalar(f"val/{name}", float(value), step)
        for name, image in images.items():
            pixels = np.clip(np.nan_to_num(np.asarray(image, np.float32)), 0.0, 1.0)
            self.writer.add_image(f"val/{name}", pixels, step, dataformats="HWC")
        self.writer.flush()

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def check_tensorboard() -> None:
    """Raises `ConfigError` (before a run starts) where tensorboardX is not installed."""
    if importlib.util.find_spec("tensorboardX") is None:
        raise ConfigError(
            'train.log_to has "tensorboard", but tensorboardX is not installed: '
            "pip install 'mixnerf_eqx[tensorboard]'"
        )


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
