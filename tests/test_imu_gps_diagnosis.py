"""Sensor diagnosis of stealthy gyro and quick GPS ramps, closed loop in the env (RC + residual detector +
reconstruction, zero override = the autopilot flying on the reconstruction; issue #5): missions drawn exactly as
the former bench/gps_xcheck.py drew them (seed 7, its world set), picked from those an earlier diagnosis got wrong:
  * stealthy gyro ramps (roll/pitch, the magnetometer quiet) that were blamed on the ACCELEROMETER for the whole alarm
    (the wrong sensor replaced while the attitude drifted: all three crashed) must be blamed on the gyro once the
    diagnosis window is over;
  * quick stealthy GPS ramps that tripped the GPS-velocity CUSUM with an IMU-bias pattern and were first blamed on
    the accelerometer must be blamed on the GPS from the first tick, no IMU sensor blamed in the alarm's first 2 s.
One compile of a 5-mission batch, 30 s of flight."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import rollout
from specguard_jax import attacks

SEED, N_KEYS = 7, 64
WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")   # former bench/gps_xcheck.py
# (sensor, bench mission index): the earlier diagnosis blamed accel for the whole alarm (gyro) / accel first (gps)
ROWS = (("gyro", 44), ("gyro", 61), ("gyro", 36), ("gps", 18), ("gps", 31))
SECONDS = 30.0
GYRO, GPS = attacks.SENSOR_NAMES.index("gyro"), attacks.SENSOR_NAMES.index("gps")
IMU = (attacks.SENSOR_NAMES.index("gyro"), attacks.SENSOR_NAMES.index("accel"))


@pytest.fixture(scope="module")
def flights():
  env = envs.make("drone", worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5,
                  reconstruction=True, override_residual=True, override_frame="body")
  keys = jax.random.split(jax.random.PRNGKey(SEED), N_KEYS)[np.array([j for _, j in ROWS])]
  sensor = jnp.asarray([attacks.SENSOR_NAMES.index(s) for s, _ in ROWS])

  def one(key, si):   # the former bench/gps_xcheck.py's draw for a stealthy attack on sensor si
    return rollout.draw_paired_episode(env, key, (("gyro", "stealthy"), ("gps", "stealthy")),
                                       jnp.where(si == GYRO, 0, 1))

  @jax.jit
  def run(keys, sensor):
    s = jax.vmap(one)(keys, sensor)
    zero = jnp.zeros((keys.shape[0], 3))

    def body(s, _):
      nx = jax.vmap(env.step)(s, zero)
      return nx, dict(t=nx.info["time"], alarm=nx.info["alarm"] > 0, diag=nx.info["diagnosis"], done=nx.done > 0)

    s, out = jax.lax.scan(body, s, None, length=int(round(SECONDS / env.dt)))
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out), s.info["attack"].onset

  out, onset = jax.device_get(run(keys, sensor))
  return env, out, onset


def _first_alarm(out, onset, i):
  hit = out["alarm"][i] & (out["t"][i] >= onset[i]) & ~out["done"][i]
  assert hit.any(), f"row {ROWS[i]}: no alarm within {SECONDS} s (onset {onset[i]:.1f} s)"
  return int(np.argmax(hit))


_NO_ALARM = pytest.mark.xfail(strict=False, reason="with the presets recalibrated for the realistic sensors the first "
                              "stealthy gyro ramp raises no alarm within the test's window (gyro_z h 28.2, gyro_x/y "
                              "102-121)")
_GYRO_ROWS = [k for k, (s, _) in enumerate(ROWS) if s == "gyro"]


@pytest.mark.parametrize("i", [pytest.param(k, marks=_NO_ALARM) if k == _GYRO_ROWS[0] else k for k in _GYRO_ROWS])
def test_stealthy_gyro_ramp_blamed_on_the_gyro(flights, i):
  env, out, onset = flights
  k = _first_alarm(out, onset, i)
  settled = k + int(round((env.det_cfg.diag_window_s + 0.2) / env.dt))   # after the diagnosis window
  seq = out["diag"][i][k:settled + 1]
  assert out["alarm"][i][settled] and int(out["diag"][i][settled]) == GYRO, (ROWS[i], seq.tolist())


GPS_ROWS = [k for k, (s, _) in enumerate(ROWS) if s == "gps"]


@pytest.mark.parametrize("i", GPS_ROWS)
def test_quick_gps_ramp_not_blamed_on_an_imu_sensor(flights, i):
  """A ramp still under the GPS's own slowly correlated error (metres, sensors.SensorConfig.gps_drift_*) when the
  flight ends may raise no alarm: nothing is blamed then, which is right; `test_a_quick_gps_ramp_is_flagged` keeps
  the rows from all going quiet."""
  env, out, onset = flights
  if not (out["alarm"][i] & (out["t"][i] >= onset[i]) & ~out["done"][i]).any():
    assert not out["alarm"][i].any(), ROWS[i]
    return
  k = _first_alarm(out, onset, i)
  seq = out["diag"][i][k:k + int(round(2.0 / env.dt))]
  seq = seq[out["alarm"][i][k:k + len(seq)]]
  assert int(seq[0]) == GPS, (ROWS[i], seq.tolist())
  assert not np.isin(seq, IMU).any(), (ROWS[i], seq.tolist())


def test_a_quick_gps_ramp_is_flagged(flights):
  """At least one of the quick GPS ramps raises the alarm within the flight (the diagnosis test above is exercised)."""
  env, out, onset = flights
  assert any((out["alarm"][i] & (out["t"][i] >= onset[i]) & ~out["done"][i]).any() for i in GPS_ROWS)
