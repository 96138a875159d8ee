"""Robustness of a bounded formula at every position of a short buffer, one array per position (the online monitor's
window form of `offline.evaluate`).

`offline.evaluate` works on [..., T] arrays: its windows are shifts and cumulative min / max along the last axis, which
jax lowers to reduce-windows (`lax.cummax` / `lax.cummin` on every backend in jax 0.10-0.11). XLA fuses those into a
kernel whose every output position re-reads its whole window, O(T^2) strided loads per trace: the kernel holding them
(the specs' robustness stack) is a sizeable share of a GPU env step with the monitor's 31-sample windows
(docs/PERFORMANCE.md). Here the
temporal-free parts of the formula stay [..., T] arrays (one op per node) and, from a window operator up, every node
is a list of T arrays [...] (positions oldest first): suffix chains, van Herk / Gil-Werman blocks for the windows, the
until recurrence, O(T) arrays per operator, each elementwise over the batch, which XLA fuses into one pass per trace.
(Splitting the predicates per position too makes a program about twice the size, compiling more than twice as long
on the CPU and longer on the GPU, for a step only slightly quicker; this form is a little quicker per drone env step
than the array form, as quick on the rover, and compiles no slower.) The values are those of `offline.evaluate`: the
same min / max / affine arithmetic per position (tests/test_stl_online.py).
"""

from __future__ import annotations

from typing import List, Mapping

import jax.numpy as jnp

from specguard_jax.stl import ast
from specguard_jax.stl.errors import STLError
from specguard_jax.stl.offline import predicate_value
from specguard_jax.stl.windows import _identity

Columns = List[jnp.ndarray]


def split_columns(x: jnp.ndarray) -> Columns:
  """[..., T] -> T arrays [...] (position k = x[..., k])."""
  return [x[..., k] for k in range(x.shape[-1])]


def _fill_like(x: Columns, value: float) -> jnp.ndarray:
  return jnp.full_like(x[0], value)


def window_columns(x: Columns, a: int, b: int, op) -> Columns:
  """out[k] = op(x[k + a .. k + b]) truncated at the buffer's end (op's identity where empty); op jnp.minimum /
  jnp.maximum. Van Herk / Gil-Werman: blocks of w = b - a + 1 positions, each position's op to its block's end (a
  suffix chain) and from its block's start (a prefix chain); a window is one suffix and at most one prefix."""
  t = len(x)
  y = x[a:]                       # y[k] = x[k + a]; positions k >= len(y) have an empty window
  n, w = len(y), b - a + 1
  if n == 0:
    return [_fill_like(x, _identity(op))] * t
  suf, pre = [None] * n, [None] * n
  for start in range(0, n, w):
    end = min(start + w, n) - 1
    suf[end] = y[end]
    for k in range(end - 1, start - 1, -1):
      suf[k] = op(y[k], suf[k + 1])
    if start > 0:   # a window ends in this block only if it starts in the one before
      pre[start] = y[start]
      for k in range(start + 1, end + 1):
        pre[k] = op(pre[k - 1], y[k])
  out = []
  for k in range(n):
    e = min(k + w - 1, n - 1)     # the window's last position (truncated)
    out.append(suf[k] if e // w == k // w else op(suf[k], pre[e]))
  return out + [_fill_like(x, _identity(op))] * (t - n)


def _until_unbounded(l: Columns, r: Columns) -> Columns:
  """out[k] = max_{j >= k} min(r[j], min_{k <= i < j} l[i]): out[k] = max(r[k], min(l[k], out[k + 1]))."""
  out = [None] * len(l)
  out[-1] = r[-1]
  for k in range(len(l) - 2, -1, -1):
    out[k] = jnp.maximum(r[k], jnp.minimum(l[k], out[k + 1]))
  return out


def _shift(x: Columns, s: int, fill: float) -> Columns:
  """y[k] = x[k + s] (fill past the end)."""
  return x[s:] + [_fill_like(x, fill)] * min(s, len(x))


def as_columns(x) -> Columns:
  """An operand as columns: a [..., T] array split by position, a list as it is."""
  return x if isinstance(x, list) else split_columns(x)


def _elementwise(op, a, b):
  """op on two operands: one [..., T] array op if both are arrays (temporal-free so far), else per position."""
  if not isinstance(a, list) and not isinstance(b, list):
    return op(a, b)
  return [op(u, v) for u, v in zip(as_columns(a), as_columns(b))]


def _evaluate(f: ast.Formula, sig: Mapping[str, jnp.ndarray]):
  """`offline.evaluate(f, sig)` (no validity mask) as a [..., T] array while f's sub-formula is temporal-free (one
  op per node), as T per-position arrays from its first window operator up."""
  ev = lambda g: _evaluate(g, sig)   # noqa: E731
  if isinstance(f, ast.Predicate):
    return predicate_value(f, sig)
  if isinstance(f, ast.Not):
    x = ev(f.arg)
    return [-v for v in x] if isinstance(x, list) else -x
  if isinstance(f, ast.And):
    return _elementwise(jnp.minimum, ev(f.left), ev(f.right))
  if isinstance(f, ast.Or):
    return _elementwise(jnp.maximum, ev(f.left), ev(f.right))
  if isinstance(f, ast.Implies):
    return _elementwise(lambda u, v: jnp.maximum(-u, v), ev(f.left), ev(f.right))
  if isinstance(f, (ast.Always, ast.Eventually)):
    op = jnp.minimum if isinstance(f, ast.Always) else jnp.maximum
    x = as_columns(ev(f.arg))
    if f.interval is None:
      return window_columns(x, 0, len(x) - 1, op)
    return window_columns(x, int(f.interval.lo), int(f.interval.hi), op)
  if isinstance(f, ast.Until):
    l, r = as_columns(ev(f.left)), as_columns(ev(f.right))
    if f.interval is None:
      return _until_unbounded(l, r)
    # offline.until_bounded's identity: G[0,a-1] l and shift_a((l U r) and F[0,b-a] r)
    a, b = int(f.interval.lo), int(f.interval.hi)
    inner = [jnp.minimum(u, v) for u, v in zip(_until_unbounded(l, r), window_columns(r, 0, b - a, jnp.maximum))]
    out = _shift(inner, a, -jnp.inf)
    if a > 0:
      out = [jnp.minimum(u, v) for u, v in zip(out, window_columns(l, 0, a - 1, jnp.minimum))]
    return out
  raise STLError(f"unknown formula node {type(f).__name__}")


def evaluate_columns(f: ast.Formula, sig: Mapping[str, jnp.ndarray]) -> Columns:
  """`offline.evaluate(f, sig)` (no validity mask) as T arrays [...], position k = its [..., k]; sig: {name: [..., T]}
  of equal shapes. The temporal-free parts stay one [..., T] op per node (a small program); from a window operator up
  every node is one op per position."""
  return as_columns(_evaluate(f, sig))
