"""Data parallelism: one device, `jax.shard_map` over a mesh, or `jax.pmap`; multi-host set-up.

`DataParallel` wraps a step written with an axis name (see `irdepth_jax.train.steps`) for one of
three modes and moves states and batches to where that mode wants them:

======== ============================== ================================ =====================
mode     state / frozen variables       batch                            step
======== ============================== ================================ =====================
single   committed to the first device  on the first device              ``jit``
shard_map replicated NamedSharding P()  sharded P(axis) (global array)   ``jit(shard_map)``
pmap     stacked, one copy per device   reshaped (devices, B/devices)    ``pmap``
======== ============================== ================================ =====================

Multi-host (``shard_map`` only): every process runs the same program, calls
`initialize_distributed` first and feeds its own shard of each global batch; `shard_batch`
assembles the global array with ``jax.make_array_from_process_local_data``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from irdepth_jax.errors import RunError

MODES = ("single", "shard_map", "pmap")
AXIS = "data"


def initialize_distributed(coordinator: str | None = None, num_processes: int | None = None,
                           process_id: int | None = None) -> None:
    """`jax.distributed.initialize` (arguments None: auto-detected by JAX on clusters).

    Call before anything touches a JAX device. Example for two processes on one machine:
    ``initialize_distributed('localhost:12345', 2, i)`` in process i.
    """
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)


def make_mesh(num_devices: int | None = None, axis_name: str = AXIS) -> Mesh:
    """A 1-D mesh over the first `num_devices` global devices (all by default).

    Built with `Mesh` (Auto axes) rather than `jax.make_mesh`, whose Explicit axes would make
    reshapes inside the steps require sharding annotations.
    """
    devices = jax.devices()
    n = len(devices) if num_devices is None else num_devices
    if n < 1 or n > len(devices):
        raise RunError(f"`devices` {n}: this machine has {len(devices)} JAX device(s)")
    return Mesh(np.asarray(devices[:n]), (axis_name,))


class DataParallel:
    """Places data and wraps steps for one parallel mode.

    Args:
      mode: 'single' | 'shard_map' | 'pmap'.
      num_devices: devices to use (all visible by default; 'single' uses one).
      axis_name: the mapped axis name passed to the steps and the models.
    """

    def __init__(self, mode: str = "shard_map", num_devices: int | None = None,
                 axis_name: str = AXIS):
        if mode not in MODES:
            raise ValueError(f"unknown parallel mode {mode!r}; choose one of {MODES}")
        if mode == "single":
            num_devices = 1
        self.mode = mode
        self.mesh = make_mesh(num_devices, axis_name)
        self.devices: Sequence[jax.Device] = list(self.mesh.devices.flat)
        self._axis = axis_name
        if mode == "pmap" and jax.process_count() > 1:
            raise ValueError("multi-host runs use mode='shard_map'")

    def _key(self) -> tuple:
        return (self.mode, tuple(d.id for d in self.devices), self._axis)

    def __eq__(self, other) -> bool:
        return isinstance(other, DataParallel) and self._key() == other._key()

    def __hash__(self) -> int:  # equal set-ups share cached (compiled) steps
        return hash(self._key())

    @property
    def axis_name(self) -> str | None:
        """The axis name for steps and models (None on one device)."""
        return None if self.mode == "single" else self._axis

    @property
    def num_devices(self) -> int:
        return len(self.devices)

    @property
    def local_devices(self) -> int:
        """Devices of this process in the mesh."""
        return sum(d.process_index == jax.process_index() for d in self.devices)

    def describe(self) -> str:
        """One line for the run log, e.g. 'shard_map over 4 devices (2 processes x 2)'."""
        processes = len({d.process_index for d in self.devices})
        where = f" ({processes} processes x {self.local_devices})" if processes > 1 else ""
        return f"{self.mode} over {self.num_devices} device{'s' * (self.num_devices > 1)}{where}"

    # ---------------------------------------------------------------- placement
    def replicate(self, tree: Any) -> Any:
        """Puts a host (or single-device) tree where the steps expect replicated values."""
        if self.mode == "single":
            return jax.device_put(tree, self.devices[0])
        if self.mode == "pmap":
            stacked = NamedSharding(self.mesh, P(self._axis))
            return jax.tree.map(
                lambda x: jax.device_put(np.stack([_first_copy(x)] * self.num_devices), stacked),
                tree)
        sharding = NamedSharding(self.mesh, P())
        return jax.tree.map(lambda x: _replicated_global(_first_copy(x), sharding), tree)

    def unreplicate(self, tree: Any) -> Any:
        """The inverse of `replicate`, as host numpy arrays (one copy)."""
        if self.mode == "pmap":
            return jax.tree.map(lambda x: np.asarray(x[0]), tree)
        return jax.tree.map(_first_copy, tree)

    def shard_batch(self, batch: Any) -> Any:
        """Places this process's part of a global batch (leading axis: examples).

        In multi-host runs every process passes its own rows (global batch / process count);
        otherwise the whole batch.
        """
        if self.mode == "single":
            return jax.device_put(batch, self.devices[0])
        if self.mode == "pmap":
            n, stacked = self.num_devices, NamedSharding(self.mesh, P(self._axis))
            return jax.tree.map(lambda x: jax.device_put(
                np.asarray(x).reshape((n, -1) + np.shape(x)[1:]), stacked), batch)
        sharding = NamedSharding(self.mesh, P(self._axis))
        return jax.tree.map(
            lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch)

    def gather(self, tree: Any) -> Any:
        """Per-example outputs of an eval step as host numpy arrays (all processes' rows)."""
        if self.mode == "pmap":
            return jax.tree.map(lambda x: np.asarray(x).reshape((-1,) + x.shape[2:]), tree)
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils
            return multihost_utils.process_allgather(tree, tiled=True)
        return jax.tree.map(np.asarray, tree)

    # ---------------------------------------------------------------- steps
    def train_step(self, step_fn: Callable, donate: bool = True) -> Callable:
        """Wraps ``step_fn(state, batch, frozen) -> (state, metrics)``.

        The wrapped step takes values placed by `replicate` / `shard_batch` and returns the
        state placed the same way and metrics as replicated scalars (see `metrics_to_host`).
        """
        donate_argnums = (0,) if donate else ()
        if self.mode == "single":
            return jax.jit(step_fn, donate_argnums=donate_argnums)
        if self.mode == "pmap":
            return jax.pmap(step_fn, axis_name=self._axis, in_axes=(0, 0, 0),
                            donate_argnums=donate_argnums)
        mapped = jax.shard_map(step_fn, mesh=self.mesh, in_specs=(P(), P(self._axis), P()),
                               out_specs=(P(), P()))
        return jax.jit(mapped, donate_argnums=donate_argnums)

    def eval_step(self, predict_fn: Callable) -> Callable:
        """Wraps ``predict_fn(variables, batch) -> per-example outputs`` (no collectives)."""
        if self.mode == "single":
            return jax.jit(predict_fn)
        if self.mode == "pmap":
            return jax.pmap(predict_fn, axis_name=self._axis, in_axes=(0, 0))
        mapped = jax.shard_map(predict_fn, mesh=self.mesh, in_specs=(P(), P(self._axis)),
                               out_specs=P(self._axis))
        return jax.jit(mapped)

    def metrics_to_host(self, metrics: dict) -> dict[str, float]:
        """Device metrics of a wrapped train step -> {name: float}."""
        if self.mode == "pmap":
            metrics = jax.tree.map(lambda x: x[0], metrics)
        return {k: float(_first_copy(v)) for k, v in metrics.items()}

    def global_batch_ok(self, batch_size: int, accum_steps: int = 1) -> None:
        """Raises ValueError unless `batch_size` splits into `accum_steps` (>= 1) equal
        micro-batches on each device."""
        if accum_steps < 1 or batch_size < 1 or batch_size % (self.num_devices * accum_steps):
            raise ValueError(f"batch size {batch_size} must be a positive multiple of devices x "
                             f"accumulation steps = {self.num_devices} x {accum_steps}")


def _first_copy(x: Any) -> np.ndarray:
    """Host value of a (replicated) array without a cross-process transfer."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return np.asarray(x.addressable_data(0))
    return np.asarray(x)


def _replicated_global(x: np.ndarray, sharding: NamedSharding) -> jax.Array:
    """A replicated global array from identical host copies (works across processes)."""
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

