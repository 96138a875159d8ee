"""Residual CUSUM detector on real env ticks: false positives, overt/stealthy detection and diagnosis, oracle, switch."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.missions import MissionConfig
from specguard_jax import attacks
from specguard_jax import detection
from specguard_jax.detection import traces
from specguard_jax.types import SENSOR_NAMES

DT = 0.02
N_TICKS = 2000          # 40 s per mission
N_CAL, N_FREE = 12, 8
ONSET, DURATION = 20.0, 8.0
TARGET_FPR = 0.125      # per mission: at most 1 of the 8 held-out attack-free missions
OVERT = {"gps": [20.0, 10.0, 2.0], "gyro": [0.0, 0.0, 1.0], "accel": [0.0, 0.0, 3.0], "mag": [2.0], "baro": [8.0],
         "flow": [2.0, 0.0]}
STEALTHY = {"gps": [30.0, 0.0, 0.0], "baro": [8.0]}


def _stack(xs):
  return jax.tree.map(lambda *x: jnp.stack(x), *xs)


@pytest.fixture(scope="module")
def run():
  env = envs.make("drone", mission=MissionConfig.drone(max_duration_s=70.0, min_duration_s=45.0))
  cells = ([("none", None)] * (N_CAL + N_FREE) + [(s, "overt") for s in OVERT] + [(s, "stealthy") for s in STEALTHY])
  sched = []
  for s, p in cells:
    if s == "none":
      sched.append(attacks.no_attack())
    else:
      bias = OVERT[s] if p == "overt" else STEALTHY[s]
      sched.append(attacks.schedule_for(s, bias, ONSET, DURATION, p, ramp_time=20.0))
  atk = _stack(sched)
  tr = traces.record_ticks(env, jax.random.split(jax.random.PRNGKey(42), len(cells)), atk, N_TICKS)
  cal = jax.tree.map(lambda x: x[:N_CAL], tr)
  rest = jax.tree.map(lambda x: x[N_CAL:], tr)
  base = detection.DetectorConfig.drone(calibrated=False)
  r, f = traces.residual_trace(base, cal, DT)
  cfg = detection.calibrate(base, r, f, TARGET_FPR)
  out = jax.device_get(traces.run_detector(cfg, rest, DT))
  rest_atk = jax.tree.map(lambda x: x[N_CAL:], atk)
  win = int(round(cfg.diag_window_s / DT))
  m = jax.device_get(traces.detection_metrics(out["alarm"], out["diagnosis"], rest, rest_atk, win))
  names = [f"{s}/{p}" for s, p in cells[N_CAL:]]
  return {"cfg": cfg, "out": out, "m": m, "names": names, "valid": np.asarray(rest.valid),
          "time": np.asarray(rest.time)}


def _idx(run, name):
  return run["names"].index(name)


def test_calibration_is_finite_and_positive(run):
  cfg = run["cfg"]
  assert len(cfg.h) == detection.N_CHANNELS and len(cfg.scale) == detection.N_CHANNELS
  assert all(np.isfinite(cfg.h)) and min(cfg.h) >= cfg.h_min
  assert all(s > 0 for s in cfg.scale)
  assert cfg.used[detection.CHANNELS.index("odom")] == 0   # the drone has no odometry


def test_false_positive_rate_at_most_target(run):
  alarm = run["out"]["alarm"][:N_FREE] & run["valid"][:N_FREE]
  fpr = np.mean(np.any(alarm, axis=-1))
  assert fpr <= TARGET_FPR, fpr
  # No pre-onset alarm on the attacked missions either (they fly attack-free until ONSET).
  assert not np.any(run["m"]["false_alarm"][N_FREE:])


@pytest.mark.parametrize("sensor", list(OVERT))
def test_overt_attack_detected_and_diagnosed(run, sensor):
  i = _idx(run, f"{sensor}/overt")
  m = run["m"]
  assert m["detected"][i], sensor
  assert m["delay"][i] < 1.5, (sensor, m["delay"][i])
  assert m["correct"][i], (sensor, SENSOR_NAMES[int(run["out"]["diagnosis"][i][int(round((ONSET + m["delay"][i]
                                                                                                + 1.0) / DT))])])


@pytest.mark.parametrize("sensor", list(STEALTHY))
def test_stealthy_attack_stays_under_threshold_longer(run, sensor):
  m = run["m"]
  i, j = _idx(run, f"{sensor}/stealthy"), _idx(run, f"{sensor}/overt")
  d_stealthy = m["delay"][i] if m["detected"][i] else np.inf
  assert d_stealthy > max(0.3, 3 * m["delay"][j]), (d_stealthy, m["delay"][j])


def test_switch_hands_back_after_attack(run):
  """After an overt attack ends, every score drops below clear_frac and the alarm clears after hold_s."""
  cfg, out = run["cfg"], run["out"]
  handed_back = []
  for s in OVERT:
    i = _idx(run, f"{s}/overt")
    alarm, t, valid = out["alarm"][i], run["time"][i], run["valid"][i]
    if not valid[-1]:
      continue   # the attack crashed the vehicle (e.g. gyro)
    during = alarm[(t > ONSET + 1.5) & (t < ONSET + DURATION)]
    assert during.all(), s                       # latched while the attack is on
    after = (t >= ONSET + DURATION)
    cleared = np.nonzero(after & ~alarm)[0]
    if cleared.size:
      t_clear = t[cleared[0]]
      assert t_clear >= ONSET + DURATION + cfg.hold_s - DT, (s, t_clear)
      assert not alarm[cleared[0]:].any(), s     # stays handed back
      handed_back.append(s)
  assert {"mag", "flow"} <= set(handed_back), handed_back


def test_oracle_delay_exact():
  s = attacks.schedule_for("baro", [5.0], onset=10.0, duration=6.0)
  ts = jnp.arange(0, 1500) * DT

  def scan(delay, hold):
    def body(st, t):
      st = detection.oracle_update(st, s, t, DT, delay=delay, hold_s=hold)
      return st, (st.alarm, st.diagnosis, st.mask)
    return jax.lax.scan(body, detection.detector_init(detection.DetectorConfig()), ts)[1]

  for delay in (0.0, 0.5, 1.3):
    alarm, diag, mask = jax.device_get(scan(delay, 0.0))
    t = np.asarray(ts)
    expect = (t - delay >= 10.0) & (t - delay < 16.0)
    np.testing.assert_array_equal(alarm, expect)
    on = np.nonzero(alarm)[0]
    assert t[on[0]] == pytest.approx(10.0 + delay, abs=DT)
    assert np.all(diag[alarm] == SENSOR_NAMES.index("baro")) and np.all(diag[~alarm] == -1)
    np.testing.assert_array_equal(mask[alarm].argmax(-1), SENSOR_NAMES.index("baro"))
  alarm, _, _ = jax.device_get(scan(0.5, 2.0))
  t = np.asarray(ts)
  np.testing.assert_array_equal(alarm, (t >= 10.5) & (t < 18.5))


def test_switch_unit_hold_and_clear():
  """Synthetic scores: alarm on a spike, latched, cleared exactly hold_s after all scores fall below clear_frac."""
  cfg = detection.DetectorConfig.drone(hold_s=1.0)
  from specguard_jax.detection import detector as det
  st = det.detector_init(cfg)
  hi = jnp.zeros(detection.N_CHANNELS).at[detection.CHANNELS.index("mag")].set(2.0)
  lo = jnp.zeros(detection.N_CHANNELS)
  seq = [hi] * 10 + [lo] * 100
  alarms, diags = [], []
  for sc in seq:
    sw = det._switch(cfg, st, sc, jnp.any(sc > 1.0), DT)
    st = st.replace(**sw)
    alarms.append(bool(st.alarm))
    diags.append(int(st.diagnosis))
  alarms = np.asarray(alarms)
  assert alarms[:10].all() and diags[0] == SENSOR_NAMES.index("mag")
  off = np.nonzero(~alarms)[0][0]
  assert (off - 10) * DT == pytest.approx(cfg.hold_s, abs=1.5 * DT)
  assert diags[-1] == -1


def test_detector_update_is_jittable_and_vmappable(run):
  cfg = run["cfg"]
  n = 3
  st = jax.vmap(lambda _: detection.detector_init(cfg))(jnp.arange(n))
  from specguard_jax import ekf as ekf_lib
  from specguard_jax.types import SensorReadings
  z = jnp.zeros((n,))
  rd = SensorReadings(gps_pos=jnp.zeros((n, 3)), gps_vel=jnp.zeros((n, 3)), gps_fresh=z + 1, gyro=jnp.zeros((n, 3)),
                      accel=jnp.tile(jnp.array([0.0, 0.0, 9.81]), (n, 1)), mag_yaw=z, mag_fresh=z + 1,
                      baro_alt=z + 10, baro_fresh=z + 1, flow=jnp.zeros((n, 2)), flow_fresh=z, odom_speed=z,
                      odom_fresh=z)
  ek = jax.vmap(lambda r: ekf_lib.ekf_init(ekf_lib.EKFConfig.drone(), r))(rd)
  act = jnp.full((n, 4), 1.5 * 9.81 / 4)
  f = jax.jit(jax.vmap(lambda s, r, e, a: detection.detector_update(cfg, s, r, e, a, DT)))
  st = f(st, rd, ek, act)
  assert st.scores.shape == (n, detection.N_CHANNELS) and st.alarm.shape == (n,)
  assert np.all(np.isfinite(np.asarray(st.scores)))
