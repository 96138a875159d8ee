"""Fixed-state online STL monitor: per-step update of the robustness of the trace-so-far at time 0.

After n updates, the returned value equals `robustness(formula, trace[:n])[..., 0]` (offline, truncated semantics).
Supported fragment: any boolean combination (not/and/or/implies) of
  * bounded sub-formulas (every operator has an interval)            -> a prefix buffer of the first h+1 samples;
  * `always(psi)`, `eventually(psi)` with psi bounded (horizon h)      -> running min/max of finalised values plus the
    still-open last h positions, recomputed each step from a sliding buffer of the last h+1 samples;
  * `psi1 until psi2` (unbounded) with bounded psi1, psi2              -> running (min l, best) pair plus the open tail.
Unbounded operators under another temporal operator (e.g. always(eventually(x > 0))) raise UnsupportedOnlineError.
The state size is fixed by the formula's horizons (a few floats per anchor plus (h+1)-sample buffers per signal).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple, Union

import jax.numpy as jnp
from flax import struct

from specguard_jax.stl import ast, columns
from specguard_jax.stl.errors import UnknownSignalError, UnsupportedOnlineError
from specguard_jax.stl.offline import as_formula, evaluate


@struct.dataclass
class MonitorState:
  """t: [...] int32 samples seen.  window: {signal: [..., Hw+1]} last samples, a ring: the sample of time s at
  slot s mod (Hw+1) (written in place, one entry per update; a shifted copy was a full rewrite of every window plus a
  copy into the training loop's carry each step, XLA not aliasing a shift with its input).
  prefix: {signal: [..., Hp+1]} first samples.  acc: per-anchor running accumulators ([...] floats)."""

  t: jnp.ndarray
  window: Dict[str, jnp.ndarray]
  prefix: Dict[str, jnp.ndarray]
  acc: Tuple[Any, ...]


def _anchors(f: ast.Formula, out: list) -> Any:
  """Split the boolean skeleton of `f` into anchors; returns a skeleton tree whose leaves are anchor indices."""
  if math.isfinite(ast.horizon(f)):
    out.append(("B", f, int(ast.horizon(f))))
    return len(out) - 1
  if isinstance(f, ast.Not):
    return ("not", _anchors(f.arg, out))
  if isinstance(f, (ast.And, ast.Or, ast.Implies)):
    return (type(f).__name__.lower(), _anchors(f.left, out), _anchors(f.right, out))
  if isinstance(f, ast.TEMPORAL) and f.interval is None:
    kids = ast.children(f)
    for c in kids:
      if not math.isfinite(ast.horizon(c)):
        raise UnsupportedOnlineError(f"online monitor: unbounded operator nested under an unbounded operator in {f} "
                                     "(supported: boolean combinations of always/eventually/until over bounded "
                                     "sub-formulas)")
    h = max(int(ast.horizon(c)) for c in kids)
    kind = {ast.Always: "G", ast.Eventually: "F", ast.Until: "U"}[type(f)]
    out.append((kind, f, h))
    return len(out) - 1
  raise UnsupportedOnlineError(f"online monitor: unbounded operator nested under bounded operator {f} "
                               "(supported: boolean combinations of always/eventually/until over bounded sub-formulas)")


@dataclasses.dataclass(frozen=True)
class OnlineMonitor:
  """Online monitor of one formula (step intervals). Build with `OnlineMonitor.create(formula_or_text, dt)`."""

  formula: ast.Formula

  @staticmethod
  def create(formula: Union[str, ast.Formula], dt: Optional[float] = None, params=None) -> "OnlineMonitor":
    mon = OnlineMonitor(as_formula(formula, dt, params))
    mon._plan()  # validate the fragment eagerly
    return mon

  def _plan(self):
    anchors = []
    skel = _anchors(self.formula, anchors)
    hw = max([h for k, _, h in anchors if k != "B"], default=-1)
    hp = max([h for k, _, h in anchors if k == "B"], default=-1)
    return skel, anchors, hw, hp

  @property
  def signals(self) -> Tuple[str, ...]:
    return ast.signals_of(self.formula)

  def init(self, batch_shape: Sequence[int] = (), dtype=jnp.float32) -> MonitorState:
    """Empty state for a batch of traces of shape `batch_shape`."""
    _, anchors, hw, hp = self._plan()
    if max(hw, hp) > ast.MAX_WINDOW_STEPS:   # a formula built in Python, not through parse / to_steps
      raise ast.window_error(f"online monitor of {str(self.formula)[:80]}", max(hw, hp))
    bs = tuple(batch_shape)
    names = self.signals
    window = {n: jnp.zeros(bs + (hw + 1,), dtype) for n in names} if hw >= 0 else {}
    prefix = {n: jnp.zeros(bs + (hp + 1,), dtype) for n in names} if hp >= 0 else {}
    inf = jnp.full(bs, jnp.inf, dtype)
    acc = []
    for kind, _, _ in anchors:
      acc.append({"G": (inf,), "F": (-inf,), "U": (inf, -inf), "B": ()}[kind])
    return MonitorState(jnp.zeros(bs, jnp.int32), window, prefix, tuple(acc))

  def update(self, state: MonitorState, signals_t: Mapping[str, jnp.ndarray]) -> Tuple[MonitorState, jnp.ndarray]:
    """Feed one sample (dict of [...] arrays); returns (new state, robustness [...] of the trace so far at time 0)."""
    skel, anchors, hw, hp = self._plan()
    missing = [n for n in self.signals if n not in signals_t]
    if missing:
      raise UnknownSignalError(f"online monitor: missing signal(s) {', '.join(map(repr, missing))}")
    bs = state.t.shape
    t = state.t
    x = {n: jnp.broadcast_to(jnp.asarray(signals_t[n]), bs)
         for n in self.signals}
    window = {n: _ring_write(b, t % (hw + 1), x[n].astype(b.dtype)) for n, b in state.window.items()}
    prefix = {n: jnp.where(jnp.arange(hp + 1) == t[..., None], x[n][..., None].astype(b.dtype), b)
              for n, b in state.prefix.items()}
    vals, new_acc = [], []
    for (kind, f, h), acc in zip(anchors, state.acc):
      if kind == "B":
        buf = {n: b[..., :h + 1] for n, b in prefix.items()}
        valid = jnp.arange(h + 1) <= t[..., None]
        vals.append(evaluate(f, buf, valid)[..., 0])
        new_acc.append(())
        continue
      # The window's h + 1 positions as separate [...] arrays (stl/columns.py: the array form's cumulative min / max
      # are O(h^2) reduce-windows on the GPU); position k holds time t - h + k (ring slot (t - h + k) mod (hw + 1)),
      # valid once t - h + k >= 0.
      slots = (t[..., None] - h + jnp.arange(h + 1)) % (hw + 1)
      buf = {n: jnp.take_along_axis(b, slots, axis=-1) for n, b in window.items()}
      valid = [t >= h - k for k in range(h + 1)]
      if kind in ("G", "F"):
        op, fill = (jnp.minimum, jnp.inf) if kind == "G" else (jnp.maximum, -jnp.inf)
        v = [jnp.where(ok, x, fill) for ok, x in zip(valid, columns.evaluate_columns(f.arg, buf))]
        red = v[0]
        for x in v[1:]:
          red = op(red, x)
        vals.append(op(acc[0], red))
        new_acc.append((op(acc[0], v[0]),))
      else:  # unbounded until: max over open positions j of min(r[j], l before j (finalised and open))
        m_fin, best_fin = acc
        lv = [jnp.where(ok, x, jnp.inf) for ok, x in zip(valid, columns.evaluate_columns(f.left, buf))]
        rv = [jnp.where(ok, x, -jnp.inf) for ok, x in zip(valid, columns.evaluate_columns(f.right, buf))]
        cm_excl, best = m_fin, jnp.minimum(rv[0], m_fin)
        for k in range(1, h + 1):
          cm_excl = jnp.minimum(cm_excl, lv[k - 1])
          best = jnp.maximum(best, jnp.minimum(rv[k], cm_excl))
        vals.append(jnp.maximum(best_fin, best))
        new_acc.append((jnp.minimum(m_fin, lv[0]), jnp.maximum(best_fin, jnp.minimum(rv[0], m_fin))))
    out = _combine(skel, vals)
    return MonitorState(t + 1, window, prefix, tuple(new_acc)), out

  def settled(self, state: MonitorState, so_far: jnp.ndarray) -> jnp.ndarray:
    """Robustness [...] over the positions of the trace whose windows have closed, for `always(psi)` with psi
    bounded: the running minimum of psi's finalised values (state: after `update`), which no later sample can raise
    (+inf before the first position closes). The trace-so-far value (`so_far`, what `update` returned) can dip below
    0 while a window of psi is still open and rise again once it closes (always(eventually[0, 3 s] ...) during a slow
    stretch shorter than 3 s), so it cannot say when a violation has become certain; this can. Any other formula:
    `so_far`."""
    skel, anchors, _, _ = self._plan()
    if skel == 0 and anchors[0][0] == "G":
      return state.acc[0][0]
    return so_far


def _ring_write(b, slot, x):
  """b [..., W] with b[..., slot] = x (slot, x [...]): an indexed write XLA does in place."""
  if b.ndim == 1:
    return b.at[slot].set(x)
  return jnp.put_along_axis(b, slot[..., None], x[..., None], axis=-1, inplace=False)


def _combine(skel, vals):
  if isinstance(skel, int):
    return vals[skel]
  if skel[0] == "not":
    return -_combine(skel[1], vals)
  a, b = _combine(skel[1], vals), _combine(skel[2], vals)
  if skel[0] == "and":
    return jnp.minimum(a, b)
  if skel[0] == "or":
    return jnp.maximum(a, b)
  return jnp.maximum(-a, b)  # implies


def monitor_init(formula: Union[str, ast.Formula], batch_shape: Sequence[int] = (), dt: Optional[float] = None,
                 dtype=jnp.float32, params=None) -> MonitorState:
  """Functional form of `OnlineMonitor.create(formula, dt).init(batch_shape)`."""
  return OnlineMonitor.create(formula, dt, params).init(batch_shape, dtype)


def monitor_update(formula: Union[str, ast.Formula], state: MonitorState, signals_t: Mapping[str, jnp.ndarray],
                   dt: Optional[float] = None, params=None) -> Tuple[MonitorState, jnp.ndarray]:
  """Functional form of `OnlineMonitor.create(formula, dt).update(state, signals_t)`."""
  return OnlineMonitor.create(formula, dt, params).update(state, signals_t)
