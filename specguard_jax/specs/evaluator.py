"""Compiled evaluation of a spec table: whole-episode robustness / violation flags offline, and an online monitor.

`SpecEvaluator.create(table, dt)` parses every spec once (intervals converted to steps with `dt`, seconds per env
step). Robustness is rtamt's discrete-time semantics at time 0 of each episode; a spec is violated when its robustness
is < 0.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence, Tuple

import jax.numpy as jnp

from specguard_jax import stl
from specguard_jax.specs.table import SpecTable


@dataclasses.dataclass(frozen=True)
class SpecEvaluator:
  """Per-spec evaluator of one table; hashable (a valid static jit argument)."""

  names: Tuple[str, ...]
  formulas: Tuple[stl.Formula, ...]
  critical: Tuple[bool, ...]
  dt: float

  @staticmethod
  def create(table: SpecTable, dt: float) -> "SpecEvaluator":
    """dt: env control step in seconds (0.1 for the SpecGuard envs)."""
    return SpecEvaluator(table.names, tuple(table.formula(n, dt) for n in table.names), table.critical, float(dt))

  @property
  def signals(self) -> Tuple[str, ...]:
    return tuple(sorted({s for f in self.formulas for s in stl.signals_of(f)}))

  def robustness_trace(self, signals: Mapping[str, jnp.ndarray], length=None) -> jnp.ndarray:
    """Robustness at every index: [..., T, n_specs]."""
    outs = [stl.robustness(f, signals, length=length) for f in self.formulas]
    shape = jnp.broadcast_shapes(*[o.shape for o in outs])
    return jnp.stack([jnp.broadcast_to(o, shape) for o in outs], axis=-1)

  def __call__(self, signals: Mapping[str, jnp.ndarray], length=None) -> Tuple[jnp.ndarray, jnp.ndarray]:
    """Episode robustness [..., n_specs] (index 0) and violation flags [..., n_specs] (robustness < 0).

    signals: {name: [..., T]} (extra names are ignored); length: optional [...] episode lengths (ragged batches).
    """
    outs = [stl.episode_robustness(f, signals, length=length) for f in self.formulas]
    shape = jnp.broadcast_shapes(*[o.shape for o in outs])
    rob = jnp.stack([jnp.broadcast_to(o, shape) for o in outs], axis=-1)
    return rob, rob < 0

  # --- online ---
  def monitors(self) -> Tuple[stl.OnlineMonitor, ...]:
    return tuple(stl.OnlineMonitor(f) for f in self.formulas)

  def monitor_init(self, batch_shape: Sequence[int] = (), dtype=jnp.float32):
    """Fixed-size online state for a batch of episodes (a tuple of per-spec MonitorStates)."""
    return tuple(m.init(batch_shape, dtype) for m in self.monitors())

  def monitor_update(self, state, signals_t: Mapping[str, jnp.ndarray]):
    """One env step: returns (state, robustness [..., n_specs] of the episode so far, violated [..., n_specs])."""
    new, vals = [], []
    for m, s in zip(self.monitors(), state):
      s2, v = m.update(s, signals_t)
      new.append(s2)
      vals.append(v)
    rob = jnp.stack(vals, axis=-1)
    return tuple(new), rob, rob < 0

  def settled(self, state, robustness) -> jnp.ndarray:
    """Per-spec robustness [..., n_specs] over the positions whose windows have closed (stl.OnlineMonitor.settled:
    never rises within an episode, < 0 once a violation is certain), from the monitor state and the so-far
    robustness [..., n_specs] that monitor_update returned with it."""
    vals = [m.settled(s, robustness[..., i]) for i, (m, s) in enumerate(zip(self.monitors(), state))]
    shape = robustness.shape[:-1]
    return jnp.stack([jnp.broadcast_to(v, shape) for v in vals], axis=-1)
