"""Exact analytic distance queries for obstacles, geofences and mission paths (pure JAX, jittable, vmappable).

All functions take ONE query point (world ENU frame, metres) and return a scalar; vmap them for batches. Shapes
stand on the ground plane z = 0 and are convex, so every signed distance here is a convex function of the point
(used by `min_dist_segment_sdf`).

Shape encodings (shared with `envs.worlds`):
  cylinder [4] = (x, y, radius, height): vertical cylinder from z = 0 to z = height.
  box      [6] = (cx, cy, half_x, half_y, yaw, height): rectangle footprint rotated by yaw (rad, CCW from +x),
                 extruded from z = 0 to z = height.
  rect     [4] = (xmin, xmax, ymin, ymax): axis-aligned rectangle in the xy plane.
Signed distances are negative inside the shape, positive outside, and exact (Euclidean), not bounds.
Norms use a double-`where` so gradients are finite everywhere (also at the surface / on a segment).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

FAR = 1e3
"""Distance returned for masked-out (absent) entries, m."""


def safe_norm(v: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
  """Euclidean norm along `axis`, exact, with a finite (zero) gradient at v = 0."""
  return _safe_sqrt(jnp.sum(v * v, axis=axis))


def _safe_sqrt(sq: jnp.ndarray) -> jnp.ndarray:
  """sqrt(sq) of a sum of squares sq >= 0, with a finite (zero) gradient at 0 (the double `where`)."""
  pos = sq > 0.0
  return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def closest_point_segment(p: jnp.ndarray, a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
  """Closest point to p [3] on the segment a [3] -> b [3] (degenerate a == b allowed). Returns [3]."""
  ab = b - a
  den = jnp.dot(ab, ab)
  t = jnp.where(den > 0.0, jnp.dot(p - a, ab) / jnp.where(den > 0.0, den, 1.0), 0.0)
  t = jnp.clip(t, 0.0, 1.0)
  return a + t * ab


def dist_point_segment(p: jnp.ndarray, a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
  """Euclidean distance from p [3] (or [2]) to the segment a -> b, m. Returns []."""
  return safe_norm(p - closest_point_segment(p, a, b))


def _safe_hypot(*xs: jnp.ndarray) -> jnp.ndarray:
  """sqrt(x0^2 + x1^2 + ...) of a few same-shaped components, with a finite (zero) gradient at 0: `safe_norm` of the
  stacked components, written on the components so that under vmap it is elementwise work over the batch (XLA fuses
  it into its neighbours) instead of a stack and a reduction over a tiny axis (a kernel of its own on a GPU)."""
  return _safe_sqrt(sum(x * x for x in xs))


def sdf_cylinder(p: jnp.ndarray, cyl: jnp.ndarray) -> jnp.ndarray:
  """Signed distance from p [3] to the vertical cylinder cyl [4] = (x, y, radius, height) standing on z = 0, m."""
  d_r = _safe_hypot(p[0] - cyl[0], p[1] - cyl[1]) - cyl[2]
  half_h = 0.5 * cyl[3]
  d_z = jnp.abs(p[2] - half_h) - half_h
  return jnp.minimum(jnp.maximum(d_r, d_z), 0.0) + _safe_hypot(jnp.maximum(d_r, 0.0), jnp.maximum(d_z, 0.0))


def prism_axes(prisms: jnp.ndarray) -> jnp.ndarray:
  """(cos yaw, sin yaw) [..., 2] of oriented prisms [..., 6] (boxes, keep-out prisms): their horizontal axes, which a
  world computes once (`worlds.World.box_axes`) for the queries that run every env step."""
  return jnp.stack([jnp.cos(prisms[..., 4]), jnp.sin(prisms[..., 4])], -1)


def _box_local_xy(p_xy: jnp.ndarray, box: jnp.ndarray, axes=None):
  """p_xy [2] expressed in the box frame (centre at the origin, axes along the box): its two coordinates [].
  axes: the box's `prism_axes` [2] if at hand, else computed from its yaw."""
  c, s = (jnp.cos(box[4]), jnp.sin(box[4])) if axes is None else (axes[0], axes[1])
  d0, d1 = p_xy[0] - box[0], p_xy[1] - box[1]
  return c * d0 + s * d1, -s * d0 + c * d1


def _sdf_orthotope(*q: jnp.ndarray) -> jnp.ndarray:
  """Signed distance to an axis-aligned box from the per-axis excesses q_k = |x_k - centre_k| - half_k []."""
  inside = q[0]
  for x in q[1:]:
    inside = jnp.maximum(inside, x)
  return jnp.minimum(inside, 0.0) + _safe_hypot(*(jnp.maximum(x, 0.0) for x in q))


def sdf_box(p: jnp.ndarray, box: jnp.ndarray, axes=None) -> jnp.ndarray:
  """Signed distance from p [3] to the oriented prism box [6] = (cx, cy, half_x, half_y, yaw, height) on z = 0, m.
  axes: optional [2] `prism_axes(box)` (else computed from the yaw)."""
  l0, l1 = _box_local_xy(p, box, axes)
  half_h = 0.5 * box[5]
  return _sdf_orthotope(jnp.abs(l0) - box[2], jnp.abs(l1) - box[3], jnp.abs(p[2] - half_h) - half_h)


def sdf_box_xy(p_xy: jnp.ndarray, box: jnp.ndarray, axes=None) -> jnp.ndarray:
  """Signed horizontal distance from p_xy [2] to the footprint of box [6] (> 0 outside the footprint), m.
  axes: optional [2] `prism_axes(box)` (else computed from the yaw)."""
  l0, l1 = _box_local_xy(p_xy, box, axes)
  return _sdf_orthotope(jnp.abs(l0) - box[2], jnp.abs(l1) - box[3])


def rect_inside_margin(p_xy: jnp.ndarray, rect: jnp.ndarray) -> jnp.ndarray:
  """Signed horizontal distance to the boundary of the axis-aligned rect [4] = (xmin, xmax, ymin, ymax).

  > 0 inside (distance to the nearest edge), < 0 outside (minus the distance to the rectangle), m. Returns [].
  """
  q0 = jnp.abs(p_xy[0] - 0.5 * (rect[0] + rect[1])) - 0.5 * (rect[1] - rect[0])
  q1 = jnp.abs(p_xy[1] - 0.5 * (rect[2] + rect[3])) - 0.5 * (rect[3] - rect[2])
  return -_sdf_orthotope(q0, q1)


def oriented_rect_inside_margin(p_xy: jnp.ndarray, centre: jnp.ndarray, half: jnp.ndarray,
                                yaw: jnp.ndarray) -> jnp.ndarray:
  """Signed horizontal distance to the boundary of an oriented rectangle (centre [2], half sizes [2], yaw []).

  > 0 inside, < 0 outside, m. Returns [].
  """
  box = jnp.concatenate([centre, half, jnp.reshape(yaw, (1,)), jnp.ones((1,))])
  return -sdf_box_xy(p_xy, box)


# Horizontal ray casts (a range sensor's beam): the distance along a unit direction d [2] from p [3] to the first
# surface; `FAR` where the beam misses. A beam starting inside a shape hits at 0. Zero direction components are
# nudged to 1e-9 so the slab tests divide without NaN.
def _nudge(d):
  return jnp.where(jnp.abs(d) < 1e-9, jnp.where(d < 0, -1e-9, 1e-9), d)


def ray_cylinder(p: jnp.ndarray, d: jnp.ndarray, cyl: jnp.ndarray) -> jnp.ndarray:
  """Range from p [3] along the horizontal unit direction d [2] to the vertical cylinder cyl [4] (a beam at height
  p[2] hits it only where 0 <= p[2] <= height), m; FAR on a miss."""
  m0, m1 = p[0] - cyl[0], p[1] - cyl[1]
  b = m0 * d[0] + m1 * d[1]
  c = m0 * m0 + m1 * m1 - cyl[2] * cyl[2]
  disc = b * b - c
  t = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
  hit = (c <= 0.0) | ((disc >= 0.0) & (b < 0.0))
  t = jnp.where(c <= 0.0, 0.0, t)
  return jnp.where(hit & (p[2] >= 0.0) & (p[2] <= cyl[3]), t, FAR)


def ray_box(p: jnp.ndarray, d: jnp.ndarray, box: jnp.ndarray, axes=None) -> jnp.ndarray:
  """Range from p [3] along the horizontal unit direction d [2] to the oriented prism box [6] (beam height within
  [0, height]), m; FAR on a miss. axes: the box's `prism_axes` [2] if at hand."""
  c, s = (jnp.cos(box[4]), jnp.sin(box[4])) if axes is None else (axes[0], axes[1])
  o0, o1 = _box_local_xy(p, box, (c, s))
  d0, d1 = _nudge(c * d[0] + s * d[1]), _nudge(-s * d[0] + c * d[1])
  ta, tb = (-box[2] - o0) / d0, (box[2] - o0) / d0
  tc, td = (-box[3] - o1) / d1, (box[3] - o1) / d1
  t_in = jnp.maximum(jnp.minimum(ta, tb), jnp.minimum(tc, td))
  t_out = jnp.minimum(jnp.maximum(ta, tb), jnp.maximum(tc, td))
  hit = (t_out >= jnp.maximum(t_in, 0.0)) & (p[2] >= 0.0) & (p[2] <= box[5])
  return jnp.where(hit, jnp.maximum(t_in, 0.0), FAR)


def ray_rect_exit(p_xy: jnp.ndarray, d: jnp.ndarray, rect: jnp.ndarray) -> jnp.ndarray:
  """Range from p_xy [2] inside the axis-aligned rect [4] = (xmin, xmax, ymin, ymax) along the unit direction d [2]
  to its edge (where the beam leaves it), m; 0 from outside."""
  d0, d1 = _nudge(d[0]), _nudge(d[1])
  tx = jnp.where(d0 > 0, (rect[1] - p_xy[0]) / d0, (rect[0] - p_xy[0]) / d0)
  ty = jnp.where(d1 > 0, (rect[3] - p_xy[1]) / d1, (rect[2] - p_xy[1]) / d1)
  inside = rect_inside_margin(p_xy, rect) >= 0.0
  return jnp.where(inside, jnp.maximum(jnp.minimum(tx, ty), 0.0), 0.0)


def masked_min(values: jnp.ndarray, mask: jnp.ndarray, empty: float = FAR) -> jnp.ndarray:
  """Minimum of values [N] over entries where mask [N] is true; `empty` (1e3) if none. Returns []."""
  return jnp.min(jnp.where(mask, values, empty), initial=empty)


def masked_argmin(values: jnp.ndarray, mask: jnp.ndarray, empty: float = FAR):
  """(min, index) of values [N] over mask [N]; (empty, 0) if nothing is valid."""
  v = jnp.where(mask, values, empty)
  i = jnp.argmin(v)
  return jnp.minimum(v[i], empty), i


def sdf_cylinders(p: jnp.ndarray, cyls: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
  """Min signed distance from p [3] to the valid cylinders cyls [N, 4] (mask [N]); 1e3 if none, m."""
  return masked_min(jax.vmap(sdf_cylinder, (None, 0))(p, cyls), mask)


def sdf_boxes(p: jnp.ndarray, boxes: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
  """Min signed distance from p [3] to the valid prisms boxes [N, 6] (mask [N]); 1e3 if none, m."""
  return masked_min(jax.vmap(sdf_box, (None, 0))(p, boxes), mask)


def dist_point_polyline(p: jnp.ndarray, points: jnp.ndarray) -> jnp.ndarray:
  """Distance from p [3] to the polyline through points [K, 3] (repeat the last point to pad), m. Returns []."""
  d = jax.vmap(dist_point_segment, (None, 0, 0))(p, points[:-1], points[1:])
  return jnp.min(d)


_INV_PHI = 0.6180339887498949


def min_sdf_on_segment(sdf, a: jnp.ndarray, b: jnp.ndarray, iters: int = 40) -> jnp.ndarray:
  """Minimum over the segment a [3] -> b [3] of a CONVEX function sdf(p [3]) -> [] (golden-section search).

  Signed distances of convex shapes are convex, so this is the exact segment-to-shape distance up to
  |b - a| * 0.618**iters (40 iterations: < 1e-6 m for a 120 m leg). Returns [].

  The two interior points m1 < m2 live in two slots (x, y) whose roles alternate: each iteration overwrites the slot
  of the point it drops with the new point, and the kept point changes role (m1 <-> m2), so x holds m1 on even
  iterations. The classic search's values exactly, without its swap (m1, m2) <- (new, m1) | (m2, new), which made XLA
  copy the loop state every iteration (bench/hlo_loops.py: 5 copies of [pool, obstacles, 4] floats per iteration in
  the reset pool's refresh).
  """
  f = lambda t: sdf(a + t * (b - a))
  c = 1.0 - _INV_PHI
  init = (jnp.zeros(()), jnp.ones(()), jnp.asarray(c), jnp.asarray(_INV_PHI), f(c), f(_INV_PHI))

  def body(i, st):  # one new evaluation per iteration
    lo, hi, x, y, fx, fy = st
    x_m1 = i % 2 == 0                # x holds m1 (y m2), else the reverse
    m1, m2 = jnp.where(x_m1, x, y), jnp.where(x_m1, y, x)
    f1, f2 = jnp.where(x_m1, fx, fy), jnp.where(x_m1, fy, fx)
    left = f1 <= f2  # minimum in [lo, m2]: m2 is dropped (new m1 = the new point, new m2 = m1), else m1 is
    lo, hi = jnp.where(left, lo, m1), jnp.where(left, m2, hi)
    new_t = jnp.where(left, hi - _INV_PHI * (hi - lo), lo + _INV_PHI * (hi - lo))
    f_new = f(new_t)
    drop_x = left != x_m1            # x holds the dropped point: m2 (left) or m1 (right)
    return (lo, hi, jnp.where(drop_x, new_t, x), jnp.where(drop_x, y, new_t), jnp.where(drop_x, f_new, fx),
            jnp.where(drop_x, fy, f_new))

  lo, hi, _, _, f1, f2 = jax.lax.fori_loop(0, iters, body, init)
  return jnp.minimum(jnp.minimum(jnp.minimum(f1, f2), f(0.5 * (lo + hi))), jnp.minimum(f(0.0), f(1.0)))


def min_sdf_on_polyline(sdf, points: jnp.ndarray, iters: int = 40) -> jnp.ndarray:
  """Minimum of a convex sdf(p [3]) over the polyline points [K, 3] (pad by repeating the last point). Returns []."""
  d = jax.vmap(lambda a, b: min_sdf_on_segment(sdf, a, b, iters))(points[:-1], points[1:])
  return jnp.min(d)


def polyline_clear(sdf, points: jnp.ndarray, threshold, k: int = 4, iters: int = 32) -> jnp.ndarray:
  """True iff a CONVEX sdf(p [3]) is >= threshold everywhere on the polyline points [K, 3] (conservative-exact).

  Cheap lower bounds sdf(midpoint) - length / 2 (sdf is 1-Lipschitz) rank the segments; the k lowest get the exact
  golden-section minimum, and the rest must be certified by their lower bound (else the answer is False, which
  only happens when more than k segments pass within reach of the shape). Returns [] bool.
  """
  a, b = points[:-1], points[1:]
  mid = 0.5 * (a + b)
  lb = jax.vmap(sdf)(mid) - 0.5 * safe_norm(b - a)
  k = min(k, lb.shape[0])
  neg_lb, idx = jax.lax.top_k(-lb, k)
  exact = jax.vmap(lambda i: min_sdf_on_segment(sdf, a[i], b[i], iters))(idx)
  rest_ok = True if k == lb.shape[0] else -jax.lax.top_k(-lb, k + 1)[0][k] >= threshold
  return jnp.all(exact >= threshold) & rest_ok
