"""Reconstruction with a replaced IMU sensor (constructed hover, shipped drone dynamics model): the shadow's
accel-bias state restarts to learn the model's error when the accelerometer is blamed, and on hand-back the replaced
sensors' bias states return to the last trusted estimate and the real readings come back."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from specguard_jax.estimation import model_file, recon
from specguard_jax.types import SENSOR_NAMES, SensorReadings

DT = 0.02
N_PRE, N_ALARM = 60, 100            # ticks before the alarm, ticks with the alarm up; then one hand-back tick
BIAS_A = np.array([0.05, -0.03, 0.02], np.float32)   # the autopilot EKF's (trusted) accel-bias estimate, m/s^2
BIAS_G = np.array([0.004, -0.002, 0.001], np.float32)


def _readings(k):
  f = lambda x: jnp.asarray(x, jnp.float32)
  return SensorReadings(gps_pos=f([0.0, 0.0, 10.0]), gps_vel=f([0.0, 0.0, 0.0]), gps_fresh=f(k % 5 == 0),
                        gyro=f([0.0, 0.0, 0.0]), accel=f([0.0, 0.0, 9.81]), mag_yaw=f(0.3), mag_fresh=f(k % 2 == 0),
                        baro_alt=f(10.0), baro_fresh=f(k % 2 == 0), flow=f([0.0, 0.0]), flow_fresh=f(k % 2 == 0),
                        odom_speed=f(0.0), odom_fresh=f(0.0))


@pytest.fixture(scope="module")
def flights():
  """{blamed sensor: per-tick (shadow accel bias, its P diagonal, trusted EKF, trusted readings)} of a hover with the
  alarm up for N_ALARM ticks blaming that sensor."""
  cfg = recon.ReconConfig(n_controls=4, ekf=ekf_lib.EKFConfig.drone())
  params = model_file.load_params(model_file.default_path("drone"), 4)
  e0 = ekf_lib.ekf_init(cfg.ekf, _readings(0)).replace(accel_bias=jnp.asarray(BIAS_A), gyro_bias=jnp.asarray(BIAS_G))
  controls = jnp.full((4,), 1.5 * 9.81 / 4)
  tick = jax.jit(lambda st, rd, mask, alarm: recon.recon_tick(cfg, params, st, e0, rd, controls, mask, alarm, DT))
  out = {}
  for name in ("accel", "gyro", "gps"):
    mask = jnp.zeros(len(SENSOR_NAMES)).at[SENSOR_NAMES.index(name)].set(1.0)
    st = recon.recon_init(cfg, e0)
    rows = []
    for k in range(N_PRE + N_ALARM + 1):
      alarm = jnp.asarray(N_PRE <= k < N_PRE + N_ALARM)
      rd = _readings(k)
      st, _, est, rd_ctrl = tick(st, rd, jnp.where(alarm, mask, 0.0), alarm)
      rows.append((np.asarray(st.shadow.accel_bias), np.diag(np.asarray(st.shadow.P)), est, rd_ctrl, rd))
    out[name] = rows
  return cfg, out


def test_accel_bias_state_restarts_when_the_accelerometer_is_replaced(flights):
  cfg, out = flights
  first = out["accel"][N_PRE]
  assert np.abs(first[0]).max() < 0.02, first[0]                     # restarted at zero, not the sensor's estimate
  assert first[1][12:15].min() > 0.5 * cfg.model_accel_sigma ** 2, first[1][12:15]
  # blaming the GPS leaves the accel-bias state alone
  np.testing.assert_allclose(out["gps"][N_PRE][0], BIAS_A, atol=0.02)
  # while the accelerometer is replaced the controller reads the model's specific force, not the sensor
  during = out["accel"][N_PRE + 10]
  assert not np.allclose(np.asarray(during[3].accel), np.asarray(during[4].accel))


@pytest.mark.parametrize("name", ["accel", "gyro"])
def test_hand_back_restores_the_replaced_sensors_bias(flights, name):
  cfg, out = flights
  est, rd_ctrl, rd = out[name][-1][2], out[name][-1][3], out[name][-1][4]
  ecfg = cfg.ekf_cfg()
  if name == "accel":
    np.testing.assert_allclose(np.asarray(est.accel_bias), BIAS_A, atol=1e-6)
    np.testing.assert_allclose(np.diag(np.asarray(est.P))[12:15], ecfg.init_accel_bias_sigma ** 2, rtol=1e-5)
  else:
    np.testing.assert_allclose(np.asarray(est.gyro_bias), BIAS_G, atol=1e-6)
    np.testing.assert_allclose(np.diag(np.asarray(est.P))[9:12], ecfg.init_gyro_bias_sigma ** 2, rtol=1e-5)
  # the sensors' own readings come back on the hand-back tick
  np.testing.assert_array_equal(np.asarray(rd_ctrl.accel), np.asarray(rd.accel))
  np.testing.assert_array_equal(np.asarray(rd_ctrl.gyro), np.asarray(rd.gyro))


def test_shadow_without_gps_rows_between_gps_samples_is_the_same():
  """recon_tick(gps_due=...) (the env's schedule: the shadow filter leaves the GPS rows out where no GPS sample can be
  fresh) gives the reconstruction of the full shadow update, alarm up (the shadow runs) blaming the gyro."""
  cfg = recon.ReconConfig(n_controls=4, ekf=ekf_lib.EKFConfig.drone())
  params = model_file.load_params(model_file.default_path("drone"), 4)
  e0 = ekf_lib.ekf_init(cfg.ekf, _readings(0))
  controls = jnp.full((4,), 1.5 * 9.81 / 4)
  mask = jnp.zeros(len(SENSOR_NAMES)).at[SENSOR_NAMES.index("gyro")].set(1.0)
  tick = jax.jit(lambda st, rd, due: recon.recon_tick(cfg, params, st, e0, rd, controls, mask, True, DT, None, due))
  full = jax.jit(lambda st, rd: recon.recon_tick(cfg, params, st, e0, rd, controls, mask, True, DT))
  a = b = recon.recon_init(cfg, e0)
  for k in range(1, 16):
    rd = _readings(k)
    a = tick(a, rd, jnp.asarray(k % 5 == 0))
    b = full(b, rd)
    xa, xb = a[1], b[1]
    a, b = a[0], b[0]
    np.testing.assert_allclose(np.asarray(xa), np.asarray(xb), rtol=1e-6, atol=1e-7)
  for name in ("pos", "vel", "quat", "P", "innov", "gps_pos_age"):
    np.testing.assert_allclose(np.asarray(getattr(a.shadow, name)), np.asarray(getattr(b.shadow, name)), rtol=1e-6,
                               atol=1e-7, err_msg=name)
  assert "cond" in str(jax.make_jaxpr(lambda st, rd, due: recon.recon_tick(
      cfg, params, st, e0, rd, controls, mask, True, DT, None, due))(a, _readings(1), True))
