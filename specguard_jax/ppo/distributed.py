"""Data-parallel training over a 1-D device mesh ('data'), on one host or many (jax.sharding + jax.distributed).

Layout (ppo/iteration.py): the batched env state is [G, B/G, ...] where G = env groups (TrainConfig.env_groups, 0 =
one per device); each group is an independent AutoReset(Vmap(env)) with its own pool of initial states, and the
group axis is sharded over the mesh, so acting, GAE and the minibatch shuffle (a permutation inside each group) are
device-local. Agent params, Adam states and normalisers are replicated; the loss and the normaliser statistics are
means over the whole batch, so XLA's SPMD partitioner inserts the all-reduces. The program depends on G, not on the
device count: the same G on 1 and on N devices gives the same result up to float summation order.

Multi-host: `initialize()` calls `jax.distributed.initialize` (flags, or JAX's own env vars / cluster detection);
`jax.devices()` is then every process's devices and the mesh spans them all; only process 0 logs and exports, Orbax
checkpoints are written collectively, and host decisions (checkpoint now, stop) are OR-ed over the processes
(`any_process`). Nothing a compiled phase closes over may live on another process's device (the envs put their
MJX model on the process's own device, envs/base.py).
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "data"


def initialize(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None):
  """Join a multi-process run. With no arguments, uses JAX's env vars (JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES,
  JAX_PROCESS_ID) or cluster auto-detection (SLURM, ...) if set; does nothing for a single-process run."""
  if coordinator is None and num_processes is None and process_id is None:
    if not os.environ.get("JAX_COORDINATOR_ADDRESS"):
      return False
    jax.distributed.initialize()
    return True
  if coordinator is None or num_processes is None or process_id is None:
    raise ValueError("multi-host needs all of --coordinator ADDR:PORT, --num-processes N and --process-id I")
  if not 0 <= process_id < num_processes:
    raise ValueError(f"--process-id must be in [0, {num_processes}), got {process_id}")
  jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
  return True


def is_main() -> bool:
  """True on the process that logs, prints and exports (process 0)."""
  return jax.process_index() == 0


def make_mesh(num_devices: int = 0) -> Mesh:
  """1-D mesh ('data') over the first `num_devices` of jax.devices() (0: all, every process's in multi-host)."""
  devs = jax.devices()
  if num_devices < 0 or num_devices > len(devs):
    raise ValueError(f"devices must be in [0, {len(devs)}] (0 = all), got {num_devices}")
  if num_devices and jax.process_count() > 1 and num_devices != len(devs):
    raise ValueError("a multi-process run uses all devices of all processes (devices=0)")
  return Mesh(np.asarray(devs[:num_devices] if num_devices else devs), (AXIS,))


def groups_for(num_envs: int, env_groups: int, mesh: Mesh) -> int:
  """The env-group count G (env_groups, or the device count when 0); one-line ValueError unless num_envs % G == 0
  and G % devices == 0."""
  d = mesh.size
  g = env_groups or d
  if num_envs % d:
    raise ValueError(f"num_envs ({num_envs}) must be divisible by the device count ({d})")
  if g % d:
    raise ValueError(f"env_groups ({g}) must be a multiple of the device count ({d})")
  if num_envs % g:
    raise ValueError(f"num_envs ({num_envs}) must be divisible by env_groups ({g})")
  return g


def use_gspmd_for_shard_map(mesh: Mesh) -> None:
  """Call before compiling a training program that runs `jax.shard_map` on `mesh` (the lanes EKF kernel's per-device
  env step or sweep members). With jax 0.11.2 on several GPUs, XLA's Shardy partitioner segfaults at compile time (in
  its `shardy-xla` pass) on our training scan with a shard_map inside it or around it; the GSPMD partitioner compiles
  and runs the same program. So on a mesh of several devices this switches the process to
  GSPMD (`jax_use_shardy_partitioner`, a process-wide JAX setting; a no-op on JAX versions without it)."""
  if mesh.size > 1 and getattr(jax.config, "jax_use_shardy_partitioner", False):
    jax.config.update("jax_use_shardy_partitioner", False)


def data_sharding(mesh: Mesh) -> NamedSharding:
  """Leading axis split over the mesh."""
  return NamedSharding(mesh, P(AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, P())


def constrain(tree, sharding):
  """with_sharding_constraint on every array leaf (0-d leaves are left to the partitioner)."""
  return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, sharding) if x.ndim else x, tree)


def replicate(tree, mesh: Mesh):
  """Host/process-local values (identical on every process) -> global arrays replicated over the mesh."""
  sh = replicated(mesh)

  def one(x):
    x = np.asarray(jax.device_get(x))
    return jax.make_array_from_callback(x.shape, sh, lambda idx: x[idx])
  return jax.tree.map(one, tree)


def to_host(tree):
  """Global arrays -> numpy (the whole array on every process). Replicated or process-local arrays are read
  locally; an array sharded over several processes (a sweep's member axis) is gathered, a collective that every
  process must call."""
  def one(x):
    if not isinstance(x, jax.Array) or x.is_fully_addressable or x.is_fully_replicated:
      return np.asarray(x)
    from jax.experimental import multihost_utils
    return np.asarray(multihost_utils.process_allgather(x, tiled=True))
  return jax.tree.map(one, tree)


def any_process(*flags: bool) -> tuple:
  """Each flag OR-ed over all processes (identity in a single-process run). Host decisions taken from a process's
  own clock or signals (checkpoint now, stop now) must agree, or the collective checkpoint save waits forever."""
  if jax.process_count() == 1:
    return tuple(bool(f) for f in flags)
  from jax.experimental import multihost_utils
  v = multihost_utils.process_allgather(np.asarray(flags, np.int32))   # [processes, n]
  return tuple(bool(f) for f in np.asarray(v).reshape(jax.process_count(), len(flags)).any(axis=0))


def barrier(name: str):
  """Wait until every process reached `name` (no-op in a single-process run): the other processes wait for
  process 0's export and held-out evaluation before they leave train() and shut jax.distributed down."""
  if jax.process_count() > 1:
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices(name)
