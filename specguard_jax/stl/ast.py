"""STL formula abstract syntax tree: immutable, hashable nodes (usable as static jit arguments).

Time intervals are kept in the unit they were written in (`Interval.unit` is "steps" or "s"); `to_steps(formula, dt)`
converts every interval to control steps with an explicit step length `dt` (seconds). Only step intervals are evaluated.

Size limits, the same on every route (the parser refuses a formula beyond them, `to_steps` and `check_size` one built
in Python), so a formula that is accepted also works in the offline robustness, the online monitor and the spec tables:
  * MAX_DEPTH levels of tree: every node is one level below its parent. The engine walks formulas recursively (a few
    Python frames per level); the parser builds and / or chains as balanced trees, so a chain of n terms is only about
    log2(n) levels deep. (The text's own nesting is bounded by parser.MAX_NESTING, about 3 x MAX_DEPTH, so that
    str() of any accepted formula parses again.)
  * MAX_NODES tree nodes (predicates and operators).
  * MAX_WINDOW_STEPS control steps for every interval bound and for the span of nested windows (the summed upper
    bounds along any path of the tree, `window_span`): the online monitor keeps span + 1 samples of every signal per
    trace and unrolls one operation per sample and operator, so its program (and compile time) grows with the span.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Tuple, Union

from specguard_jax.stl.errors import FormulaSizeError, IntervalError, UnknownSignalError

MAX_DEPTH = 32
"""Deepest formula tree accepted (levels; see the module docstring)."""
MAX_NODES = 4096
"""Most tree nodes (predicates + operators) in one formula."""
MAX_WINDOW_STEPS = 1000
"""Longest interval bound and nested-window span, in control steps (100 s at the envs' 0.1 s step)."""


@dataclasses.dataclass(frozen=True)
class Interval:
  """Closed interval [lo, hi] of a temporal operator; unit "steps" (integers) or "s" (seconds)."""

  lo: float
  hi: float
  unit: str = "steps"

  def __str__(self) -> str:
    if self.unit == "steps":
      return f"[{int(self.lo)},{int(self.hi)}]"
    return f"[{_num(self.lo)}s,{_num(self.hi)}s]"


@dataclasses.dataclass(frozen=True)
class Predicate:
  """Affine predicate with robustness  sum_i coef_i * signal_i + offset  (>= 0 means satisfied).

  `x > c` and `x >= c` both give x - c; `x < c` and `x <= c` both give c - x (rtamt's discrete-time semantics).
  `text` is the source form, kept for printing.
  """

  terms: Tuple[Tuple[str, float], ...]
  offset: float
  text: str = dataclasses.field(default="", compare=False)

  def __str__(self) -> str:
    if self.text:
      return f"({self.text})"
    lhs = " + ".join(f"({_num(c)}*{n})" for n, c in self.terms) or "0"
    return f"({lhs} > {_num(-self.offset)})"


@dataclasses.dataclass(frozen=True)
class Not:
  arg: "Formula"

  def __str__(self) -> str:
    return f"(not {self.arg})"


@dataclasses.dataclass(frozen=True)
class And:
  left: "Formula"
  right: "Formula"

  def __str__(self) -> str:
    return f"({self.left} and {self.right})"


@dataclasses.dataclass(frozen=True)
class Or:
  left: "Formula"
  right: "Formula"

  def __str__(self) -> str:
    return f"({self.left} or {self.right})"


@dataclasses.dataclass(frozen=True)
class Implies:
  left: "Formula"
  right: "Formula"

  def __str__(self) -> str:
    return f"({self.left} -> {self.right})"


@dataclasses.dataclass(frozen=True)
class Always:
  """G_I(arg); `interval=None` is the unbounded always (to the end of the trace)."""

  arg: "Formula"
  interval: Optional[Interval] = None

  def __str__(self) -> str:
    return f"(always{self.interval or ''}({self.arg}))"


@dataclasses.dataclass(frozen=True)
class Eventually:
  """F_I(arg); `interval=None` is the unbounded eventually."""

  arg: "Formula"
  interval: Optional[Interval] = None

  def __str__(self) -> str:
    return f"(eventually{self.interval or ''}({self.arg}))"


@dataclasses.dataclass(frozen=True)
class Until:
  """left U_I right; `interval=None` is the unbounded until."""

  left: "Formula"
  right: "Formula"
  interval: Optional[Interval] = None

  def __str__(self) -> str:
    return f"({self.left} until{self.interval or ''} {self.right})"


Formula = Union[Predicate, Not, And, Or, Implies, Always, Eventually, Until]
TEMPORAL = (Always, Eventually, Until)


def _num(v: float) -> str:
  return repr(int(v)) if float(v).is_integer() else repr(float(v))


def children(f: Formula) -> Tuple[Formula, ...]:
  """Direct sub-formulas of `f`."""
  if isinstance(f, Predicate):
    return ()
  if isinstance(f, (Not, Always, Eventually)):
    return (f.arg,)
  return (f.left, f.right)


def signals_of(f: Formula) -> Tuple[str, ...]:
  """Sorted names of the signals `f` reads."""
  out = set()

  def walk(g):
    if isinstance(g, Predicate):
      out.update(n for n, _ in g.terms)
    for c in children(g):
      walk(c)

  walk(f)
  return tuple(sorted(out))


def check_signals(f: Formula, allowed) -> None:
  """Raise UnknownSignalError if `f` reads a signal not in `allowed`."""
  allowed = set(allowed)
  bad = [s for s in signals_of(f) if s not in allowed]
  if bad:
    raise UnknownSignalError(f"unknown signal(s) {', '.join(map(repr, bad))} in formula {f} "
                             f"(known: {', '.join(sorted(allowed))})")


def has_seconds(f: Formula) -> bool:
  """True when some interval of `f` is written in seconds (needs a dt to evaluate)."""
  iv = getattr(f, "interval", None)
  if iv is not None and iv.unit != "steps":
    return True
  return any(has_seconds(c) for c in children(f))


def _steps(v: float, dt: float, what: str) -> int:
  n = v / dt
  r = round(n)
  if abs(n - r) > 1e-6 * max(1.0, abs(n)):
    raise IntervalError(f"interval bound {what}={v} s is not a multiple of dt={dt} s")
  return int(r)


def monitor_bytes(samples: float) -> str:
  """Readable size of `samples` float32 values (the online monitor's buffer of one signal for one trace)."""
  size = 4.0 * samples
  for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
    if size < 1000 or unit == "PB":
      return f"{size:.3g} {unit}"
    size /= 1000
  return ""


def window_error(what: str, steps: float, dt: Optional[float] = None) -> IntervalError:
  """The error for a window of `steps` control steps above MAX_WINDOW_STEPS (`what` names it; dt in s if known)."""
  at_dt = f" at dt={dt:g} s" if dt is not None else ""
  return IntervalError(f"{what}: a window of {steps:,.0f} steps{at_dt}; the online monitor would keep {steps + 1:,.0f} "
                       f"samples per signal and trace ({monitor_bytes(steps + 1)} in float32) and unroll as many "
                       f"operations; the maximum is {MAX_WINDOW_STEPS} steps")


def check_size(f: Formula) -> Formula:
  """Raise FormulaSizeError if `f` is deeper than MAX_DEPTH or has more than MAX_NODES nodes; returns `f`.
  Walks the tree with an explicit stack (no recursion), stopping at the first limit crossed."""
  stack, nodes = [(f, 1)], 0
  while stack:
    g, depth = stack.pop()
    nodes += 1
    if depth > MAX_DEPTH:
      raise FormulaSizeError(f"formula nests more than {MAX_DEPTH} levels deep (the maximum)")
    if nodes > MAX_NODES:
      raise FormulaSizeError(f"formula has more than {MAX_NODES} nodes (predicates and operators; the maximum)")
    stack.extend((c, depth + 1) for c in children(g))
  return f


def window_span(f: Formula) -> int:
  """Longest chain of nested windows in steps: the summed interval upper bounds along the worst root-to-leaf path
  (unbounded operators add 0). The online monitor buffers window_span(f) + 1 samples per signal."""
  own = int(f.interval.hi) if getattr(f, "interval", None) is not None else 0
  return own + max((window_span(c) for c in children(f)), default=0)


def to_steps(f: Formula, dt: Optional[float] = None) -> Formula:
  """Return `f` with every interval in control steps (`dt`: seconds per step, needed only for "s" intervals).

  Raises FormulaSizeError / IntervalError when `f` is beyond the module's size limits (an interval bound or the nested
  windows' span above MAX_WINDOW_STEPS steps, once converted)."""
  out = _to_steps(check_size(f), dt)
  span = window_span(out)
  if span > MAX_WINDOW_STEPS:
    text = str(f)
    raise window_error(f"the nested windows of {text if len(text) <= 80 else text[:77] + '...'}", span, dt)
  return out


def _to_steps(f: Formula, dt: Optional[float]) -> Formula:
  if isinstance(f, Predicate):
    return f
  iv = getattr(f, "interval", None)
  if iv is not None and iv.unit != "steps":
    if dt is None or not (dt > 0 and math.isfinite(dt)):
      raise IntervalError(f"formula {f} has intervals in seconds: pass a positive dt (seconds per step)")
    if not iv.hi / dt <= MAX_WINDOW_STEPS:
      raise window_error(f"interval {iv} of {type(f).__name__.lower()}", iv.hi / dt, dt)
    iv = Interval(_steps(iv.lo, dt, "lo"), _steps(iv.hi, dt, "hi"), "steps")
  elif iv is not None and not iv.hi <= MAX_WINDOW_STEPS:
    raise window_error(f"interval {iv} of {type(f).__name__.lower()}", iv.hi, dt)
  kids = tuple(_to_steps(c, dt) for c in children(f))
  if isinstance(f, (Not,)):
    return Not(kids[0])
  if isinstance(f, (Always, Eventually)):
    return type(f)(kids[0], iv)
  if isinstance(f, Until):
    return Until(kids[0], kids[1], iv)
  return type(f)(*kids)


def is_temporal(f: Formula) -> bool:
  """True when `f` contains a temporal operator."""
  return isinstance(f, TEMPORAL) or any(is_temporal(c) for c in children(f))


def horizon(f: Formula) -> float:
  """Future horizon in steps (how far past t the value at t looks); math.inf if f has an unbounded operator."""
  if isinstance(f, Predicate):
    return 0
  hs = [horizon(c) for c in children(f)]
  if isinstance(f, TEMPORAL):
    if f.interval is None:
      return math.inf
    if f.interval.unit != "steps":
      raise IntervalError("horizon() needs step intervals: call to_steps(formula, dt) first")
    return int(f.interval.hi) + max(hs)
  return max(hs)
