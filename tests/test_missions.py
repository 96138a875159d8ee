"""Generated missions satisfy their MissionConfig; path helpers; jit/vmap/determinism."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import missions as ms
from envs.missions import MAX_WAYPOINTS, Mission, MissionConfig

N = 512


def _batch(cfg, seed=0, n=N):
  keys = jax.random.split(jax.random.key(seed), n)
  return jax.tree.map(np.asarray, jax.jit(jax.vmap(lambda k: ms.generate_mission(cfg, k)))(keys))


@pytest.fixture(scope="module")
def drones():
  return _batch(MissionConfig.drone())


@pytest.fixture(scope="module")
def rovers():
  return _batch(MissionConfig.rover(), seed=1)


def _legs(m, i):
  """Horizontal leg vectors [n, 2] of mission i (leg 0 from above home)."""
  n = m.n_waypoints[i]
  pts = np.concatenate([m.home[i][None], m.waypoints[i][:n]], 0)
  return pts[1:, :2] - pts[:-1, :2]


@pytest.mark.parametrize("which", ["drone", "rover"])
def test_config_respected(which, drones, rovers):
  cfg = MissionConfig.drone() if which == "drone" else MissionConfig.rover()
  m = drones if which == "drone" else rovers
  assert m.waypoints.shape == (N, MAX_WAYPOINTS, 3)
  assert m.n_waypoints.dtype == np.int32 and m.loiter_wp.dtype == np.int32
  assert np.all((m.n_waypoints >= 1) & (m.n_waypoints <= MAX_WAYPOINTS))
  np.testing.assert_array_equal(m.home[:, 2], 0.0)
  max_turn = 0.0
  for i in range(N):
    n = m.n_waypoints[i]
    legs = _legs(m, i)
    ln = np.linalg.norm(legs, axis=-1)
    assert np.all(ln >= cfg.leg_length[0] - 1e-3) and np.all(ln <= cfg.leg_length[1] + 1e-3), ln
    if n > 1:
      cos = np.sum(legs[1:] * legs[:-1], -1) / (ln[1:] * ln[:-1])
      max_turn = max(max_turn, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max()))
    z = m.waypoints[i, :n, 2]
    dl = m.deadline[i, :n]
    assert np.all(np.diff(dl) > 0), dl
    assert np.all(m.window_open[i, :n] < dl)
    assert np.all(np.diff(m.window_open[i, :n]) > 0)
    # padding repeats the last valid waypoint / deadline
    np.testing.assert_array_equal(m.waypoints[i, n:], np.broadcast_to(m.waypoints[i, n - 1], (MAX_WAYPOINTS - n, 3)))
    np.testing.assert_array_equal(m.deadline[i, n:], dl[-1])
    assert m.nominal_duration[i] <= cfg.max_duration_s + 1e-3
    if which == "drone":
      assert np.all((z >= 12.0 - 1e-4) & (z <= 18.0 + 1e-4))
      assert 12.0 - 1e-4 <= m.takeoff_alt[i] <= 18.0 + 1e-4
    else:
      np.testing.assert_array_equal(z, 0.0)
      assert m.takeoff_alt[i] == 0 and m.land[i] == 0 and m.loiter_wp[i] == -1
    if m.loiter_wp[i] >= 0:
      assert m.loiter_wp[i] < n and 10.0 <= m.loiter_time[i] <= 30.0
    else:
      assert m.loiter_time[i] == 0.0
  assert max_turn <= cfg.max_turn_deg + 1e-2
  assert np.all((m.cruise_speed >= cfg.cruise_speed[0]) & (m.cruise_speed <= cfg.cruise_speed[1]))
  np.testing.assert_allclose(m.acceptance_radius, 5.0 if which == "drone" else 2.0)   # rover: ArduRover WP_RADIUS
  np.testing.assert_allclose(m.loiter_radius, 8.0)
  # 1-5 minutes like the paper (min duration is best effort: nearly all missions reach it)
  assert np.mean(m.nominal_duration >= cfg.min_duration_s) > 0.95
  assert np.all(m.nominal_duration <= 300.0)


def test_variety(drones):
  assert 0.15 < np.mean(drones.loiter_wp >= 0) < 0.45
  assert 0.65 < np.mean(drones.land) < 0.95
  assert len(np.unique(drones.n_waypoints)) >= 5


def test_deadline_formula(drones):
  cfg = MissionConfig.drone()
  i = int(np.argmax(drones.loiter_wp >= 0))
  m = jax.tree.map(lambda x: x[i], drones)
  n = m.n_waypoints
  pts = np.concatenate([[[0, 0, m.takeoff_alt]], m.waypoints[:n]], 0)
  arr = m.takeoff_alt / cfg.climb_speed + np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=-1)) / m.cruise_speed
  arr = arr + np.where(np.arange(n) > m.loiter_wp, m.loiter_time, 0.0)
  np.testing.assert_allclose(m.deadline[:n], 1.5 * arr + 10.0, rtol=1e-5)
  np.testing.assert_allclose(m.window_open[:n], 0.5 * arr, rtol=1e-5)


def test_max_duration_short_missions():
  cfg = MissionConfig.drone(max_duration_s=45.0, min_duration_s=0.0, n_waypoints=(2, 6))
  m = _batch(cfg, seed=3, n=256)
  assert np.all(m.nominal_duration <= 45.0 + 1e-3)
  assert np.all(m.n_waypoints >= 1)


def test_path_kinds():
  line = _batch(MissionConfig.drone(path_kind_probs=(1, 0, 0)), n=64)
  circ = _batch(MissionConfig.drone(path_kind_probs=(0, 1, 0)), n=64)
  for i in range(64):
    legs = _legs(line, i)
    hd = np.unwrap(np.arctan2(legs[:, 1], legs[:, 0]))
    assert np.all(np.abs(np.diff(hd)) <= math.radians(15.0) + 1e-4)
    legs = _legs(circ, i)
    ln = np.linalg.norm(legs, axis=-1)
    np.testing.assert_allclose(ln, ln[0], rtol=1e-4)
    hd = np.unwrap(np.arctan2(legs[:, 1], legs[:, 0]))
    if len(hd) > 2:
      np.testing.assert_allclose(np.diff(hd), np.diff(hd)[0], atol=1e-4)


def test_determinism_and_jit(drones):
  cfg = MissionConfig.drone()
  gen = jax.jit(ms.generate_mission, static_argnums=0)
  keys = jax.random.split(jax.random.key(0), N)
  a, b = gen(cfg, keys[5]), gen(cfg, keys[5])
  for x, y, z in zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(drones)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_allclose(np.asarray(x), z[5], rtol=1e-5, atol=1e-4)  # vmap == single call
  c = gen(cfg, keys[6])
  assert not np.allclose(np.asarray(a.waypoints), np.asarray(c.waypoints))


def test_config_validation():
  with pytest.raises(ValueError):
    MissionConfig(vehicle="boat")
  with pytest.raises(ValueError):
    MissionConfig(n_waypoints=(1, MAX_WAYPOINTS + 1))
  hash(MissionConfig.drone())  # usable as a static jit argument


def _toy():
  wps = np.zeros((MAX_WAYPOINTS, 3), np.float32)
  wps[0] = [30, 0, 15]
  wps[1] = [30, 40, 15]
  wps[2:] = wps[1]
  f = lambda x: jnp.asarray(x, jnp.float32)
  return Mission(home=f([0, 0, 0]), waypoints=f(wps), n_waypoints=jnp.int32(2), window_open=f(np.zeros(12)),
                 deadline=f(np.arange(12) + 10.0), takeoff_alt=f(10.0), cruise_speed=f(8.0),
                 acceptance_radius=f(5.0), loiter_wp=jnp.int32(-1), loiter_time=f(0.0), loiter_radius=f(8.0),
                 land=f(1.0), nominal_duration=f(0.0))


def test_legs_and_polyline():
  m = _toy()
  s, e = ms.mission_leg(m, 0)
  np.testing.assert_allclose(s, [0, 0, 10]); np.testing.assert_allclose(e, [30, 0, 15])
  s, e = ms.mission_leg(m, jnp.int32(1))
  np.testing.assert_allclose(s, [30, 0, 15]); np.testing.assert_allclose(e, [30, 40, 15])
  s, e = ms.mission_leg(m, 2)  # landing
  np.testing.assert_allclose(s, [30, 40, 15]); np.testing.assert_allclose(e, [30, 40, 0])
  s, e = ms.mission_leg(m.replace(land=jnp.float32(0.0)), 5)
  np.testing.assert_allclose(s, [30, 40, 15]); np.testing.assert_allclose(e, [30, 40, 15])
  pts, valid = ms.path_polyline(m)
  assert pts.shape == (MAX_WAYPOINTS + 3, 3) and valid.shape == (MAX_WAYPOINTS + 3,)
  assert int(valid.sum()) == 5
  np.testing.assert_allclose(pts[-1], [30, 40, 0])
  np.testing.assert_allclose(float(ms.path_length(m)), 10 + math.hypot(30, 5) + 40 + 15, rtol=1e-6)
  np.testing.assert_allclose(ms.final_waypoint(m), [30, 40, 15])
  # vmap over target indices
  s, e = jax.vmap(ms.mission_leg, (None, 0))(m, jnp.arange(4))
  assert s.shape == (4, 3)
