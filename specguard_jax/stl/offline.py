"""Offline (whole-trace) quantitative STL semantics, equal to rtamt's discrete-time offline semantics.

`robustness(formula, signals)[..., i]` is the robustness at every time index i of traces given as a dict of
[..., T] arrays (any leading batch axes, broadcast against each other). Windows look forward and are truncated at the
trace end (an empty window gives +inf for always, -inf for eventually / until). Optional `length` ([...] ints) treats
each trace as ending at its own length (ragged episodes): samples at index >= length are ignored.
"""

from __future__ import annotations

from typing import Mapping, Optional, Union

import jax.numpy as jnp

from specguard_jax.stl import ast, windows
from specguard_jax.stl.errors import STLError, UnknownSignalError
from specguard_jax.stl.parser import parse


def as_formula(formula: Union[str, ast.Formula], dt: Optional[float] = None, params=None) -> ast.Formula:
  """Parse text if needed and convert every interval to control steps (dt: seconds per step)."""
  if isinstance(formula, str):
    formula = parse(formula, params=params)
  if not isinstance(formula, (ast.Predicate, ast.Not, ast.And, ast.Or, ast.Implies) + ast.TEMPORAL):
    raise STLError(f"expected STL text or a Formula, got {type(formula).__name__}")
  return ast.to_steps(formula, dt)


def stack_signals(formula: ast.Formula, signals: Mapping[str, jnp.ndarray]):
  """Return {name: [..., T] float array} for the signals `formula` reads, broadcast to one shape."""
  names = ast.signals_of(formula)
  missing = [n for n in names if n not in signals]
  if missing:
    raise UnknownSignalError(f"formula reads signal(s) {', '.join(map(repr, missing))} not in the given signals "
                             f"({', '.join(sorted(signals)) or 'none'})")
  arrs = [jnp.asarray(signals[n]) for n in names]
  arrs = [a if jnp.issubdtype(a.dtype, jnp.floating) else a.astype(jnp.float32) for a in arrs]
  if any(a.ndim == 0 for a in arrs):
    raise STLError("signals must have a time axis: shape [..., T]")
  shape = jnp.broadcast_shapes(*[a.shape for a in arrs])
  dtype = jnp.result_type(*arrs)
  return {n: jnp.broadcast_to(a, shape).astype(dtype) for n, a in zip(names, arrs)}


def predicate_value(p: ast.Predicate, sig: Mapping[str, jnp.ndarray]) -> jnp.ndarray:
  """Robustness of an affine predicate, elementwise."""
  acc = None
  for name, coef in p.terms:
    term = sig[name] if coef == 1.0 else sig[name] * coef
    acc = term if acc is None else acc + term
  return acc + p.offset if p.offset != 0.0 else acc


def evaluate(f: ast.Formula, sig: Mapping[str, jnp.ndarray], valid: Optional[jnp.ndarray] = None) -> jnp.ndarray:
  """Robustness of a step-interval formula at every index; `valid` ([..., T] bool) marks the samples in the trace."""
  ev = lambda g: evaluate(g, sig, valid)
  mask = (lambda x, fill: x) if valid is None else (lambda x, fill: jnp.where(valid, x, fill))
  if isinstance(f, ast.Predicate):
    return predicate_value(f, sig)
  if isinstance(f, ast.Not):
    return -ev(f.arg)
  if isinstance(f, ast.And):
    return jnp.minimum(ev(f.left), ev(f.right))
  if isinstance(f, ast.Or):
    return jnp.maximum(ev(f.left), ev(f.right))
  if isinstance(f, ast.Implies):
    return jnp.maximum(-ev(f.left), ev(f.right))
  if isinstance(f, (ast.Always, ast.Eventually)):
    op, fill = (jnp.minimum, jnp.inf) if isinstance(f, ast.Always) else (jnp.maximum, -jnp.inf)
    x = mask(ev(f.arg), fill)
    if f.interval is None:
      return windows.suffix_reduce(x, op)
    return windows.window_reduce(x, f.interval.lo, f.interval.hi, op)
  if isinstance(f, ast.Until):
    l = mask(ev(f.left), jnp.inf)
    r = mask(ev(f.right), -jnp.inf)
    if f.interval is None:
      return windows.until_unbounded(l, r)
    return windows.until_bounded(l, r, f.interval.lo, f.interval.hi)
  raise STLError(f"unknown formula node {type(f).__name__}")


def robustness(formula: Union[str, ast.Formula], signals: Mapping[str, jnp.ndarray], dt: Optional[float] = None,
               length: Optional[jnp.ndarray] = None, params=None) -> jnp.ndarray:
  """Robustness [..., T] of `formula` (text or Formula) over `signals` (dict of [..., T] arrays) at every index.

  dt: seconds per step, needed only when intervals are written in seconds.  length: optional [...] int episode
  lengths (samples at index >= length are outside the trace; outputs there are meaningless).  params: constants
  substituted when `formula` is text.  Jittable (formula static), vmappable, differentiable where min/max are.
  """
  f, sig, valid = _prepare(formula, signals, dt, length, params)
  out = evaluate(f, sig, valid)
  if valid is not None:
    out = jnp.broadcast_to(out, jnp.broadcast_shapes(out.shape, valid.shape))
  return out


def _prepare(formula, signals, dt, length, params):
  """(Formula, stacked signals, validity mask [..., T] or None) shared by the offline entry points."""
  f = as_formula(formula, dt, params)
  sig = stack_signals(f, signals)
  valid = None
  if length is not None:
    t = next(iter(sig.values())).shape[-1]
    valid = jnp.arange(t) < jnp.asarray(length)[..., None]
  return f, sig, valid


def evaluate_at0(f: ast.Formula, sig: Mapping[str, jnp.ndarray], valid: Optional[jnp.ndarray] = None) -> jnp.ndarray:
  """Robustness at index 0 only ([...]): top-level always/eventually become plain reductions instead of scans."""
  if isinstance(f, ast.Predicate):
    return predicate_value(f, {n: v[..., 0] for n, v in sig.items()})
  if isinstance(f, ast.Not):
    return -evaluate_at0(f.arg, sig, valid)
  if isinstance(f, (ast.And, ast.Or, ast.Implies)):
    a, b = evaluate_at0(f.left, sig, valid), evaluate_at0(f.right, sig, valid)
    if isinstance(f, ast.And):
      return jnp.minimum(a, b)
    return jnp.maximum(a, b) if isinstance(f, ast.Or) else jnp.maximum(-a, b)
  if isinstance(f, (ast.Always, ast.Eventually)):
    red, fill = (jnp.min, jnp.inf) if isinstance(f, ast.Always) else (jnp.max, -jnp.inf)
    x = evaluate(f.arg, sig, valid)
    if valid is not None:
      x = jnp.where(valid, x, fill)
    if f.interval is not None:
      lo, hi = int(f.interval.lo), int(f.interval.hi)
      x = x[..., lo:hi + 1]
      if x.shape[-1] == 0:
        return jnp.full(x.shape[:-1], fill, x.dtype)
    return red(x, axis=-1)
  return evaluate(f, sig, valid)[..., 0]


def episode_robustness(formula: Union[str, ast.Formula], signals: Mapping[str, jnp.ndarray],
                       dt: Optional[float] = None, length: Optional[jnp.ndarray] = None, params=None) -> jnp.ndarray:
  """Robustness of whole episodes at time 0, [...]: equals robustness(...)[..., 0], computed with reductions where
  possible (top-level always/eventually), so it is cheaper than the every-index form."""
  f, sig, valid = _prepare(formula, signals, dt, length, params)
  out = evaluate_at0(f, sig, valid)
  if valid is not None:
    out = jnp.broadcast_to(out, jnp.broadcast_shapes(out.shape, valid.shape[:-1]))
  return out
