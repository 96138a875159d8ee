"""Compile ahead: a run's later programs (phase 2's init and run, the held-out evaluation's rollout) are compiled on
background threads while the current phase compiles and trains.

Why: on a GPU a default run spends more time in XLA compiling its three programs, one after the other, than in
training (several times more; docs/PERFORMANCE.md). XLA compilation
releases the GIL, so the programs compile side by side on the host's cores (evaluation.precompile does the same for
`evaluate.py`). What a thread compiles is exactly what the runner later calls: `jax.jit(f).lower(args).compile()`
fills the same compile cache that `f(args)` looks up (checked by tests/test_train.py, which counts XLA compiles), so
the runner's calls are unchanged and only wait (`CompileAhead.wait`) for a program still compiling.

The inputs are abstract (`jax.ShapeDtypeStruct` with the sharding the real value will have): phase n+1's agent
states reach its init as `distributed.replicate`d arrays, and its run gets init's output, whose shardings are read
off init's compiled executable.
"""

from __future__ import annotations

import concurrent.futures
import threading
import time

import jax

from specguard_jax.ppo import distributed


def _thread_future(fn, *args) -> concurrent.futures.Future:
  """fn(*args) on a new thread. Not a daemon: an XLA compile cannot be cancelled, and a process that exits while a
  daemon thread is inside one aborts (C++ `terminate`, exit status 134, seen on jax 0.10.2); so a run stopped early
  (its checkpoint already written) exits once its compiles end."""
  fut = concurrent.futures.Future()

  def target():
    try:
      fut.set_result(fn(*args))
    except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
      fut.set_exception(e)
  threading.Thread(target=target, name="specguard-compile-ahead", daemon=False).start()
  return fut


class CompileAhead:
  """Named compile jobs on background threads: submit(name, fn, *args) starts one; wait(name) blocks until it is
  done (re-raising its error) and returns the seconds waited (0.0 if no such job)."""

  def __init__(self):
    self._jobs: dict[str, concurrent.futures.Future] = {}

  def submit(self, name: str, fn, *args) -> None:
    self._jobs[name] = _thread_future(fn, *args)

  def wait(self, name: str) -> float:
    fut = self._jobs.pop(name, None)
    if fut is None:
      return 0.0
    t0 = time.perf_counter()
    fut.result()
    return time.perf_counter() - t0

  def pending(self) -> list:
    return [n for n, f in self._jobs.items() if not f.done()]


def replicated_spec(tree, mesh):
  """Abstract twin of `distributed.replicate(tree, mesh)` (shapes and dtypes of tree's leaves, concrete or not)."""
  sh = distributed.replicated(mesh)
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh), tree)


def compile_phase(phase, key, sg_state, aa_state) -> None:
  """Compile `phase.init(key, sg_state, aa_state)` and `phase.run` on init's output (all arguments abstract, with
  their shardings), so the runner's first calls of both find them compiled."""
  init = phase.init.lower(key, sg_state, aa_state).compile()
  shapes = jax.eval_shape(phase.init, key, sg_state, aa_state)
  carry = jax.tree.map(lambda s, sh: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sh, weak_type=s.weak_type),
                       shapes, init.output_shardings)
  phase.run.lower(carry).compile()
