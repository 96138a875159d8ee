"""Sensor models: rates/fresh flags, held samples, noise statistics, physics of each reading, rng and vmap."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax.math3d import euler_to_quat
from specguard_jax.sensors import SURFACES, SensorConfig, check_rates, init_sensors, mag_heading, sense
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


def _no_dropout(cfg):
  """cfg without optical-flow quality dropouts (tests that count fresh flow samples)."""
  return dataclasses.replace(cfg, flow_dropout=tuple((name, 0.0) for name, _ in cfg.flow_dropout))


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
  rs, st = _run(_no_dropout(SensorConfig.drone()), truth, jax.random.PRNGKey(0), 100)
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
  rs, _ = _run(SensorConfig.rover(odom_scale_sigma=0.0), truth, jax.random.PRNGKey(1), 50)
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
  # every per-episode error is zero: no flow scale error or dropout, no iron or structure disturbance, no slip
  for name in ("flow_scale", "flow_dropout", "flow_bad", "mag_hard", "mag_dist", "odom_scale"):
    np.testing.assert_array_equal(np.asarray(getattr(st, name)), 0, err_msg=name)
  np.testing.assert_array_equal(st.mag_soft, np.eye(2))
  _, r = _sense(cfg, st, t, key, DT, obstacle_distance=0.6)
  np.testing.assert_allclose(r.mag_yaw, 2.0, atol=1e-6)
  rover = SensorConfig.rover().noiseless()
  tr = _truth(pos=(0.0, 0.0, 0.2), vel=(3.0, 0.0, 0.0), euler=(0.0, 0.0, 0.0), acc=(0.0, 5.0, 0.0))
  _, r = _sense(rover, _init(rover, tr, key), tr, key, DT)
  np.testing.assert_allclose(r.odom_speed, 3.0, atol=1e-6)
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


def test_flow_valid_height_range():
  """Flow samples are valid only within [flow_min_height, flow_max_height]; outside: zeros, flow_fresh 0."""
  cfg = _no_dropout(SensorConfig.drone())
  lo, hi = cfg.flow_min_height, cfg.flow_max_height
  for h, valid in ((0.5 * lo, False), (1.5 * lo, True), (10.0, True), (hi - 0.5, True), (hi + 0.5, False),
                   (3.0 * hi, False)):
    rs, _ = _run(cfg, _truth(pos=(0.0, 0.0, h), vel=(1.0, 0.0, 0.0)), jax.random.PRNGKey(2), 10)
    np.testing.assert_array_equal(np.asarray(rs.flow_fresh), (np.arange(10) % 2 == 0) * float(valid), err_msg=h)
    if not valid:
      np.testing.assert_array_equal(np.asarray(rs.flow), 0.0)


@pytest.fixture(scope="module")
def batch_first_readings():
  """One fresh sample from each of 4,000 independent sensor suites (default drone config), plus the truth."""
  n = 4000
  # white noise and IMU biases only: the per-episode flow and magnetometer errors have tests of their own
  cfg = _no_dropout(SensorConfig.drone(flow_scale_sigma=0.0, mag_hard_iron_sigma=0.0, mag_soft_iron_sigma=0.0))
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


# ---------------------------------------------------------------------------------------------------------------------
# Per-episode and correlated error models: their statistics match their SensorConfig parameters.

_N_EP = 4000


@functools.partial(jax.jit, static_argnums=(0,))
def _episodes(cfg, truth, key, surface=0):
  """_N_EP independent sensor suites: (their init states, one fresh reading each)."""
  def one(k):
    k0, k1 = jax.random.split(k)
    st = init_sensors(cfg, truth, k0, surface=surface)
    return st, sense(cfg, st, truth, k1, DT)[1]
  return jax.vmap(one)(jax.random.split(key, _N_EP))


def test_flow_scale_factor_spread():
  cfg = dataclasses.replace(SensorConfig.drone().noiseless(), flow_scale_sigma=0.05)
  t = _truth(vel=(2.0, -1.0, 0.0), euler=(0.0, 0.0, 0.0))
  st, r = _episodes(cfg, t, jax.random.PRNGKey(10))
  ratio = np.asarray(r.flow) * 10.0 / np.array([2.0, -1.0]) - 1.0     # measured / true flow - 1, [N, 2]
  np.testing.assert_allclose(ratio, np.asarray(st.flow_scale), atol=1e-5)
  np.testing.assert_allclose(ratio.std(0), 0.05, rtol=0.06)
  assert np.all(np.abs(ratio.mean(0)) < 0.005)
  assert abs(np.corrcoef(ratio.T)[0, 1]) < 0.06      # independent per axis


@pytest.mark.parametrize("surface", ["asphalt", "snow"])
def test_flow_dropout_rate_and_correlation(surface):
  """Share of invalid flow samples = the surface's dropout rate; lag-1 correlation of the dropout state =
  exp(-flow period / flow_dropout_tau)."""
  cfg = SensorConfig.drone()
  sid = SURFACES.index(surface)
  p = dict(cfg.flow_dropout)[surface]
  t = _truth(vel=(1.0, 0.0, 0.0))
  n_veh, n_ticks = 200, 400        # 200 samples per vehicle at 25 Hz

  @jax.jit
  def run(keys):
    def one(k):
      k0, k1 = jax.random.split(k)
      st = init_sensors(cfg, t, k0, surface=sid)
      _, rs = jax.lax.scan(lambda s, kk: sense(cfg, s, t, kk, DT), st, jax.random.split(k1, n_ticks))
      return rs.flow_fresh
    return jax.vmap(one)(keys)

  bad = 1.0 - np.asarray(run(jax.random.split(jax.random.PRNGKey(11), n_veh)))[:, ::2]   # flow samples [V, 200]
  assert abs(bad.mean() - p) < 0.03, (bad.mean(), p)
  rho = math.exp(-2 * DT / cfg.flow_dropout_tau)
  x = bad - bad.mean()
  lag1 = float(np.mean(x[:, 1:] * x[:, :-1]) / np.mean(x * x))
  assert abs(lag1 - rho) < 0.05, (lag1, rho)


def test_flow_dropout_rate_follows_the_world_surface():
  cfg = SensorConfig.drone()
  for i, name in enumerate(SURFACES):
    np.testing.assert_allclose(cfg.flow_dropout_rate(i), dict(cfg.flow_dropout)[name])
  rates = [float(cfg.flow_dropout_rate(SURFACES.index(s))) for s in ("grass", "asphalt", "snow", "water")]
  assert rates == sorted(rates) and rates[0] < 0.05 and rates[-1] > 0.5


def _mag_state(cfg, hard=(0.0, 0.0), soft=((1.0, 0.0), (0.0, 1.0)), dist=(0.0, 0.0)):
  st = _init(cfg, _truth(), jax.random.PRNGKey(0))
  f = lambda v: jnp.asarray(v, jnp.float32)
  return st.replace(mag_hard=f(hard), mag_soft=f(soft), mag_dist=f(dist))


def test_mag_hard_soft_iron_heading_error_curve():
  """Heading error vs heading: one cycle per turn (amplitude |b|) from hard iron b, two from soft iron; the per-episode
  draws have the configured spread."""
  cfg = SensorConfig.drone().noiseless()
  yaws = np.linspace(-3.0, 3.0, 25)
  read = jax.jit(jax.vmap(lambda st, y: _sense(cfg, st, _truth(euler=(0.0, 0.0, y)), jax.random.PRNGKey(1), DT)[1]
                          .mag_yaw, in_axes=(None, 0)))
  err = lambda st: (np.asarray(read(st, jnp.asarray(yaws, jnp.float32))) - yaws + np.pi) % (2 * np.pi) - np.pi
  # hard iron b = (0.05, 0.03) H: error = atan2(sin y - b_y, cos y + b_x) - y ~ -(b_y cos y + b_x sin y)
  b = np.array([0.05, 0.03])
  e = err(_mag_state(cfg, hard=b))
  np.testing.assert_allclose(e, np.arctan2(np.sin(yaws) - b[1], np.cos(yaws) + b[0]) - yaws, atol=1e-5)
  np.testing.assert_allclose(e, -(b[1] * np.cos(yaws) + b[0] * np.sin(yaws)), atol=3e-3)
  # soft iron diag(1 + k, 1 - k): error ~ -k sin(2 y), two cycles per turn
  k = 0.04
  e = err(_mag_state(cfg, soft=((1 + k, 0.0), (0.0, 1 - k))))
  np.testing.assert_allclose(e, -k * np.sin(2 * yaws), atol=3e-3)
  # per-episode draws
  cfg = dataclasses.replace(cfg, mag_hard_iron_sigma=0.05, mag_soft_iron_sigma=0.03)
  st, _ = _episodes(cfg, _truth(), jax.random.PRNGKey(12))
  np.testing.assert_allclose(np.asarray(st.mag_hard).std(0), 0.05, rtol=0.06)
  e_soft = np.asarray(st.mag_soft) - np.eye(2)
  np.testing.assert_allclose(e_soft.reshape(-1, 4).std(0), 0.03, rtol=0.06)
  np.testing.assert_array_equal(e_soft[:, 0, 1], e_soft[:, 1, 0])     # symmetric
  one = jax.tree.map(lambda x: x[0], st)
  np.testing.assert_allclose(err(one), np.asarray(jax.vmap(lambda y: mag_heading(y, one.mag_hard, one.mag_soft,
                                                                              jnp.zeros(2)))(yaws)) - yaws, atol=1e-5)


def test_mag_default_is_a_calibrated_compass_residual():
  """The default hard / soft iron are residuals after a compass calibration: over episodes and headings the heading
  error's RMS is sqrt(σ_b^2 + 0.75 σ_E^2) (sensors.SensorConfig) and about 1 deg, the accuracy quoted for a compensated
  strapdown compass; an uncalibrated compass (hard iron ~H) would be tens of degrees."""
  base = SensorConfig.drone()
  cfg = dataclasses.replace(base.noiseless(), mag_hard_iron_sigma=base.mag_hard_iron_sigma,
                            mag_soft_iron_sigma=base.mag_soft_iron_sigma)
  st, _ = _episodes(cfg, _truth(), jax.random.PRNGKey(16))
  yaws = jax.random.uniform(jax.random.PRNGKey(17), (_N_EP,), minval=-np.pi, maxval=np.pi)
  head = jax.jit(jax.vmap(mag_heading, in_axes=(0, 0, 0, None)))(yaws, st.mag_hard, st.mag_soft, jnp.zeros(2))
  err = (np.asarray(head) - np.asarray(yaws) + np.pi) % (2 * np.pi) - np.pi
  expect = math.hypot(base.mag_hard_iron_sigma, math.sqrt(0.75) * base.mag_soft_iron_sigma)
  assert abs(np.sqrt(np.mean(err ** 2)) / expect - 1.0) < 0.06, (np.sqrt(np.mean(err ** 2)), expect)
  assert math.radians(0.5) < expect < math.radians(2.0), math.degrees(expect)


def test_mag_disturbance_falls_off_with_distance():
  """A world-fixed disturbance δ (H) at distance d from a structure: heading error -atan2(δ_y, 1 + δ_x) with
  δ = mag_dist (mag_dist_ref / d)^3, i.e. 8x smaller per doubling of the distance; nothing far from structures."""
  cfg = SensorConfig.drone().noiseless()
  dist = np.array([0.3, 0.2])
  st = _mag_state(cfg, dist=dist)
  t = _truth(euler=(0.0, 0.0, 0.7))
  ds = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 30.0])
  e = np.array([float(_sense(cfg, st, t, jax.random.PRNGKey(1), DT, obstacle_distance=d)[1].mag_yaw) - 0.7
                for d in ds])
  delta = dist[None] * (cfg.mag_dist_ref / np.maximum(ds, cfg.mag_dist_min))[:, None] ** 3
  np.testing.assert_allclose(e, -np.arctan2(delta[:, 1], 1.0 + delta[:, 0]), atol=2e-6)
  np.testing.assert_allclose(e[3] / e[4], 8.0, rtol=0.02)
  assert abs(e[-1]) < 1e-4 and abs(e[0]) > 0.2
  _, r = _sense(cfg, st, t, jax.random.PRNGKey(1), DT)    # no obstacle distance: no disturbance
  np.testing.assert_allclose(r.mag_yaw, 0.7, atol=1e-6)
  # the per-episode disturbance's spread
  cfg = dataclasses.replace(cfg, mag_dist_sigma=1.0)
  st, _ = _episodes(cfg, _truth(), jax.random.PRNGKey(13))
  np.testing.assert_allclose(np.asarray(st.mag_dist).std(0), 1.0, rtol=0.06)


def test_gps_gauss_markov_stationary_sigma_and_autocorrelation():
  """Default GPS error: stationary σ as configured at every time, autocorrelation exp(-1) at lag τ."""
  cfg = SensorConfig.drone()
  t = _truth()
  dt, lag = 1.0, int(round(cfg.gps_drift_tau))          # 1 s ticks: the lag in ticks is τ / 1 s

  @jax.jit
  def run(keys):
    def one(k):
      k0, k1 = jax.random.split(k)
      st = init_sensors(cfg, t, k0)
      _, drift = jax.lax.scan(lambda s, kk: (lambda s2: (s2, s2.gps_drift))(sense(cfg, s, t, kk, dt)[0]), st,
                              jax.random.split(k1, 2 * lag))
      return drift
    return jax.vmap(one)(keys)

  drift = np.asarray(run(jax.random.split(jax.random.PRNGKey(14), 2000)))   # [V, 2 lag, 3]
  sig = np.array([cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_v])
  for k in (0, lag, 2 * lag - 1):
    np.testing.assert_allclose(drift[:, k].std(0), sig, rtol=0.06)
  x0, x1 = drift[:, 0] / sig, drift[:, lag] / sig
  acf = float(np.mean(x0 * x1))
  assert abs(acf - math.exp(-1.0)) < 0.05, acf
  assert cfg.gps_drift_sigma_h >= 1.5      # a u-blox M8-class receiver's metres, not decimetres


def test_odometry_slip_grows_with_lateral_acceleration():
  cfg = dataclasses.replace(SensorConfig.rover().noiseless(), odom_slip_peak=0.1, odom_slip_mu=0.9)
  key = jax.random.PRNGKey(0)
  for a_lat in (0.0, 1.0, 3.0, -6.0):
    t = _truth(pos=(0.0, 0.0, 0.2), vel=(4.0, 0.0, 0.0), euler=(0.0, 0.0, 0.0), acc=(0.0, a_lat, 0.0))
    _, r = _sense(cfg, _init(cfg, t, key), t, key, DT)
    np.testing.assert_allclose(r.odom_speed, 4.0 * (1.0 + 0.1 * abs(a_lat) / (0.9 * 9.81)), rtol=1e-5)
  # a yawed rover turning: the lateral acceleration is taken in the body frame
  yaw = 1.0
  acc = 2.0 * np.array([-np.sin(yaw), np.cos(yaw), 0.0])
  t = _truth(pos=(0.0, 0.0, 0.2), vel=4.0 * np.array([np.cos(yaw), np.sin(yaw), 0.0]), euler=(0.0, 0.0, yaw), acc=acc)
  _, r = _sense(cfg, _init(cfg, t, key), t, key, DT)
  np.testing.assert_allclose(r.odom_speed, 4.0 * (1.0 + 0.1 * 2.0 / (0.9 * 9.81)), rtol=1e-5)
  # per-episode scale error
  cfg = dataclasses.replace(cfg, odom_scale_sigma=0.01)
  t = _truth(pos=(0.0, 0.0, 0.2), vel=(4.0, 0.0, 0.0), euler=(0.0, 0.0, 0.0))
  st, r = _episodes(cfg, t, jax.random.PRNGKey(15))
  np.testing.assert_allclose(np.asarray(r.odom_speed) / 4.0 - 1.0, np.asarray(st.odom_scale), atol=1e-5)
  np.testing.assert_allclose(np.asarray(st.odom_scale).std(), 0.01, rtol=0.06)
