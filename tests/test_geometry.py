"""Exactness of the analytic distance queries in envs.geometry on hand-made layouts."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import geometry as g

CYL = jnp.array([10.0, 5.0, 2.0, 8.0])  # x, y, radius, height
BOX = jnp.array([0.0, 0.0, 4.0, 2.0, 0.0, 6.0])  # cx, cy, hx, hy, yaw, height


@pytest.mark.parametrize("p, want", [
  ((15.0, 5.0, 4.0), 3.0),            # beside, radial
  ((10.0, 5.0, 11.0), 3.0),           # above the top face
  ((10.0, 5.0, 4.0), -2.0),           # centre, inside: nearest is the side wall (r = 2 < 4 to caps)
  ((10.0, 5.0, 7.5), -0.5),           # inside, near the top cap
  ((15.0, 5.0, 12.0), 5.0),           # above-outside the rim: 3-4-5
  ((10.0, 9.0, 0.0), 2.0),            # on the ground, beside
  ((13.0, 9.0, 8.0), 3.0),            # at top height, radial 5 - 2
])
def test_cylinder(p, want):
  assert float(g.sdf_cylinder(jnp.array(p), CYL)) == pytest.approx(want, abs=1e-5)


@pytest.mark.parametrize("p, want", [
  ((7.0, 0.0, 3.0), 3.0),             # beside +x face
  ((0.0, -5.0, 3.0), 3.0),            # beside -y face
  ((0.0, 0.0, 10.0), 4.0),            # above
  ((7.0, 6.0, 3.0), 5.0),             # vertical edge corner: (3, 4)
  ((7.0, 4.0, 10.0), math.sqrt(9 + 4 + 16)),  # vertex corner
  ((0.0, 0.0, 3.0), -2.0),            # inside, nearest face is +-y (hy = 2)
  ((3.5, 0.0, 3.0), -0.5),            # inside near +x face
  ((0.0, 0.0, 5.9), -0.1),            # inside near the top
])
def test_box_axis_aligned(p, want):
  assert float(g.sdf_box(jnp.array(p), BOX)) == pytest.approx(want, abs=1e-5)


def test_box_rotated_matches_rotated_query():
  yaw = 0.7
  box = BOX.at[0].set(3.0).at[1].set(-2.0).at[4].set(yaw)
  rng = np.random.default_rng(0)
  c, s = math.cos(yaw), math.sin(yaw)
  for _ in range(50):
    q = rng.uniform(-10, 10, 3)  # point in the box frame
    p = np.array([3.0 + c * q[0] - s * q[1], -2.0 + s * q[0] + c * q[1], q[2]])
    want = float(g.sdf_box(jnp.array(q, dtype=jnp.float32), BOX))
    assert float(g.sdf_box(jnp.array(p, dtype=jnp.float32), box)) == pytest.approx(want, abs=1e-4)
  # footprint corner of a 45-degree rotated square: (hx, 0) rotated -> on the surface
  sq = jnp.array([0.0, 0.0, 1.0, 1.0, math.pi / 4, 5.0])
  assert float(g.sdf_box_xy(jnp.array([math.sqrt(2.0) + 1.0, 0.0]), sq)) == pytest.approx(1.0, abs=1e-5)


def test_segment():
  a, b = jnp.array([0.0, 0.0, 0.0]), jnp.array([10.0, 0.0, 0.0])
  assert float(g.dist_point_segment(jnp.array([5.0, 3.0, 4.0]), a, b)) == pytest.approx(5.0)
  assert float(g.dist_point_segment(jnp.array([-3.0, 4.0, 0.0]), a, b)) == pytest.approx(5.0)
  assert float(g.dist_point_segment(jnp.array([13.0, 0.0, 4.0]), a, b)) == pytest.approx(5.0)
  assert float(g.dist_point_segment(jnp.array([1.0, 1.0, 1.0]), a, a)) == pytest.approx(math.sqrt(3.0))
  # gradients are finite on the segment itself and for degenerate segments
  gr = jax.grad(lambda p: g.dist_point_segment(p, a, b))(jnp.array([5.0, 0.0, 0.0]))
  assert np.all(np.isfinite(gr))
  gr = jax.grad(lambda p: g.dist_point_segment(p, a, a))(a)
  assert np.all(np.isfinite(gr))


def test_rect_margin():
  rect = jnp.array([-10.0, 20.0, 0.0, 10.0])
  assert float(g.rect_inside_margin(jnp.array([0.0, 5.0]), rect)) == pytest.approx(5.0)
  assert float(g.rect_inside_margin(jnp.array([18.0, 5.0]), rect)) == pytest.approx(2.0)
  assert float(g.rect_inside_margin(jnp.array([25.0, 5.0]), rect)) == pytest.approx(-5.0)
  assert float(g.rect_inside_margin(jnp.array([23.0, 14.0]), rect)) == pytest.approx(-5.0)  # outside corner
  assert float(g.rect_inside_margin(jnp.array([20.0, 10.0]), rect)) == pytest.approx(0.0)
  # oriented rectangle: 2 x 1 half sizes, rotated 90 degrees
  m = g.oriented_rect_inside_margin(jnp.array([0.0, 1.5]), jnp.zeros(2), jnp.array([2.0, 1.0]), jnp.array(math.pi / 2))
  assert float(m) == pytest.approx(0.5, abs=1e-5)
  m = g.oriented_rect_inside_margin(jnp.array([4.0, 0.0]), jnp.zeros(2), jnp.array([2.0, 1.0]), jnp.array(math.pi / 2))
  assert float(m) == pytest.approx(-3.0, abs=1e-5)


def test_masked_min_and_batches():
  cyls = jnp.stack([CYL, CYL.at[0].set(100.0), jnp.zeros(4)])
  mask = jnp.array([False, True, False])
  p = jnp.array([15.0, 5.0, 4.0])
  assert float(g.sdf_cylinders(p, cyls, mask)) == pytest.approx(83.0, abs=1e-4)
  assert float(g.sdf_cylinders(p, cyls, jnp.zeros(3, bool))) == g.FAR
  assert float(g.masked_min(jnp.zeros((0,)), jnp.zeros((0,), bool))) == g.FAR
  ps = jnp.tile(p, (7, 1))
  out = jax.jit(jax.vmap(g.sdf_boxes, (0, None, None)))(ps, jnp.stack([BOX]), jnp.array([True]))
  assert out.shape == (7,)
  assert float(out[0]) == pytest.approx(float(g.sdf_box(p, BOX)))


def test_min_sdf_on_segment_matches_dense_sampling():
  rng = np.random.default_rng(1)
  for _ in range(20):
    a = jnp.array(rng.uniform(-30, 30, 3), dtype=jnp.float32)
    b = jnp.array(rng.uniform(-30, 30, 3), dtype=jnp.float32)
    box = jnp.array([*rng.uniform(-10, 10, 2), *rng.uniform(1, 8, 2), rng.uniform(-3, 3), rng.uniform(2, 20)],
                    dtype=jnp.float32)
    f = lambda p: g.sdf_box(p, box)
    got = float(g.min_sdf_on_segment(f, a, b))
    ts = jnp.linspace(0.0, 1.0, 20001)
    dense = float(jnp.min(jax.vmap(lambda t: f(a + t * (b - a)))(ts)))
    assert got <= dense + 1e-4
    assert got >= dense - 5e-3  # dense grid spacing bound


def _golden_reference(f, iters):
  """The classic golden-section search in float64 (interior points m1 < m2 swapped each iteration), returning what
  min_sdf_on_segment returns: min(f(m1), f(m2), f(mid of the last interval), f(0), f(1))."""
  phi = 0.6180339887498949
  lo, hi, m1, m2 = 0.0, 1.0, 1.0 - phi, phi
  f1, f2 = f(m1), f(m2)
  for _ in range(iters):
    if f1 <= f2:
      hi = m2
      m1, m2, f2 = hi - phi * (hi - lo), m1, f1
      f1 = f(m1)
    else:
      lo = m1
      m1, m2, f1 = m2, lo + phi * (hi - lo), f2
      f2 = f(m2)
  return min(f1, f2, f(0.5 * (lo + hi)), f(0.0), f(1.0))


def test_min_sdf_on_segment_takes_the_classic_golden_section_steps():
  """The slot form (no swap in the loop state) visits the classic search's points: after 1..9 iterations its result
  equals a float64 reference of the classic search (a role mix-up would drift the interval off the minimum)."""
  rng = np.random.default_rng(2)
  for _ in range(10):
    c, w = rng.uniform(-0.3, 1.3), rng.uniform(0.5, 3.0)
    for iters in range(1, 10):
      got = float(g.min_sdf_on_segment(lambda p: w * jnp.abs(p[0] - c) + p[1], jnp.zeros(3, jnp.float32),
                                       jnp.array([1.0, 0.0, 0.0], jnp.float32), iters))
      want = _golden_reference(lambda t: w * abs(t - c), iters)
      assert abs(got - want) <= 1e-5 * (1.0 + abs(want)), (c, w, iters, got, want)


def _sdf_vector_form(q):
  """The textbook box / capsule form on a stacked excess vector q [n]: min(max(q), 0) + |max(q, 0)| (numpy, f64)."""
  return min(np.max(q), 0.0) + np.linalg.norm(np.maximum(q, 0.0))


def test_component_wise_sdfs_equal_the_vector_form():
  """sdf_cylinder / sdf_box / sdf_box_xy / rect_inside_margin, written on components (no stack + reduction, so they
  fuse on a GPU), equal the stacked-vector form (float64 numpy) on random points to float32 rounding (the points are
  tens of metres out: 5e-5 m), and keep finite gradients on the cylinder's axis and on a box's faces (where the
  norms' arguments are 0)."""
  rng = np.random.default_rng(3)
  pts = rng.uniform([-30, -30, -5], [30, 30, 20], (400, 3))
  cyl = np.array([1.5, -2.0, 3.0, 9.0])
  box = np.array([2.0, 1.0, 5.0, 2.5, 0.7, 7.0])
  rect = np.array([-12.0, 8.0, -4.0, 15.0])
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  f = jax.jit(jax.vmap(lambda p: jnp.stack([
      g.sdf_cylinder(p, f32(cyl)), g.sdf_box(p, f32(box)), g.sdf_box_xy(p[:2], f32(box)),
      g.rect_inside_margin(p[:2], f32(rect))])))
  pts = pts.astype(np.float32).astype(np.float64)
  got = np.asarray(f(f32(pts)), np.float64)
  for p, (d_cyl, d_box, d_box_xy, m_rect) in zip(pts, got):
    d_r = np.hypot(*(p[:2] - cyl[:2])) - cyl[2]
    assert d_cyl == pytest.approx(_sdf_vector_form(np.array([d_r, abs(p[2] - cyl[3] / 2) - cyl[3] / 2])), abs=5e-5)
    c, s = math.cos(box[4]), math.sin(box[4])
    d = p[:2] - box[:2]
    loc = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    q = np.abs(loc) - box[2:4]
    assert d_box == pytest.approx(_sdf_vector_form(np.append(q, abs(p[2] - box[5] / 2) - box[5] / 2)), abs=5e-5)
    assert d_box_xy == pytest.approx(_sdf_vector_form(q), abs=5e-5)
    centre = np.array([rect[0] + rect[1], rect[2] + rect[3]]) / 2
    half = np.array([rect[1] - rect[0], rect[3] - rect[2]]) / 2
    assert m_rect == pytest.approx(-_sdf_vector_form(np.abs(p[:2] - centre) - half), abs=5e-5)
  on_axis = jax.grad(lambda p: g.sdf_cylinder(p, f32(cyl)))(jnp.array([1.5, -2.0, 20.0]))
  on_face = jax.grad(lambda p: g.sdf_box(p, jnp.asarray(BOX)))(jnp.array([4.0, 0.0, 3.0]))
  assert np.all(np.isfinite(on_axis)) and np.all(np.isfinite(on_face))
  np.testing.assert_allclose(np.asarray(on_axis), [0.0, 0.0, 1.0], atol=1e-6)   # above the top cap: straight up
