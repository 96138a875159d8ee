"""Sensor attacks: only the target sensor changes, timing/profile as scheduled, Table 3 ranges, env integration."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import attacks
from specguard_jax.types import SENSOR_NAMES, SensorReadings


def _readings():
  z = jnp.zeros(())
  return SensorReadings(gps_pos=jnp.array([1.0, 2.0, 3.0]), gps_vel=jnp.array([0.5, 0.0, 0.0]), gps_fresh=z + 1,
                        gyro=jnp.array([0.01, 0.02, 0.03]), accel=jnp.array([0.0, 0.0, 9.81]), mag_yaw=z + 0.3,
                        mag_fresh=z + 1, baro_alt=z + 15.0, baro_fresh=z + 1, flow=jnp.array([0.2, -0.1]),
                        flow_fresh=z + 1, odom_speed=z, odom_fresh=z)


FIELDS = {"gps": ("gps_pos", "gps_vel"), "gyro": ("gyro",), "accel": ("accel",), "mag": ("mag_yaw",),
          "baro": ("baro_alt",), "flow": ("flow",)}


@pytest.mark.parametrize("sensor", SENSOR_NAMES)
@pytest.mark.parametrize("profile", attacks.PROFILES)
def test_attack_changes_only_its_target(sensor, profile):
  bias = np.arange(1, attacks.BIAS_DIMS[sensor] + 1, dtype=np.float32) * 0.4
  s = attacks.schedule_for(sensor, bias, onset=10.0, duration=20.0, profile=profile, ramp_time=8.0)
  r = _readings()
  before = attacks.apply_attack(r, s, 9.99)
  during = attacks.apply_attack(r, s, 14.0)
  after = attacks.apply_attack(r, s, 30.0)
  for name in SensorReadings.__dataclass_fields__:
    x0 = np.asarray(getattr(r, name))
    np.testing.assert_array_equal(np.asarray(getattr(before, name)), x0)
    np.testing.assert_array_equal(np.asarray(getattr(after, name)), x0)
    if name not in FIELDS[sensor]:
      np.testing.assert_array_equal(np.asarray(getattr(during, name)), x0)
  frac = 1.0 if profile == "overt" else 4.0 / 8.0          # stealthy: half-way up its 8 s ramp at t = 14
  main = FIELDS[sensor][0]
  got = np.atleast_1d(np.asarray(getattr(during, main)) - np.asarray(getattr(r, main)))
  np.testing.assert_allclose(got, bias[:got.shape[0]] * frac, rtol=1e-5, atol=1e-6)
  if sensor == "gps":   # a ramping spoofer moves the fake velocity consistently; a constant one does not
    dv = np.asarray(during.gps_vel - r.gps_vel)
    np.testing.assert_allclose(dv, bias / 8.0 if profile == "stealthy" else 0 * bias, atol=1e-6)


def test_stealthy_ramp_is_gradual_and_saturates():
  s = attacks.schedule_for("baro", [8.0], onset=5.0, duration=100.0, profile="stealthy", ramp_time=16.0)
  ts = jnp.arange(0.0, 40.0, 0.5)
  b = jax.vmap(lambda t: attacks.bias_at(s, t)[0][4, 0])(ts)
  b = np.asarray(b)
  assert np.all(np.diff(b) >= -1e-6) and np.max(np.diff(b)) <= 8.0 / 16.0 * 0.5 + 1e-6
  assert b[ts < 5.0].max() == 0.0 and b[-1] == pytest.approx(8.0)


def test_sampled_attacks_follow_table3():
  cfg = attacks.AttackConfig()
  s = jax.vmap(lambda k: attacks.sample_attack(cfg, k, 120.0))(jax.random.split(jax.random.PRNGKey(0), 2000))
  mask, bias = np.asarray(s.mask), np.asarray(s.bias)
  assert np.all(mask.sum(-1) == 1)
  counts = mask.sum(0)
  assert np.all(counts > 200)                              # every sensor gets attacked
  for i, name in enumerate(SENSOR_NAMES):
    mag = np.linalg.norm(bias[mask[:, i] > 0, i], axis=-1)
    lo, hi = attacks.BIAS_RANGES[name]
    assert mag.min() >= lo * 0.999 and mag.max() <= hi * 1.001
    assert np.all(bias[:, i, attacks.BIAS_DIMS[name]:] == 0)
  assert set(np.unique(np.asarray(s.profile))) == {0, 1}
  onset = np.asarray(s.onset)
  assert onset.min() >= 0.15 * 120 - 1e-3 and onset.max() <= 0.5 * 120 + 1e-3
  two = jax.vmap(lambda k: attacks.sample_attack(attacks.AttackConfig(sensors=("gps", "gyro"), n_sensors=2), k,
                                                 60.0))(jax.random.split(jax.random.PRNGKey(1), 50))
  np.testing.assert_array_equal(np.asarray(two.mask)[:, :2], 1.0)
  assert np.asarray(two.mask)[:, 2:].sum() == 0


def test_bad_attack_specs_are_one_line_errors():
  with pytest.raises(ValueError, match="unknown sensor 'lidar'"):
    attacks.schedule_for("lidar", [1.0], 0, 1)
  with pytest.raises(ValueError, match="gps bias must have 3"):
    attacks.schedule_for("gps", [1.0], 0, 1)
  with pytest.raises(ValueError, match="unknown or no attack sensor"):
    attacks.AttackConfig(sensors=("gps", "sonar"))
  with pytest.raises(ValueError, match="n_sensors"):
    attacks.AttackConfig(sensors=("gps",), n_sensors=2)


def test_overt_gps_attack_in_env_is_gated_then_reset():
  """A 40 m overt GPS spoof enters before the EKF: EKF2-style gating rejects it (estimate stays near the truth),
  then after ~7 s of rejections the filter resets onto the spoofed position and the drone is dragged off its path."""
  import envs
  from envs import missions as missions_lib
  from envs import rollout
  env = envs.make("drone", world="open_beach", domain_randomization=False,
                  mission=missions_lib.MissionConfig.drone(max_duration_s=60.0, min_duration_s=40.0))
  s = attacks.schedule_for("gps", [40.0, 0.0, 0.0], onset=12.0, duration=100.0)
  batch = jax.tree.map(lambda x: jnp.stack([x, x]), s)
  state, traj, t = rollout.fly_batch(env, jax.random.split(jax.random.PRNGKey(2), 2), 300, attacks=batch)
  valid = np.asarray(traj["valid"])
  time = (np.arange(len(valid)) + 1) * env.dt
  # The estimate's move since the onset: before it, the EKF already sits on the GPS's slowly correlated error (metres,
  # sensors.SensorConfig.gps_drift_*, which nothing on board observes); what the spoof does is move it from there.
  d = (np.asarray(traj["est"]) - np.asarray(traj["pos"]))[:, :2]
  err = np.linalg.norm(d - d[np.flatnonzero(time < 12.0)[-1]], axis=-1)
  assert err[(time > 12.5) & (time < 18.0) & valid].max() < 3.0      # gated: the spoof is not believed
  assert err[(time > 21.0) & (time < 25.0) & valid].min() > 20.0     # reset to GPS after the 7 s timeout
  assert float(state.info["episode"]["attacked"][0]) == 1.0
  assert np.any(np.asarray(state.info["spec_robustness"]) < 0)      # no protection: specs get violated
