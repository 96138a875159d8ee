"""Reconstruction with the gyroscope blamed (constructed flights, shipped drone dynamics model; then one closed-loop
stealthy gyro ramp in the env). A slow gyro ramp drags the autopilot's attitude before the alarm: the shadow must not
start from that attitude (re-levelled from the GPS-derived acceleration and the model's specific force, yaw from the
magnetometer), the model rate's correction must not saturate over a long alarm, and a gyro blamed for longer than
ReconConfig.sticky_after_s stays replaced when the diagnosis later moves to another sensor (a shorter, transient blame
does not)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.missions import MissionConfig
from specguard_jax import attacks, math3d
from specguard_jax import ekf as ekf_lib
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.estimation import model_file, recon
from specguard_jax.types import SENSOR_NAMES, SensorReadings

DT = 0.02
N_PRE = 75                                   # ticks before the alarm (1.5 s: the gravity reference settles)
TRUE_EUL = np.array([0.10, -0.15, 0.30])     # the vehicle's true attitude (rad)
DRAG_EUL = np.array([0.40, -0.25, 0.80])     # what the spoofed gyro added to the autopilot's estimate (rad)
HOVER = 1.5 * 9.81 / 4                       # N per rotor


def _mask(*names):
  return jnp.asarray([float(n in names) for n in SENSOR_NAMES])


def _tilt_err(q, eul):
  z_est = np.asarray(math3d.quat_to_rot(q))[:, 2]
  z_true = np.asarray(math3d.quat_to_rot(math3d.euler_to_quat(jnp.asarray(eul, jnp.float32))))[:, 2]
  return float(np.degrees(np.arccos(np.clip(z_est @ z_true, -1, 1))))


@pytest.fixture(scope="module")
def setup():
  cfg = recon.ReconConfig(n_controls=4, ekf=ekf_lib.EKFConfig.drone())
  params = model_file.load_params(model_file.default_path("drone"), 4)
  tick = jax.jit(lambda st, e, rd, u, mask, alarm: recon.recon_tick(cfg, params, st, e, rd, u, mask, alarm, DT))
  return cfg, params, tick


def _tilted_flight(params, k, mag_bias=0.0):
  """Readings of a vehicle holding TRUE_EUL under hover thrust: it accelerates along R f + g (f: the model's
  specific force of that thrust), GPS velocity at 10 Hz, magnetometer heading TRUE_EUL[2]."""
  q = math3d.euler_to_quat(jnp.asarray(TRUE_EUL, jnp.float32))
  u = jnp.full((4,), HOVER)
  f = dyn.specific_force(params, dyn.DynState(jnp.zeros(3), jnp.zeros(3), q, jnp.zeros(3)), u)
  a = math3d.quat_to_rot(q) @ f + dyn.G
  t = k * DT
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  rd = SensorReadings(gps_pos=f32([0.0, 0.0, 20.0]) + 0.5 * a * t * t, gps_vel=a * (t - (k % 5) * DT),
                      gps_fresh=f32(k % 5 == 0), gyro=f32([0.0, 0.0, 0.0]), accel=f,
                      mag_yaw=f32(TRUE_EUL[2] + mag_bias),
                      mag_fresh=f32(1.0), baro_alt=f32(20.0), baro_fresh=f32(k % 2 == 0), flow=f32([0.0, 0.0]),
                      flow_fresh=f32(0.0), odom_speed=f32(0.0), odom_fresh=f32(0.0))
  return rd, u, a


@pytest.fixture(scope="module")
def relevel(setup):
  """{blamed sensor: shadow after the alarm tick} of the tilted flight, the autopilot's EKF dragged by DRAG_EUL."""
  cfg, params, tick = setup
  rd0, u, _ = _tilted_flight(params, 0)
  e = ekf_lib.ekf_init(cfg.ekf, rd0).replace(
      quat=math3d.euler_to_quat(jnp.asarray(TRUE_EUL + DRAG_EUL, jnp.float32)))
  out = {}
  for name, mag_bias in (("gyro", 0.0), ("gps", 0.0), ("gyro+spoofed mag", np.pi)):
    st = recon.recon_init(cfg, e)
    for k in range(N_PRE + 1):
      rd, u, _ = _tilted_flight(params, k, mag_bias * (k == N_PRE))   # the magnetometer spoofed on the alarm tick
      alarm = jnp.asarray(k == N_PRE)
      st, _, _, _ = tick(st, e, rd, u, jnp.where(alarm, _mask(name.split("+")[0]), 0.0), alarm)
    out[name] = st.shadow
  return cfg, out


def test_newly_blamed_gyro_relevels_the_dragged_attitude(relevel):
  cfg, out = relevel
  sh = out["gyro"]
  assert _tilt_err(sh.quat, TRUE_EUL) < 3.0, _tilt_err(sh.quat, TRUE_EUL)     # the checkpoint's: ~33 deg
  yaw = float(math3d.quat_to_euler(sh.quat)[2])
  assert abs(yaw - TRUE_EUL[2]) < 0.05, yaw                                     # the magnetometer's heading
  p = np.diag(np.asarray(sh.P))
  assert p[6] > 0.5 * cfg.relevel_tilt_sigma ** 2 and p[7] > 0.5 * cfg.relevel_tilt_sigma ** 2, p[6:9]
  # blaming another sensor leaves the (checkpoint's) attitude alone
  assert _tilt_err(out["gps"].quat, TRUE_EUL) > 20.0


def test_relevel_keeps_the_heading_when_the_magnetometer_is_spoofed_too(relevel):
  """Gyro and magnetometer spoofed together, the diagnosis naming only the gyro (the red team's attack on DeLorean):
  a magnetometer 180 deg off the true heading (134 deg off the shadow's, beyond ReconConfig.relevel_mag_gate) must not
  set it; the tilt is still re-levelled from the gravity reference. With the spoofed heading the autopilot flies
  reversed and flips."""
  cfg, out = relevel
  sh = out["gyro+spoofed mag"]
  yaw = float(math3d.quat_to_euler(sh.quat)[2])
  assert abs(yaw - (TRUE_EUL[2] + DRAG_EUL[2])) < 0.05, yaw                    # the shadow's (dragged) heading
  assert DRAG_EUL[2] < cfg.relevel_mag_gate < np.pi / 2                         # the honest case above is inside
  assert _tilt_err(sh.quat, TRUE_EUL) < 3.0, _tilt_err(sh.quat, TRUE_EUL)
  # the heading's variance is reset to the initial one, not to the magnetometer's noise (as when it is taken)
  p_yaw, ecfg = float(np.diag(np.asarray(sh.P))[8]), cfg.ekf_cfg()
  assert 0.5 * ecfg.init_yaw_sigma ** 2 < p_yaw < 2 * ecfg.init_yaw_sigma ** 2, p_yaw
  assert float(np.diag(np.asarray(out["gyro"].P))[8]) < 0.5 * ecfg.init_yaw_sigma ** 2


@pytest.mark.parametrize("n_pre", [5, 10, 11, N_PRE])
def test_relevel_trusts_a_far_magnetometer_only_before_a_trusted_checkpoint(setup, n_pre):
  """A gyro attack from take-off drags the heading 86 deg (beyond relevel_mag_gate) before an alarm n_pre ticks in:
  up to lag (10) ticks the ring holds no checkpoint `lag` entries old, so the shadow's heading is no reference and the
  (honest) magnetometer's is taken. From lag + 1 ticks the same disagreement reads as a spoofed magnetometer: the
  heading is kept."""
  cfg, params, tick = setup
  drag = np.array([0.0, 0.0, 1.5])
  rd0, _, _ = _tilted_flight(params, 0)
  e = ekf_lib.ekf_init(cfg.ekf, rd0).replace(quat=math3d.euler_to_quat(jnp.asarray(TRUE_EUL + drag, jnp.float32)))
  st = recon.recon_init(cfg, e)
  for k in range(n_pre + 1):
    rd, u, _ = _tilted_flight(params, k)
    alarm = jnp.asarray(k == n_pre)
    st, _, _, _ = tick(st, e, rd, u, jnp.where(alarm, _mask("gyro"), 0.0), alarm)
  assert drag[2] > cfg.relevel_mag_gate and cfg.lag_ticks == 10
  yaw = float(math3d.quat_to_euler(st.shadow.quat)[2])
  assert abs(yaw - (TRUE_EUL[2] if n_pre <= cfg.lag_ticks else TRUE_EUL[2] + drag[2])) < 0.05, yaw


def test_model_rate_correction_does_not_saturate_over_a_long_alarm(setup):
  """Level hover, gyro blamed for 8 s, one rotor's thrust 0.2 N above the others: the model predicts a steady roll
  acceleration the vehicle does not have (its true rates are zero, the aiding says level), so the shadow keeps
  correcting the model rate. The correction must not walk into the clamp and let the attitude go."""
  cfg, params, tick = setup
  f32 = lambda x: jnp.asarray(x, jnp.float32)

  def rd_at(k):
    return SensorReadings(gps_pos=f32([0.0, 0.0, 20.0]), gps_vel=f32([0.0, 0.0, 0.0]), gps_fresh=f32(k % 5 == 0),
                          gyro=f32([0.3, -0.2, 0.1]), accel=f32([0.0, 0.0, 9.81]), mag_yaw=f32(0.3),
                          mag_fresh=f32(1.0), baro_alt=f32(20.0), baro_fresh=f32(k % 2 == 0), flow=f32([0.0, 0.0]),
                          flow_fresh=f32(0.0), odom_speed=f32(0.0), odom_fresh=f32(0.0))

  e = ekf_lib.ekf_init(cfg.ekf, rd_at(0))
  u = jnp.full((4,), HOVER).at[0].add(0.2)
  st = recon.recon_init(cfg, e)
  level = np.array([0.0, 0.0, 0.3])
  errs, gbias = [], []
  for k in range(10 + 400):
    alarm = jnp.asarray(k >= 10)
    st, _, est, rd_ctrl = tick(st, e, rd_at(k), u, jnp.where(alarm, _mask("gyro"), 0.0), alarm)
    if k >= 10:
      errs.append(_tilt_err(est.quat, level))
      gbias.append(np.abs(np.asarray(est.gyro_bias)).max())
      assert not np.allclose(np.asarray(rd_ctrl.gyro), [0.3, -0.2, 0.1])      # the spoofed gyro is not flown on
  assert max(errs[-150:]) < 10.0, max(errs[-150:])
  assert max(gbias) < 0.9 * cfg.model_rate_limit, max(gbias)


def _gyro_then_gps(setup, n_gyro):
  """Gyro blamed for n_gyro ticks from the alarm, then the GPS; yields (trusted readings) of the GPS-blamed ticks."""
  cfg, params, tick = setup
  rd0, u, _ = _tilted_flight(params, 0)
  e = ekf_lib.ekf_init(cfg.ekf, rd0)
  st = recon.recon_init(cfg, e)
  for k in range(N_PRE + n_gyro + 20):
    rd, u, _ = _tilted_flight(params, k)
    rd = rd.replace(gyro=jnp.asarray([0.5, 0.0, 0.0], jnp.float32))
    alarm = jnp.asarray(k >= N_PRE)
    mask = jnp.where(alarm, jnp.where(k < N_PRE + n_gyro, _mask("gyro"), _mask("gps")), 0.0)
    st, _, _, rd_ctrl = tick(st, e, rd, u, mask, alarm)
    if k >= N_PRE + n_gyro:
      yield rd_ctrl


def test_blamed_gyro_stays_replaced_when_the_diagnosis_moves(setup):
  cfg = setup[0]
  n = int(np.ceil(cfg.sticky_after_s / DT)) + 5   # blamed longer than sticky_after_s
  for rd_ctrl in _gyro_then_gps(setup, n):
    assert not np.allclose(np.asarray(rd_ctrl.gyro), [0.5, 0.0, 0.0])        # still the model's rate
    assert float(rd_ctrl.gps_fresh) == 0.0                                    # and the newly blamed GPS is out


def test_transient_gyro_blame_does_not_stick(setup):
  """A gyro blamed for a few ticks only (a quick GPS ramp's first ticks, issue #5) is not kept replaced: the
  shadow flies on the gyro again once the diagnosis has moved to the GPS."""
  cfg = setup[0]
  n = max(1, int(cfg.sticky_after_s / DT) // 3)
  for rd_ctrl in _gyro_then_gps(setup, n):
    np.testing.assert_allclose(np.asarray(rd_ctrl.gyro), [0.5, 0.0, 0.0])    # the sensor's rate
    assert float(rd_ctrl.gps_fresh) == 0.0
