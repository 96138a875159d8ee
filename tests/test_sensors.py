"""Sensor models: rates/fresh flags, held samples, noise statistics, physics of each reading, rng and vmap."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax.math3d import euler_to_quat
from specguard_jax.sensors import SensorConfig, check_rates, init_sensors, sense
from specguard_jax.types import TrueState

DT = 0.02


def _truth(pos=(3.0, -2.0, 10.0), vel=(0.0, 0.0, 0.0), euler=(0.0, 0.0, 0.5), ang_vel=(0.0, 0.0, 0.0),
           acc=(0.0, 0.0, 0.0)):
  f = lambda v: jnp.asarray(v, jnp.float32)
  return TrueState(pos=f(pos), vel=f(vel), quat=euler_to_quat(f(euler)), ang_vel=f(ang_vel), acc=f(acc))


@functools.partial(jax.jit, static_argnums=(0, 3))
def _run(cfg, truth, rng, n):
  """n ticks of a constant truth; returns the stacked readings and the final sensor state (one jitted scan)."""
  k0, k1 = jax.random.split(rng)
  st = init_sensors(cfg, truth, k0)
  st, rs = jax.lax.scan(lambda s, k: sense(cfg, s, truth, k, DT), st, jax.random.split(k1, n))
  return rs, st


_sense = jax.jit(sense, static_argnums=0)
_init = jax.jit(init_sensors, static_argnums=0)


def test_presets_and_rate_check():
  d, r = SensorConfig.drone(), SensorConfig.rover()
  assert d.has_flow and not d.has_odom and r.has_odom and not r.has_flow
  check_rates(d, DT)
  check_rates(r, DT)
  with pytest.raises(ValueError):
    check_rates(dataclasses.replace(d, gps_rate=7.0), DT)
  with pytest.raises(ValueError):
    check_rates(dataclasses.replace(d, baro_rate=100.0), DT)


def test_fresh_flags_and_held_samples():
  truth = _truth(vel=(1.0, 0.5, 0.0))
  rs, st = _run(SensorConfig.drone(), truth, jax.random.PRNGKey(0), 100)
  k = np.arange(100)
  expect = {"gps": 5, "mag": 1, "baro": 2, "flow": 2}
  for name, period in expect.items():
    fresh = np.asarray(getattr(rs, f"{name}_fresh"))
    np.testing.assert_array_equal(fresh, (k % period == 0).astype(np.float32), err_msg=name)
  assert int(st.tick) == 100
  np.testing.assert_array_equal(np.asarray(rs.odom_fresh), 0.0)
  np.testing.assert_array_equal(np.asarray(rs.odom_speed), 0.0)
  # stale ticks repeat the previous sample exactly; fresh ticks bring a new one
  for field, period in (("gps_pos", 5), ("gps_vel", 5), ("baro_alt", 2), ("flow", 2)):
    x = np.asarray(getattr(rs, field)).reshape(100, -1)
    same = np.all(x[1:] == x[:-1], axis=1)
    np.testing.assert_array_equal(same, (k[1:] % period != 0), err_msg=field)
  # IMU is new every tick
  for field in ("gyro", "accel"):
    x = np.asarray(getattr(rs, field))
    assert np.all(np.any(x[1:] != x[:-1], axis=1)), field


def test_rover_suite():
  truth = _truth(pos=(0.0, 0.0, 0.2), vel=(2.0, 1.0, 0.0), euler=(0.0, 0.0, math.atan2(1.0, 2.0)))
  rs, _ = _run(SensorConfig.rover(), truth, jax.random.PRNGKey(1), 50)
  np.testing.assert_array_equal(np.asarray(rs.flow_fresh), 0.0)
  np.testing.assert_array_equal(np.asarray(rs.flow), 0.0)
  np.testing.assert_array_equal(np.asarray(rs.odom_fresh), (np.arange(50) % 2 == 0).astype(np.float32))
  speed = np.asarray(rs.odom_speed)[::2]
  assert abs(speed.mean() - math.sqrt(5.0)) < 0.05 and 0.02 < speed.std() < 0.09


def test_noiseless_physics():
  cfg = SensorConfig.drone().noiseless()
  key = jax.random.PRNGKey(0)
  # level hover: accelerometer reads +g up, gyro zero, heading = yaw, baro = height
  t = _truth(euler=(0.0, 0.0, 2.0))
  st = _init(cfg, t, key)
  _, r = _sense(cfg, st, t, key, DT)
  np.testing.assert_allclose(r.accel, [0.0, 0.0, 9.81], atol=1e-5)
  np.testing.assert_allclose(r.gyro, 0.0, atol=1e-7)
  np.testing.assert_allclose(r.mag_yaw, 2.0, atol=1e-6)
  np.testing.assert_allclose(r.baro_alt, 10.0, atol=1e-5)
  np.testing.assert_allclose(r.gps_pos, [3.0, -2.0, 10.0], atol=1e-5)
  # pitched 30 deg (FLU: nose down), rolling and accelerating: specific force R^T (acc - g), body rate passthrough
  e = np.array([0.3, math.radians(30.0), -1.0])
  acc = np.array([1.0, -2.0, 0.5])
  t = _truth(euler=e, ang_vel=(0.1, -0.2, 0.3), acc=acc, vel=(4.0, 3.0, -1.0), pos=(0.0, 0.0, 5.0))
  _, r = _sense(cfg, st, t, key, DT)
  cr, sr, cp, sp, cy, sy = np.cos(e[0]), np.sin(e[0]), np.cos(e[1]), np.sin(e[1]), np.cos(e[2]), np.sin(e[2])
  rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
  ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
  rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
  rot = rz @ ry @ rx
  np.testing.assert_allclose(r.accel, rot.T @ (acc + [0, 0, 9.81]), atol=1e-4)
  np.testing.assert_allclose(r.gyro, [0.1, -0.2, 0.3], atol=1e-6)
  np.testing.assert_allclose(r.mag_yaw, -1.0, atol=1e-5)
  vb = rot.T @ np.array([4.0, 3.0, -1.0])
  np.testing.assert_allclose(r.flow, vb[:2] / 5.0, atol=1e-5)
  # pure pitch: gravity shows up on -x
  _, r = _sense(cfg, st, _truth(euler=(0.0, math.radians(30.0), 0.0)), key, DT)
  np.testing.assert_allclose(r.accel, [-9.81 * 0.5, 0.0, 9.81 * math.cos(math.radians(30.0))], atol=1e-4)


def test_flow_invalid_near_ground():
  cfg = SensorConfig.drone()
  t = _truth(pos=(0.0, 0.0, 0.2), vel=(1.0, 0.0, 0.0))
  rs, _ = _run(cfg, t, jax.random.PRNGKey(2), 10)
  np.testing.assert_array_equal(np.asarray(rs.flow_fresh), 0.0)
  np.testing.assert_array_equal(np.asarray(rs.flow), 0.0)


@pytest.fixture(scope="module")
def batch_first_readings():
  """One fresh sample from each of 4,000 independent sensor suites (default drone config), plus the truth."""
  n = 4000
  cfg = SensorConfig.drone()
  t = _truth(vel=(2.0, -1.0, 0.5), ang_vel=(0.1, 0.0, -0.2))

  @jax.jit
  def one(k):
    k0, k1 = jax.random.split(k)
    return sense(cfg, init_sensors(cfg, t, k0), t, k1, DT)[1]

  return cfg, t, jax.vmap(one)(jax.random.split(jax.random.PRNGKey(3), n))


def test_noise_statistics_match_config(batch_first_readings):
  cfg, t, r = batch_first_readings
  std = lambda x: np.asarray(x).std(axis=0)
  tol = 0.06  # relative; 4,000 samples give ~1.1% σ error

  def close(measured, expected, what):
    np.testing.assert_allclose(measured, expected, rtol=tol, err_msg=what)

  close(std(r.gps_pos - t.pos), np.hypot([cfg.gps_pos_sigma_h] * 2 + [cfg.gps_pos_sigma_v],
                                         [cfg.gps_drift_sigma_h] * 2 + [cfg.gps_drift_sigma_v]), "gps pos")
  close(std(r.gps_vel - t.vel), [cfg.gps_vel_sigma_h] * 2 + [cfg.gps_vel_sigma_v], "gps vel")
  close(std(r.gyro - t.ang_vel), [math.hypot(cfg.gyro_sigma, cfg.gyro_bias_init)] * 3, "gyro")
  close(std(r.accel), [math.hypot(cfg.accel_sigma, cfg.accel_bias_init)] * 3, "accel")
  close(std(r.mag_yaw - 0.5), cfg.mag_sigma, "mag")
  close(std(r.baro_alt - 10.0), cfg.baro_sigma, "baro")
  close(std(r.flow), [cfg.flow_sigma] * 2, "flow")
  # unbiased white noise
  assert np.all(np.abs(np.asarray(r.gps_vel - t.vel).mean(0)) < 0.01)
  assert abs(float(np.asarray(r.baro_alt).mean()) - 10.0) < 0.02


_WALK_CFG = dataclasses.replace(SensorConfig.drone().noiseless(), gyro_bias_walk=0.01, accel_bias_walk=0.02,
                                baro_drift_walk=0.05, gps_drift_sigma_h=1.0, gps_drift_sigma_v=2.0, gps_drift_tau=5.0)


def test_bias_random_walk_and_gps_wander():
  """Bias/drift processes: random walks grow as walk*sqrt(t); the GPS wander is stationary with the configured σ."""
  cfg, t = _WALK_CFG, _truth()
  n_ticks = 500  # 10 s

  st = jax.vmap(lambda k: _run(cfg, t, k, n_ticks)[1])(jax.random.split(jax.random.PRNGKey(4), 1000))
  tsec = n_ticks * DT
  np.testing.assert_allclose(np.asarray(st.gyro_bias).std(0), 0.01 * math.sqrt(tsec), rtol=0.1)
  np.testing.assert_allclose(np.asarray(st.accel_bias).std(0), 0.02 * math.sqrt(tsec), rtol=0.1)
  np.testing.assert_allclose(np.asarray(st.baro_drift).std(), 0.05 * math.sqrt(tsec), rtol=0.1)
  np.testing.assert_allclose(np.asarray(st.gps_drift).std(0), [1.0, 1.0, 2.0], rtol=0.1)


def test_gps_wander_is_correlated():
  rs, _ = _run(_WALK_CFG, _truth(), jax.random.PRNGKey(5), 500)
  err = np.asarray(rs.gps_pos[:, 0]) - 3.0
  # sample-to-sample (0.1 s) changes have σ sqrt(2 (1 - exp(-0.1 / 5))) = 0.2 m (white noise of σ 1 m: 1.41 m)
  steps = np.diff(err[::5])
  assert 0.12 < np.std(steps) < 0.28, np.std(steps)


def test_reproducible_and_vmappable():
  cfg = SensorConfig.drone()
  t = _truth(vel=(1.0, 0.5, 0.0))
  a, _ = _run(cfg, t, jax.random.PRNGKey(7), 100)
  b, _ = _run(cfg, t, jax.random.PRNGKey(7), 100)
  c, _ = _run(cfg, t, jax.random.PRNGKey(8), 100)
  for x, y, z in zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(c)):
    np.testing.assert_array_equal(x, y)
  assert not np.array_equal(np.asarray(a.gps_pos), np.asarray(c.gps_pos))
  # batch of different vehicles, one tick
  truths = jax.tree.map(lambda x: jnp.stack([x, x + 0.1, x - 0.1]), t)
  truths = truths.replace(quat=jnp.stack([t.quat] * 3))
  keys = jax.random.split(jax.random.PRNGKey(9), 3)
  st = jax.vmap(lambda tr, k: _init(cfg, tr, k))(truths, keys)
  st2, r = jax.jit(jax.vmap(lambda s, tr, k: sense(cfg, s, tr, k, DT)))(st, truths, keys)
  assert r.gps_pos.shape == (3, 3) and r.mag_yaw.shape == (3,) and st2.tick.shape == (3,)
  _, r1 = _sense(cfg, jax.tree.map(lambda x: x[1], st), jax.tree.map(lambda x: x[1], truths), keys[1], DT)
  np.testing.assert_allclose(r.gps_pos[1], r1.gps_pos, atol=1e-5)
