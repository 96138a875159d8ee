"""Procedural worlds: presets, path clearance over many seeds, boundary/ceiling, and exact world_queries."""

import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import worlds as W
from envs.mission_files import load_mission
from envs.missions import MAX_WAYPOINTS, Mission, MissionConfig, generate_mission, path_polyline
from specguard_jax.signals import SIGNAL_NAMES

SEEDS = 256
SAMPLES_PER_SEG = 40


_world_gen = jax.jit(jax.vmap(W.generate_world, (None, 0, 0)))  # traced preset id: one compile for all presets


def _gen(cfg):
  mission_gen = jax.jit(jax.vmap(lambda k: generate_mission(cfg, k)))

  def gen(pid, keys):
    m = mission_gen(keys)
    return m, _world_gen(jnp.int32(pid), m, jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys))

  return gen


def _path_samples(m):
  """Dense points on the path [S, 3] plus the loiter circle (if any) and its centre."""
  pts, _ = path_polyline(m)
  t = jnp.linspace(0.0, 1.0, SAMPLES_PER_SEG)
  seg = pts[:-1, None, :] + t[None, :, None] * (pts[1:] - pts[:-1])[:, None, :]
  ang = jnp.linspace(0.0, 2 * math.pi, 24, endpoint=False)
  lc = m.waypoints[jnp.clip(m.loiter_wp, 0, MAX_WAYPOINTS - 1)]
  ring = lc + m.loiter_radius * jnp.stack([jnp.cos(ang), jnp.sin(ang), jnp.zeros_like(ang)], -1)
  ring = jnp.where(m.loiter_wp >= 0, ring, pts[0])
  return jnp.concatenate([seg.reshape(-1, 3), ring], 0)


@jax.jit
@jax.vmap
def _clearance_stats(m, w):
  """(min obstacle sdf, min fence margin) over dense path samples and the loiter circle."""
  p = _path_samples(m)
  obs = jax.vmap(W.obstacle_sdf, (None, 0))(w, p)
  fm = jax.vmap(lambda q: W.fence_distances(w, q)[0])(p)
  return jnp.min(obs), jnp.min(fm)


@pytest.fixture(scope="module")
def drone_gen():
  return _gen(MissionConfig.drone()), jax.random.split(jax.random.key(7), SEEDS)


@pytest.fixture(scope="module")
def drone_batches(drone_gen):
  gen, keys = drone_gen
  return {name: jax.tree.map(np.asarray, gen(pid, keys)) for pid, name in enumerate(W.PRESET_NAMES)}


def test_preset_table():
  assert W.PRESET_NAMES == ("suburban_residential", "suburban_streets", "urban_city_areas", "urban_city_streets",
                            "urban_park", "urban_green_areas", "urban_high_rise", "manufacturing_plant",
                            "open_mountain", "open_beach")
  assert "".join(p.label for p in W.PRESETS.values()) == "ABCDEFGHIJ"
  for name, p in W.PRESETS.items():
    want = {"A": "properties", "B": "properties", "C": "properties", "D": "properties", "G": "properties",
            "E": "boundary", "F": "boundary", "I": "boundary", "J": "boundary", "H": "indoor"}[p.label]
    assert p.geofence == want, name
    assert p.density("cylinder") + p.density("box") > 0
  assert W.PRESETS["manufacturing_plant"].ceiling is not None
  assert W.PRESETS["manufacturing_plant"].wind_speed == (0.0, 0.0)
  assert W.PRESETS["open_beach"].wind_speed[1] > W.PRESETS["suburban_residential"].wind_speed[1]
  with pytest.raises(ValueError):
    W.WorldPreset("x", "X", "", (), geofence="moat")


def test_clearance_over_seeds(drone_batches):
  for name, (m, w) in drone_batches.items():
    obs, fm = _clearance_stats(m, w)
    obs, fm = np.asarray(obs), np.asarray(fm)
    assert obs.min() >= W.DEFAULT_CLEARANCE - 1e-3, (name, obs.min())
    assert fm.min() >= W.DEFAULT_CLEARANCE - 1e-3, (name, fm.min())
    # obstacles matter: most worlds have something within 15 m of the path
    assert np.mean(obs < W.DEFAULT_CLEARANCE + 15.0) > 0.6, (name, np.mean(obs < 24.0))


def test_rover_clearance():
  gen = _gen(MissionConfig.rover())
  keys = jax.random.split(jax.random.key(3), SEEDS)
  for pid in (W.PRESET_NAMES.index("urban_city_streets"), W.PRESET_NAMES.index("manufacturing_plant")):
    m, w = gen(pid, keys)
    obs, fm = _clearance_stats(m, w)
    assert float(obs.min()) >= W.DEFAULT_CLEARANCE - 1e-3
    assert float(fm.min()) >= W.DEFAULT_CLEARANCE - 1e-3
    assert np.all(np.asarray(w.ceiling) > 0)


def test_example_mission_files_get_clear_worlds():
  data = pathlib.Path(__file__).resolve().parents[1] / "envs" / "data"
  for fname, vehicle in (("drone_inspection.plan", "drone"), ("drone_patrol.waypoints", "drone"),
                         ("rover_loop.waypoints", "rover")):
    m = load_mission(data / fname, vehicle)
    mb = jax.tree.map(lambda x: jnp.broadcast_to(x, (SEEDS,) + x.shape), m)  # same shapes: no recompile
    keys = jax.random.split(jax.random.key(11), SEEDS)
    for pid in (0, 7):
      w = _world_gen(jnp.int32(pid), mb, keys)
      obs, fm = _clearance_stats(mb, w)
      assert float(obs.min()) >= W.DEFAULT_CLEARANCE - 1e-3, (fname, pid)
      assert float(fm.min()) >= W.DEFAULT_CLEARANCE - 1e-3, (fname, pid)
      assert float(w.cylinder_mask.sum(-1).mean() + w.box_mask.sum(-1).mean()) >= 4.0, (fname, pid)


def test_structure_boundary_ceiling_weather(drone_batches):
  for pid, (name, (m, w)) in enumerate(drone_batches.items()):
    preset = W.PRESETS[name]
    assert w.cylinders.shape == (SEEDS, W.MAX_CYLINDERS, 4) and w.boxes.shape == (SEEDS, W.MAX_BOXES, 6)
    assert w.fences.shape == (SEEDS, W.MAX_FENCES, 6) and w.cylinder_mask.dtype == bool
    np.testing.assert_array_equal(w.preset_id, pid)
    pts = np.stack([np.asarray(path_polyline(jax.tree.map(lambda x: x[i], m))[0]) for i in range(16)])
    b = w.boundary[:16]
    lo_margin = preset.boundary_margin[0] - 1e-3
    assert np.all(pts[..., 0].min(1) - b[:, 0] >= lo_margin) and np.all(b[:, 1] - pts[..., 0].max(1) >= lo_margin)
    assert np.all(pts[..., 1].min(1) - b[:, 2] >= lo_margin) and np.all(b[:, 3] - pts[..., 1].max(1) >= lo_margin)
    np.testing.assert_array_equal(w.boundary_on, preset.geofence != "properties")
    # the prisms' horizontal axes, which the queries read in place of their yaws
    for prisms, axes in ((w.boxes, w.box_axes), (w.fences, w.fence_axes)):
      yaw = prisms[..., 4].astype(np.float64)
      np.testing.assert_allclose(axes, np.stack([np.cos(yaw), np.sin(yaw)], -1), atol=2e-6, err_msg=name)
    n_fences = w.fence_mask.sum(-1)
    if preset.geofence == "properties":
      assert n_fences.mean() >= 3.0, name
      np.testing.assert_allclose(w.fences[w.fence_mask][:, 5], W.FENCE_HEIGHT)
    else:
      assert n_fences.max() == 0
    if preset.geofence == "indoor":
      assert np.all(w.ceiling >= preset.ceiling[0] - 1e-4) and np.all(w.ceiling < 40.0)
      np.testing.assert_array_equal(w.wind_mean, 0.0)
      np.testing.assert_array_equal(w.gust_std, 0.0)
    else:
      np.testing.assert_array_equal(w.ceiling, W.NO_CEILING)
    speed = np.linalg.norm(w.wind_mean, axis=-1)
    assert np.all(speed >= preset.wind_speed[0] - 1e-4) and np.all(speed <= preset.wind_speed[1] + 1e-4)
    np.testing.assert_array_equal(w.wind_mean[:, 2], 0.0)
    assert w.cylinder_mask.sum(-1).mean() + w.box_mask.sum(-1).mean() >= 8.0, name
    # masked slots are parked far away with zero size
    assert np.all(w.cylinders[~w.cylinder_mask][:, 2] == 0.0)
    # valid sizes within the kind ranges
    hmax = max(k.height[1] for k in preset.kinds)
    assert np.all(w.cylinders[w.cylinder_mask][:, 3] <= hmax) and np.all(w.boxes[w.box_mask][:, 5] <= hmax)


def test_determinism_and_preset_forms(drone_gen, drone_batches):
  gen, keys = drone_gen
  m, w = gen(jnp.int32(4), keys)  # same compiled function, same keys -> identical worlds
  for x, y in zip(jax.tree.leaves(w), jax.tree.leaves(drone_batches["urban_park"][1])):
    np.testing.assert_array_equal(np.asarray(x), y)
  assert not np.allclose(w.cylinders[0], w.cylinders[1])
  # names, registered WorldPresets and ids resolve to the same table row
  for pid, name in enumerate(W.PRESET_NAMES):
    assert W._resolve(name)[1:] == (pid, pid) and W._resolve(W.PRESETS[name])[1:] == (pid, pid)
  with pytest.raises(ValueError):
    W._resolve("moon_base")
  # a custom preset (static) works under jit
  custom = W.WorldPreset("my_yard", "Z", "one tree kind", (W.ObstacleKind("tree", "cylinder", 20.0, (5.0, 9.0),
                                                                          radius=(1.0, 2.0)),), geofence="boundary")
  m0 = jax.tree.map(lambda x: jnp.asarray(x[0]), drone_batches["urban_park"][0])
  e = jax.jit(W.generate_world, static_argnums=0)(custom, m0, jax.random.key(2))
  assert int(e.preset_id) == -1 and int(e.box_mask.sum()) == 0 and int(e.cylinder_mask.sum()) > 0
  assert np.all(np.asarray(e.cylinders)[np.asarray(e.cylinder_mask), 2] <= 2.0)


# ---------------------------------------------------------------------------------------------------------------
# Exact queries on a hand-made layout


def _toy_mission():
  wps = np.zeros((MAX_WAYPOINTS, 3), np.float32)
  wps[0] = [100, 0, 15]
  wps[1] = [100, 100, 15]
  wps[2:] = wps[1]
  f = lambda x: jnp.asarray(x, jnp.float32)
  return Mission(home=f([0, 0, 0]), waypoints=f(wps), n_waypoints=jnp.int32(2), window_open=f(np.zeros(12)),
                 deadline=f(np.full(12, 100.0)), takeoff_alt=f(15.0), cruise_speed=f(8.0), acceptance_radius=f(5.0),
                 loiter_wp=jnp.int32(-1), loiter_time=f(0.0), loiter_radius=f(8.0), land=f(1.0),
                 nominal_duration=f(60.0))


def _toy_world(boundary_on=True, ceiling=30.0):
  cyl = np.zeros((W.MAX_CYLINDERS, 4), np.float32)
  cyl[0] = [50, 20, 2, 10]      # tree beside the first leg
  box = np.zeros((W.MAX_BOXES, 6), np.float32)
  box[0] = [120, 50, 5, 5, 0, 30]
  fen = np.zeros((W.MAX_FENCES, 6), np.float32)
  fen[0] = [50, -40, 20, 10, 0, 120]  # keep-out prism: y in [-50, -30], x in [30, 70]
  cm = np.zeros(W.MAX_CYLINDERS, bool); cm[0] = True
  bm = np.zeros(W.MAX_BOXES, bool); bm[0] = True
  fm = np.zeros(W.MAX_FENCES, bool); fm[0] = True
  return W.make_world(cylinders=cyl, cylinder_mask=cm, boxes=box, box_mask=bm, fences=fen, fence_mask=fm,
                      boundary=[-30, 130, -60, 130], boundary_on=boundary_on, ceiling=ceiling, wind_mean=[0, 0, 0],
                      gust_std=0.0)


@pytest.mark.parametrize("pos, target, want", [
  # on the first leg, 15 m above, beside the tree: radial 20 - 2 = 18; top 10 -> dz 5 -> but radial dominates
  ((50, 0, 15), 0, dict(obstacle_distance=math.hypot(18, 5), path_deviation=0.0, dist_wp=50.0,
                        dist_final=math.hypot(50, 100), fence_margin=15.0, fence_h=100.0, fence_v=15.0)),
  # near the keep-out prism (y = -30 face); ceiling 20 m above, boundary 35 m south
  ((50, -25, 10), 1, dict(fence_margin=5.0, fence_h=5.0, fence_v=10.0 - 120.0, path_deviation=math.hypot(50, 25, 5),
                          dist_wp=math.hypot(50, 125, 5))),
  # outside the boundary on the east side (x = 135): boundary margin -5
  ((135, 50, 15), 1, dict(fence_margin=-5.0, fence_h=-5.0, fence_v=100.0, path_deviation=35.0,
                          obstacle_distance=10.0)),
  # inside the box (5 m deep from its faces), ceiling 8 m above (boundary 10 m east)
  ((120, 50, 22), 1, dict(obstacle_distance=-5.0, fence_margin=8.0, fence_v=8.0, fence_h=100.0)),
  # take-off: on the vertical segment above home
  ((0, 0, 5), 0, dict(path_deviation=0.0, dist_wp=math.hypot(100, 10))),
  # after the last waypoint: landing leg, dist_wp to the landing point on the ground
  ((100, 100, 7), 2, dict(path_deviation=0.0, dist_wp=7.0, dist_final=8.0)),
])
def test_world_queries_exact(pos, target, want):
  out = jax.jit(W.world_queries)(_toy_world(), _toy_mission(), jnp.asarray(pos, jnp.float32), jnp.int32(target))
  assert set(out) == set(W.WORLD_SIGNALS) and set(out) <= set(SIGNAL_NAMES)
  for k, v in want.items():
    assert float(out[k]) == pytest.approx(v, abs=1e-3), k
    assert out[k].dtype == jnp.float32 and out[k].shape == ()


def test_world_queries_caps_and_no_fences():
  w = _toy_world(boundary_on=False, ceiling=W.NO_CEILING)
  w = w.replace(fence_mask=jnp.zeros(W.MAX_FENCES, bool), cylinder_mask=jnp.zeros(W.MAX_CYLINDERS, bool),
                box_mask=jnp.zeros(W.MAX_BOXES, bool))
  out = jax.jit(W.world_queries)(w, _toy_mission(), jnp.array([0.0, 0.0, 5.0]), 0)
  for k in ("obstacle_distance", "fence_margin", "fence_h", "fence_v"):
    assert float(out[k]) == W.SIGNAL_CAP


def test_world_queries_vmap_and_grad():
  w, m = _toy_world(), _toy_mission()
  pos = jax.random.uniform(jax.random.key(0), (1000, 3), minval=-50, maxval=150)
  tgt = jnp.arange(1000, dtype=jnp.int32) % 3
  out = jax.jit(jax.vmap(W.world_queries, (None, None, 0, 0)))(w, m, pos, tgt)
  assert all(v.shape == (1000,) for v in out.values())
  # batch of worlds too
  wb = jax.tree.map(lambda x: jnp.stack([x, x]), w)
  out2 = jax.jit(jax.vmap(W.world_queries, (0, None, 0, None)))(wb, m, pos[:2], 1)
  out3 = {k: v[:2] for k, v in jax.jit(jax.vmap(W.world_queries, (None, None, 0, None)))(w, m, pos, 1).items()}
  for k in out2:
    np.testing.assert_allclose(out2[k], out3[k], rtol=1e-6)
  g = jax.jit(jax.grad(lambda p: W.world_queries(w, m, p, 1)["obstacle_distance"]))(jnp.array([50.0, 30.0, 5.0]))
  np.testing.assert_allclose(g, [0.0, 1.0, 0.0], atol=1e-5)


def _worlds_and_points_near_obstacles(drone_batches, rng, shape):
  """(world, points [*shape, 3] around its obstacles: inside, outside, above) for 3 presets x 4 worlds; the fourth of
  each preset with every obstacle masked off."""
  for name in ("urban_city_areas", "urban_high_rise", "manufacturing_plant"):
    worlds = drone_batches[name][1]
    for k in range(4):
      w = jax.tree.map(lambda x: x[k], worlds)
      if k == 3:
        w = w.replace(cylinder_mask=np.zeros_like(w.cylinder_mask), box_mask=np.zeros_like(w.box_mask))
      centres = np.concatenate([np.asarray(w.cylinders)[:, :2], np.asarray(w.boxes)[:, :2]])
      xy = centres[rng.integers(0, len(centres), shape)] + rng.normal(0.0, 8.0, shape + (2,))
      yield k, w, np.concatenate([xy, rng.uniform(0.0, 60.0, shape + (1,))], -1).astype(np.float32)


def test_obstacle_sdf_and_grad_equals_autodiff_of_the_sdf(drone_batches):
  """The env's observation of the nearest obstacle (distance and direction) from one reverse pass over the nearest
  obstacle equals jax.value_and_grad of obstacle_sdf over all of them: 3 presets x 4 worlds x 64 points around the
  obstacles (inside, outside, above), one world with every obstacle masked off (distance 1e3, gradient 0).
  The reference runs eagerly: jitted, XLA:CPU recomputed the min in the reverse pass with another rounding than the
  forward's, so no obstacle equalled it and the gradient of a few points inside a box came out 0 (what the argmin
  here cannot do)."""
  rng = np.random.default_rng(0)
  ref_fn = jax.vmap(jax.value_and_grad(W.obstacle_sdf, argnums=1), (None, 0))
  fn = jax.jit(jax.vmap(W.obstacle_sdf_and_grad, (None, 0)))
  checked = 0
  for _, w, p in _worlds_and_points_near_obstacles(drone_batches, rng, (64,)):
    (d_ref, g_ref), (d, g) = ref_fn(w, p), fn(w, p)
    np.testing.assert_allclose(np.asarray(d), np.asarray(d_ref), rtol=1e-6, atol=2e-6)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-5, atol=1e-6)
    checked += int(np.sum(np.asarray(d) < 1e3))
  assert checked > 300


def test_obstacle_queries_equal_the_separate_queries(drone_batches):
  """The env step's one-pass obstacle queries equal obstacle_sdf at every point and jax.value_and_grad of it at the
  estimate (eager, as above; 3 presets x 4 worlds, 5 points + 1 estimate around the obstacles per env, one world
  with every obstacle masked off), to float32 rounding; and a tie between two slots takes the first's gradient, as
  argmin."""
  rng = np.random.default_rng(1)
  fn = jax.jit(jax.vmap(W.obstacle_queries, (None, 0, 0)))
  sdf_at = jax.vmap(W.obstacle_sdf, (None, 0))
  grad_at = jax.vmap(jax.value_and_grad(W.obstacle_sdf, argnums=1), (None, 0))

  def ref(w, pts, p):
    return (jax.vmap(lambda q: sdf_at(w, q))(pts), *grad_at(w, p))

  near = 0
  for k, w, pts in _worlds_and_points_near_obstacles(drone_batches, rng, (32, 6)):
    got, want = fn(w, pts[:, :5], pts[:, 5]), ref(w, pts[:, :5], pts[:, 5])
    for g, r in zip(got, want):
      np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=1e-5, atol=1e-5)
    near += int(np.sum(np.asarray(got[1]) < 1e3))
    if k == 3:
      assert np.all(np.asarray(got[0]) == 1e3) and np.all(np.asarray(got[2]) == 0.0)
  assert near > 200
  # two cylinders exactly as near (on either side of the point): the first slot's gradient, as argmin picks it; a
  # NaN point's distance is NaN, as obstacle_sdf's
  w = jax.tree.map(lambda x: x[0], drone_batches["urban_city_areas"][1])
  for first in (0, 1):
    cyl = np.asarray(w.cylinders).copy()
    cyl[first], cyl[1 - first] = [0.0, 0.0, 1.0, 10.0], [6.0, 0.0, 1.0, 10.0]
    mask = np.zeros_like(w.cylinder_mask)
    mask[:2] = True
    wt = w.replace(cylinders=cyl, cylinder_mask=mask, box_mask=np.zeros_like(w.box_mask))
    p = np.array([3.0, 0.0, 1.0], np.float32)
    d_pts, d, g = W.obstacle_queries(wt, np.stack([p, np.full(3, np.nan, np.float32)]), p)
    np.testing.assert_allclose([d, *g], [2.0, 1.0 if first == 0 else -1.0, 0.0, 0.0], atol=1e-6)
    assert float(d_pts[0]) == 2.0 and np.isnan(d_pts[1])
