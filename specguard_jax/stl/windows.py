"""Sliding-window and until kernels over the last axis of [..., T] arrays (pure JAX, jittable, differentiable).

All windows look forward and are truncated at the trace end; an empty window yields the operator's identity
(+inf for min, -inf for max), exactly like rtamt's discrete-time offline semantics.
  * `window_reduce`: out[i] = op(x[i+a .. i+b]) in O(T log w) (sparse-table doubling) for w = b-a+1 <= 32, else O(T)
    (van Herk / Gil-Werman block prefix/suffix scans). No T x T masks.
  * `until_unbounded`: out[i] = max_{j>=i} min(r[j], min_{i<=k<j} l[k]) via an associative scan over clip functions.
  * `until_bounded`: phi U[a,b] psi = G[0,a-1] phi  and  shift_a((phi U psi) and F[0,b-a] psi)  (exact identity).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

_DOUBLING_MAX_W = 32


def _identity(op) -> float:
  return jnp.inf if op is jnp.minimum else -jnp.inf


def shift_left(x: jnp.ndarray, s: int, fill: float) -> jnp.ndarray:
  """y[..., i] = x[..., i + s] (fill where i + s >= T); s >= 0 static."""
  t = x.shape[-1]
  if s == 0:
    return x
  if s >= t:
    return jnp.full_like(x, fill)
  pad = jnp.full(x.shape[:-1] + (s,), fill, x.dtype)
  return jnp.concatenate([x[..., s:], pad], axis=-1)


def suffix_reduce(x: jnp.ndarray, op) -> jnp.ndarray:
  """out[i] = op(x[i:]) (suffix min/max)."""
  f = lax.cummin if op is jnp.minimum else lax.cummax
  return f(x, axis=x.ndim - 1, reverse=True)


def _window_doubling(y, w, op, fill):
  m, k = y, 1
  while 2 * k <= w:
    m = op(m, shift_left(m, k, fill))
    k *= 2
  return m if k == w else op(m, shift_left(m, w - k, fill))


def _window_vhgw(y, w, op, fill):
  t = y.shape[-1]
  nb = -(-(t + w - 1) // w)
  pad = jnp.full(y.shape[:-1] + (nb * w - t,), fill, y.dtype)
  blocks = jnp.concatenate([y, pad], axis=-1).reshape(y.shape[:-1] + (nb, w))
  cum = lax.cummin if op is jnp.minimum else lax.cummax
  pre = cum(blocks, axis=blocks.ndim - 1).reshape(y.shape[:-1] + (nb * w,))
  suf = cum(blocks, axis=blocks.ndim - 1, reverse=True).reshape(y.shape[:-1] + (nb * w,))
  return op(suf[..., :t], pre[..., w - 1:w - 1 + t])


def window_reduce(x: jnp.ndarray, a: int, b: int, op, method: str = "auto") -> jnp.ndarray:
  """out[..., i] = op(x[..., i+a .. i+b]) truncated at the trace end (identity if empty); op: jnp.minimum/maximum."""
  a, b = int(a), int(b)
  fill = _identity(op)
  t = x.shape[-1]
  y = shift_left(x, a, fill)
  w = b - a + 1
  if w >= t:
    return suffix_reduce(y, op)
  if w == 1:
    return y
  if method == "doubling" or (method == "auto" and w <= _DOUBLING_MAX_W):
    return _window_doubling(y, w, op, fill)
  return _window_vhgw(y, w, op, fill)


def _clip_compose(later, cur):
  """Compose clip functions: result = cur o later, each clip(z) = min(max(z, lo), hi) with lo <= hi."""
  lo_l, hi_l = later
  lo_c, hi_c = cur
  return jnp.clip(lo_l, lo_c, hi_c), jnp.clip(hi_l, lo_c, hi_c)


def until_unbounded(l: jnp.ndarray, r: jnp.ndarray) -> jnp.ndarray:
  """out[i] = max_{j >= i} min(r[j], min_{i <= k < j} l[k]) (rtamt's untimed until), O(T) work, O(log T) depth."""
  # out[i] = f_i(out[i+1]) with f_i(z) = max(r_i, min(l_i, z)) = clip(z, r_i, max(l_i, r_i)); out[T] = -inf.
  lo = r
  hi = jnp.maximum(l, r)
  lo_s, _ = lax.associative_scan(_clip_compose, (lo, hi), reverse=True, axis=l.ndim - 1)
  return lo_s  # composite applied to -inf is its lower clip bound


def until_bounded(l: jnp.ndarray, r: jnp.ndarray, a: int, b: int) -> jnp.ndarray:
  """out[i] = max_{j in [i+a, i+b], j < T} min(r[j], min_{i <= k < j} l[k]); -inf when the window is empty."""
  a, b = int(a), int(b)
  inner = jnp.minimum(until_unbounded(l, r), window_reduce(r, 0, b - a, jnp.maximum))
  out = shift_left(inner, a, -jnp.inf)
  if a > 0:
    out = jnp.minimum(out, window_reduce(l, 0, a - 1, jnp.minimum))
  return out
