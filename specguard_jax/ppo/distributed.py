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

import ipaddress
import os
import re
import socket
import sys
import threading
import time

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from specguard_jax import checks

AXIS = "data"


DEFAULT_TIMEOUT_S = 300   # jax.distributed.initialize's own initialization_timeout
_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*$")   # RFC 1123 host names, IPv4 addresses


def parse_address(addr, what: str = "--coordinator") -> tuple:
  """(host, port) of a coordinator address HOST:PORT (a host name, an IPv4 address or a bracketed IPv6 address
  [::1]:1234; port 1-65535); one-line ValueError otherwise (jax's own parser fails on one with an IndexError)."""
  allowed = "HOST:PORT (a host name or IP address, [IPv6]:PORT; port 1-65535), e.g. 10.0.0.1:1234"
  host, sep, port = str(addr).rpartition(":")
  if host.startswith("[") and host.endswith("]"):
    try:
      ipaddress.IPv6Address(host[1:-1])
    except ValueError:
      raise ValueError(f"{what} {addr!r}: {host} is not an IPv6 address; expected {allowed}") from None
    host = host[1:-1]
  elif not sep or not _HOSTNAME.match(host):
    raise ValueError(f"{what} {addr!r} is not a coordinator address; expected {allowed}")
  if not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
    raise ValueError(f"{what} {addr!r}: port {port!r} is not in 1-65535; expected {allowed}")
  return host, int(port)


def check_port_free(port: int, what: str) -> None:
  """Process 0 serves the coordinator on `port` of every interface (jax's default bind address): one-line
  ValueError when something on this host holds it already (jax would crash the process)."""
  for family, addr in ((socket.AF_INET6, "::"), (socket.AF_INET, "0.0.0.0")):
    try:
      with socket.socket(family, socket.SOCK_STREAM) as sk:
        sk.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sk.bind((addr, port))
      return
    except OSError as e:
      if e.errno == 98:   # EADDRINUSE; other errors (no IPv6 on this host): try the next family
        raise ValueError(f"{what}: port {port} is in use on this host (process 0 serves the coordinator there); "
                         "pick a free port") from None


def _tcp_state(host: str, port: int) -> str:
  try:
    with socket.create_connection((host, port), timeout=2.0):
      return "its port accepts connections"
  except OSError as e:
    return f"TCP connect: {e.strerror or e}"


def _exit_with_error(message: str) -> None:
  print(f"error: {message}", file=sys.stderr, flush=True)
  os._exit(2)


def initialize(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None, *,
               timeout_s: float = DEFAULT_TIMEOUT_S, log=print, give_up=_exit_with_error):
  """Join a multi-process run. With no arguments, uses JAX's env vars (JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES,
  JAX_PROCESS_ID) or cluster auto-detection (SLURM, ...) if set; does nothing for a single-process run.

  Addresses, counts and (on process 0) the coordinator's port are checked before jax sees them (one-line
  ValueError). While the processes have not all joined, logs "waiting for coordinator ADDR (N s)" (after 1 s, then
  every 10 s); after timeout_s s calls give_up(one-line reason), which must not return: jax itself would abort the
  whole process with a C++ fatal error and a stack trace a little later (its timeout is set beyond ours), and a
  thread cannot interrupt the native call, so the default prints the reason on stderr and exits with status 2."""
  checks.number("--coordinator-timeout", timeout_s, 1)
  if coordinator is None and num_processes is None and process_id is None:
    env_addr = os.environ.get("JAX_COORDINATOR_ADDRESS")
    if not env_addr:
      return False
    parse_address(env_addr, "JAX_COORDINATOR_ADDRESS")
    _join(env_addr, None, timeout_s, log, give_up)
    return True
  if coordinator is None or num_processes is None or process_id is None:
    raise ValueError("multi-host needs all of --coordinator ADDR:PORT, --num-processes N and --process-id I")
  host, port = parse_address(coordinator)
  if num_processes < 1:
    raise ValueError(f"--num-processes must be >= 1, got {num_processes}")
  if not 0 <= process_id < num_processes:
    raise ValueError(f"--process-id must be in [0, {num_processes}), got {process_id}")
  if process_id == 0:
    check_port_free(port, f"--coordinator {coordinator}")
  _join(coordinator, (host, port, num_processes, process_id), timeout_s, log, give_up)
  return True


def _join(addr: str, run, timeout_s: float, log, give_up) -> None:
  """jax.distributed.initialize (run: (host, port, num_processes, process_id), None: from JAX's env vars) under a
  watchdog thread that logs the wait and gives up after timeout_s."""
  done = threading.Event()
  t0 = time.time()

  def watch():
    next_log = 1.0
    while not done.wait(min(next_log, timeout_s) - (time.time() - t0)):
      waited = time.time() - t0
      if waited >= timeout_s:
        if run is None:
          why = f"the processes did not all join coordinator {addr} within {timeout_s:g} s"
        elif run[3] == 0:
          why = (f"not all {run[2]} processes joined coordinator {addr} within {timeout_s:g} s (this is process 0); "
                 "start the others with the same --coordinator and --num-processes, or raise --coordinator-timeout")
        else:
          why = (f"coordinator {addr} not reached within {timeout_s:g} s ({_tcp_state(run[0], run[1])}); start "
                 "process 0 first, check the address, or raise --coordinator-timeout")
        give_up(why)
        return
      log(f"waiting for coordinator {addr} ({waited:.0f} s)")
      next_log = waited + 10.0

  watcher = threading.Thread(target=watch, name="coordinator-watchdog", daemon=True)
  watcher.start()
  jax_timeout = int(timeout_s) + 60   # beyond ours: the watchdog gives up first, with its one-line reason
  try:
    if run is None:
      jax.distributed.initialize(initialization_timeout=jax_timeout)
    else:
      jax.distributed.initialize(coordinator_address=addr, num_processes=run[2], process_id=run[3],
                                 initialization_timeout=jax_timeout)
  finally:
    done.set()
    watcher.join()


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
