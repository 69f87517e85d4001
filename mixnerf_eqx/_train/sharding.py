"""Data-parallel training over every device: one mesh axis, the ray batch split along it.

The training step stays the single-device step. `DataParallel` only says where its inputs
and outputs live: the parameters, optimiser state and ray table are replicated on every
device of a `jax.sharding.Mesh` with one axis, `"data"`, and each batch is split along that
axis, so each device renders `batch_size / num_devices` rays. XLA's partitioner turns the
loss's mean over rays into an all-reduce, so every device applies the same update and the
replicas stay equal. The step's randomness does not depend on the layout (JAX draws
partitionable random bits), so a sharded step equals the single-device step up to the order
of the floating-point sums.

Several hosts: call `initialize_distributed()` (which calls `jax.distributed.initialize`) in
every process before anything touches a device; the mesh then spans the devices of all
processes. `docs/scaling.md` shows a Slurm launch.
"""

import os
from collections.abc import Callable
from typing import Any, TypeVar

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._config import ConfigError

DATA_AXIS = "data"
# Set to 1 to have `initialize_distributed` join a multi-process run (Slurm, or the
# coordinator variables that `jax.distributed.initialize` reads).
ENV_DISTRIBUTED = "MIXNERF_EQX_DISTRIBUTED"

_Tree = TypeVar("_Tree")


def initialize_distributed() -> bool:
    """Joins a multi-process run when `MIXNERF_EQX_DISTRIBUTED=1`; returns whether it did.

    `jax.distributed.initialize()` finds the coordinator, the number of processes and this
    process's rank from Slurm's variables (one task per host), or from
    `JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID`. Without the variable
    nothing happens, so single-host runs are unchanged.
    """
    if os.environ.get(ENV_DISTRIBUTED, "") not in ("1", "true", "yes"):
        return False
    jax.distributed.initialize()
    return True


def data_parallel_mesh(mode: str, batch_size: int, devices: list[Any] | None = None) -> Mesh | None:
    """The mesh that `mode` asks for, or `None` for single-device training.

    **Arguments:**

    - `mode`: `"auto"` (every device when there is more than one), `"on"` or `"off"`
      (`train.data_parallel`).
    - `batch_size`: rays per step; it must split evenly over the devices.
    - `devices`: the devices to use (default: `jax.devices()`, every process's).

    **Returns:**

    A one-axis `Mesh` named `"data"`, or `None`.
    """
    devices = jax.devices() if devices is None else devices
    if mode == "off" or (mode == "auto" and len(devices) == 1):
        return None
    if batch_size % len(devices):
        raise ConfigError(
            f"train.batch_size = {batch_size} does not split over {len(devices)} devices for "
            f"data-parallel training; choose a multiple of {len(devices)}, or set "
            'train.data_parallel = "off" to train on one device'
        )
    return Mesh(np.asarray(devices), (DATA_AXIS,))


def _place(tree: _Tree, sharding: NamedSharding) -> _Tree:
    """Every array leaf of `tree` as a global array laid out by `sharding` (on one host or many:
    each process supplies the same host value)."""

    def put(leaf):
        if not eqx.is_array(leaf):
            return leaf
        if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            return jax.random.wrap_key_data(put(jax.random.key_data(leaf)), impl=jax.random.key_impl(leaf))
        value = np.asarray(leaf)
        return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])

    return jax.tree_util.tree_map(put, tree)


class DataParallel:
    """Where a data-parallel run's arrays live, and its step and batch draw wrapped to match.

    **Arguments:**

    - `mesh`: a one-axis mesh (`data_parallel_mesh`).
    """

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        self.replicated = NamedSharding(mesh, PartitionSpec())
        self.split = NamedSharding(mesh, PartitionSpec(DATA_AXIS))

    @property
    def num_devices(self) -> int:
        return self.mesh.size

    def replicate(self, tree: _Tree) -> _Tree:
        """`tree` (a `TrainState`, the training rays) copied onto every device."""
        return _place(tree, self.replicated)

    def _constrain(self, tree: _Tree, sharding: NamedSharding) -> _Tree:
        arrays, static = eqx.partition(tree, eqx.is_array)
        arrays = jax.tree_util.tree_map(lambda leaf: jax.lax.with_sharding_constraint(leaf, sharding), arrays)
        return eqx.combine(arrays, static)

    def step(self, step: Callable[[Any, Any], tuple[Any, Any]]) -> Callable[[Any, Any], tuple[Any, Any]]:
        """The training step `(state, batch) -> (state, metrics)` with the batch split over the
        devices and the new state and the metrics replicated."""

        def sharded_step(state, batch):
            state, metrics = step(state, self._constrain(batch, self.split))
            return self._constrain(state, self.replicated), self._constrain(metrics, self.replicated)

        return eqx.filter_jit(sharded_step)

    def draw(self, draw: Callable[..., Any]) -> Callable[..., Any]:
        """A batch draw `(data, state, batch_size) -> Batch` whose batch is split over the
        devices as it is drawn (each device gathers only its own rays)."""

        def sharded_draw(data, state, batch_size):
            return self._constrain(draw(data, state, batch_size), self.split)

        return eqx.filter_jit(sharded_draw)
