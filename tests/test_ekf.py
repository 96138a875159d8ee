"""EKF on analytic truth trajectories with noisy sensors: accuracy, gating, GPS timeout reset, ramp drag, rng, vmap."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax.ekf import CH, CHANNELS, EKFConfig, ekf_body_rates, ekf_euler, ekf_init, ekf_std, ekf_step
from specguard_jax.math3d import euler_to_quat, quat_to_rot
from specguard_jax.sensors import SensorConfig, init_sensors, sense
from specguard_jax.types import SensorReadings, TrueState

DT = 0.02


# ----------------------------------------------------------------------------------------------------------------------
# analytic truth: position and yaw as functions of t; velocity/acceleration by autodiff; a multicopter's attitude
# aligns body z with the thrust direction (acc - g) at the given yaw; a rover stays level; body rates from dR/dt.


def _trajectory(p, t):
  """Parametric position and yaw at time t (s). p [9]: x0, y0, z0, radius, omega, vx, vz, yaw0, yaw_follow.

  Horizontal circle of the given radius whose angular rate ramps from 0 to omega as 1 - exp(-(t / 4 s)^2) (starts at
  rest with zero acceleration, like a vehicle on the ground), plus a constant eastward speed vx and a climb whose rate
  ramps to vz; yaw = yaw0 + yaw_follow * circle angle.
  """
  tau = 4.0
  phi = p[4] * (t - tau * 0.5 * math.sqrt(math.pi) * jax.lax.erf(t / tau))
  pos = jnp.stack([p[0] + p[3] * (jnp.cos(phi) - 1.0) + p[5] * t, p[1] + p[3] * jnp.sin(phi),
                   p[2] + p[6] * (jnp.sqrt(1.0 + t * t) - 1.0)])
  return pos, p[7] + p[8] * phi


def _truth_at(p, t, rover):
  pos_fn = lambda t: _trajectory(p, t)[0]
  d1 = jax.jacfwd(pos_fn)
  d2 = jax.jacfwd(d1)

  def quat(t):
    psi = _trajectory(p, t)[1]
    if rover:
      return euler_to_quat(jnp.stack([0.0 * psi, 0.0 * psi, psi]))
    zb = d2(t) + jnp.array([0.0, 0.0, 9.81])
    zb = zb / jnp.linalg.norm(zb)
    c, s = jnp.cos(psi), jnp.sin(psi)
    u = jnp.stack([c * zb[0] + s * zb[1], -s * zb[0] + c * zb[1], zb[2]])  # thrust axis in the yawed frame
    roll = jnp.arctan2(-u[1], jnp.sqrt(u[0] ** 2 + u[2] ** 2))
    pitch = jnp.arctan2(u[0], u[2])
    return euler_to_quat(jnp.stack([roll, pitch, psi]))

  q = quat(t)
  w = quat_to_rot(q).T @ jax.jacfwd(lambda t: quat_to_rot(quat(t)))(t)
  return TrueState(pos=pos_fn(t), vel=d1(t), quat=q, ang_vel=jnp.stack([w[2, 1], w[0, 2], w[1, 0]]), acc=d2(t))


@functools.partial(jax.jit, static_argnums=(1, 2))
def make_truth(params, n, rover=False):
  """TrueState [B, n] for trajectory parameters [B, 9] (see `_trajectory`), n ticks of DT."""
  t = jnp.arange(n, dtype=jnp.float32) * DT
  return jax.vmap(lambda p: jax.vmap(lambda t: _truth_at(p, t, rover))(t))(params)


PI = math.pi
TRAJ = {  # x0, y0, z0, radius, omega, vx, vz, yaw0, yaw_follow
  "hover": [3.0, -2.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0],
  "circle": [25.0, 0.0, 10.0, 25.0, 8.0 / 25.0, 0.0, 0.0, PI / 2, 1.0],  # 8 m/s, 2.56 m/s^2 centripetal
  "climb": [0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 2.0, -1.0, 0.0],  # climbs at up to 2 m/s
  "rover": [10.0, 0.0, 0.2, 10.0, 0.3, 0.0, 0.0, PI / 2, 1.0],  # 3 m/s on a 10 m circle
}


# ----------------------------------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=(0, 1))
def simulate(scfg, ecfg, truth, gps_offset, rng):
  """Sensors + EKF over a truth trajectory [n]; gps_offset [n, 3] is added to the GPS position (spoofing).

  Tick 0 initialises the filter; outputs are for ticks 1..n-1. gps_err: the GPS's slowly correlated position error
  (sensors.SensorState.gps_drift, m), which no filter fusing that GPS can see.
  """
  n = truth.pos.shape[0]
  t0 = jax.tree.map(lambda x: x[0], truth)
  k0, k1, k2 = jax.random.split(rng, 3)
  ss = init_sensors(scfg, t0, k0)
  ss, r0 = sense(scfg, ss, t0, k1, DT)
  ekf = ekf_init(ecfg, r0.replace(gps_pos=r0.gps_pos + gps_offset[0]))

  def body(carry, inp):
    ss, ekf = carry
    tr, off, k = inp
    ss, r = sense(scfg, ss, tr, k, DT)
    r = r.replace(gps_pos=r.gps_pos + off)
    ekf = ekf_step(ecfg, ekf, r, DT)
    out = dict(pos=ekf.pos, vel=ekf.vel, euler=ekf_euler(ekf), rates=ekf_body_rates(ekf, r), ratio=ekf.test_ratio,
               accepted=ekf.accepted, fresh=ekf.fresh, reset=ekf.reset, std=ekf_std(ekf), gps_err=ss.gps_drift)
    return (ss, ekf), out

  rest = jax.tree.map(lambda x: x[1:], truth)
  _, out = jax.lax.scan(body, (ss, ekf), (rest, gps_offset[1:], jax.random.split(k2, n - 1)))
  return out


DRONE = (SensorConfig.drone(), EKFConfig.drone())
ROVER = (SensorConfig.rover(), EKFConfig.rover())
N = 2500  # 50 s
SETTLE = 500  # accuracy is judged after the first 10 s
T_ATTACK = 20.0  # s, start of the GPS spoofing scenarios
RAMP_RATE = 0.2  # m/s
_simulate_batch = jax.jit(jax.vmap(functools.partial(simulate, *DRONE)))

# Drone scenarios, all run in ONE vmapped call (one compile): (name, trajectory, GPS attack, rng seed)
SCENARIOS = (("hover", "hover", None, 0), ("circle", "circle", None, 0), ("climb", "climb", None, 0),
             ("jump", "hover", "jump", 2), ("ramp", "hover", "ramp", 3), ("hover_seed5", "hover", None, 5))
IDX = {name: i for i, (name, *_) in enumerate(SCENARIOS)}


def _offset(kind):
  t = np.arange(N)[:, None] * DT
  if kind == "jump":  # 50 m east, at once
    return np.where(t >= T_ATTACK, [50.0, 0.0, 0.0], 0.0)
  if kind == "ramp":  # slowly growing east offset
    return np.clip(t - T_ATTACK, 0.0, None) * [RAMP_RATE, 0.0, 0.0]
  return np.zeros((N, 3))


def _drone_inputs(order):
  sc = [SCENARIOS[i] for i in order]
  truth = make_truth(jnp.asarray([TRAJ[traj] for _, traj, _, _ in sc], jnp.float32), N)
  off = jnp.asarray(np.stack([_offset(kind) for _, _, kind, _ in sc]), jnp.float32)
  keys = jnp.stack([jax.random.PRNGKey(seed) for *_, seed in sc])
  return truth, off, keys


@pytest.fixture(scope="module")
def drone():
  """(truth [B, N], outputs [B, N-1]) of all drone scenarios, numpy."""
  truth, off, keys = _drone_inputs(range(len(SCENARIOS)))
  out = _simulate_batch(truth, off, keys)
  return jax.tree.map(np.asarray, truth), jax.tree.map(np.asarray, out)


def _pick(tree, i):
  return jax.tree.map(lambda x: x[i], tree)


def _np_euler(q):
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  return np.stack([np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                   np.arcsin(np.clip(2 * (w * y - z * x), -1, 1)),
                   np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))], -1)


def _gps_ref(truth, out):
  """[N-1, 3] the position the EKF can know: horizontally, the truth + the GPS's slowly correlated error (metres,
  τ 60 s: sensors.SensorConfig.gps_drift_*), which nothing else in the sensor suite observes; vertically the truth
  (the height follows the barometer, EKF2's default height source). Position accuracy is judged against it."""
  ref = np.asarray(truth.pos)[1:].copy()
  ref[:, :2] += np.asarray(out["gps_err"])[:, :2]
  return ref


def _errors(truth, out, settle=SETTLE):
  """RMS errors after `settle` ticks: position (m, 3-D, to the GPS reference `_gps_ref`), velocity (m/s, 3-D), tilt
  (deg, roll/pitch, and max), yaw (deg), body rates (rad/s, 3-D)."""
  s = slice(settle, None)
  tv, tq, tw = (np.asarray(x)[1:][s] for x in (truth.vel, truth.quat, truth.ang_vel))
  tp = _gps_ref(truth, out)[s]
  de = np.asarray(out["euler"])[s] - _np_euler(tq)
  de = np.degrees((de + np.pi) % (2 * np.pi) - np.pi)
  rms = lambda x: float(np.sqrt(np.mean(np.sum(np.square(x), axis=-1))))
  return dict(pos=rms(np.asarray(out["pos"])[s] - tp), vel=rms(np.asarray(out["vel"])[s] - tv),
              tilt=float(np.sqrt(np.mean(de[:, :2] ** 2))), tilt_max=float(np.abs(de[:, :2]).max()),
              yaw=float(np.sqrt(np.mean(de[:, 2] ** 2))), rates=rms(np.asarray(out["rates"])[s] - tw))


@pytest.mark.parametrize("name", ["hover", "circle", "climb"])
def test_drone_tracks_truth(drone, name):
  truth, out = (_pick(x, IDX[name]) for x in drone)
  e = _errors(truth, out)
  assert e["pos"] < 1.0 and e["vel"] < 0.3, e
  assert e["tilt"] < 2.0 and e["tilt_max"] < 4.0 and e["yaw"] < 5.0, e
  # body rates = gyro - estimated bias: white gyro noise (3-D RMS sqrt(3) 0.005) plus a small bias residual
  gyro_floor = math.sqrt(3.0) * DRONE[0].gyro_sigma
  assert e["rates"] < 1.25 * gyro_floor, e
  bias_residual = np.mean(out["rates"][SETTLE:] - truth.ang_vel[1:][SETTLE:], axis=0)
  assert np.all(np.abs(bias_residual) < 0.005), bias_residual  # EKF2's bias process noise lets it wander ~0.002
  # every drone channel delivers, and healthy samples pass their gates (3σ gates reject a few by design)
  fresh = out["fresh"][SETTLE:] > 0
  acc = out["accepted"][SETTLE:]
  for i, ch in enumerate(CHANNELS):
    if ch != "odom":
      assert fresh[:, i].sum() > 100, ch
      # The GPS height's slowly correlated error (metres, sensors.SensorConfig.gps_drift_sigma_v, τ 60 s) walks out of
      # its gate around the barometer-held height for long stretches: most samples, not 97 %, pass.
      assert acc[fresh[:, i], i].mean() > (0.5 if ch == "gps_pos_z" else 0.97), ch
  assert fresh[:, CH["odom"]].sum() == 0
  assert not np.any(out["reset"])
  # the filter's position σ is sane
  std = out["std"][SETTLE:]
  assert np.all(std[:, :3] < 1.5) and np.all(std[:, :3] > 0.01)


def test_rover_tracks_truth():
  truth = _pick(make_truth(jnp.asarray([TRAJ["rover"]], jnp.float32), N, True), 0)
  assert abs(float(jnp.linalg.norm(truth.vel[-1])) - 3.0) < 0.01
  out = jax.tree.map(np.asarray, simulate(*ROVER, truth, jnp.zeros((N, 3)), jax.random.PRNGKey(1)))
  e = _errors(truth, out)
  # (1.5 m: the rover's GPS height passes its gate more often than a flying drone's, so part of the GPS's vertical
  # correlated error, metres, reaches its height beside the barometer's)
  assert e["pos"] < 1.5 and e["vel"] < 0.3 and e["tilt"] < 2.0 and e["yaw"] < 5.0, e
  fresh = out["fresh"] > 0
  assert fresh[:, CH["odom"]].sum() > 1000 and fresh[:, CH["flow_x"]].sum() == 0
  assert out["accepted"][SETTLE:][fresh[SETTLE:, CH["odom"]], CH["odom"]].mean() > 0.97


def test_gps_jump_rejected_then_reset(drone):
  truth, out = (_pick(x, IDX["jump"]) for x in drone)
  tt = np.arange(1, N) * DT
  ex = out["pos"][:, 0] - _gps_ref(truth, out)[:, 0]    # the spoofing offset is on top of the GPS's own error
  acc = out["accepted"][:, CH["gps_pos_x"]]
  ratio = out["ratio"][:, CH["gps_pos_x"]]
  reset_t = tt[out["reset"] > 0]
  # before the attack: accepted, near truth
  before = (tt > 5.0) & (tt < T_ATTACK)
  assert acc[before].mean() > 0.99 and np.all(np.abs(ex[before]) < 1.5)
  # the 50 m jump fails the 5σ gate and the estimate stays with the truth ...
  during = (tt >= T_ATTACK) & (tt < T_ATTACK + 6.5)
  assert np.all(acc[during] == 0.0) and np.all(ratio[during] > 1.0)
  assert np.all(np.abs(ex[during]) < 1.0)
  # ... until ~7 s of continuous rejection, when the filter resets to the (spoofed) GPS, once
  assert len(reset_t) == 1 and T_ATTACK + 6.5 <= reset_t[0] <= T_ATTACK + 7.5, reset_t
  after = tt > reset_t[0] + 0.5
  assert np.all(np.abs(ex[after] - 50.0) < 1.5)
  assert acc[after].mean() > 0.98


def test_slow_gps_ramp_passes_gate_and_drags(drone):
  truth, out = (_pick(x, IDX["ramp"]) for x in drone)
  tt = np.arange(1, N) * DT
  ex = out["pos"][:, 0] - _gps_ref(truth, out)[:, 0]    # the spoofing offset is on top of the GPS's own error
  fresh = out["fresh"][:, CH["gps_pos_x"]] > 0
  during = (tt > T_ATTACK) & fresh
  assert np.all(out["accepted"][during, CH["gps_pos_x"]] == 1.0)
  assert np.all(out["ratio"][during, CH["gps_pos_x"]] < 1.0)
  assert not np.any(out["reset"])
  final_offset = RAMP_RATE * (tt[-1] - T_ATTACK)  # 6 m
  assert ex[-1] > 0.7 * final_offset, (ex[-1], final_offset)


def test_reproducible_and_batch_independent(drone):
  """Same rng -> same outputs; vehicles in a vmapped batch are independent of their batch position."""
  _, out = drone
  assert not np.allclose(out["pos"][IDX["hover"]], out["pos"][IDX["hover_seed5"]])
  order = list(reversed(range(len(SCENARIOS))))
  out2 = jax.tree.map(np.asarray, _simulate_batch(*_drone_inputs(order)))
  for j, i in enumerate(order):
    for key in ("pos", "vel", "euler", "ratio"):
      np.testing.assert_allclose(out2[key][j], out[key][i], rtol=0, atol=1e-5, err_msg=key)


# ----------------------------------------------------------------------------------------------------------------------
# the filter alone on hand-made readings


@functools.partial(jax.jit, static_argnums=0)
def run_filter(ecfg, readings):
  """ekf_init on readings[0], then ekf_step over readings[1:]; returns the EKFState history."""
  s0 = ekf_init(ecfg, _pick(readings, 0))
  return jax.lax.scan(lambda s, r: (ekf_step(ecfg, s, r, DT),) * 2, s0, _pick(readings, slice(1, None)))[1]


def _hover_readings(n, gps_jump_at=None):
  """Perfect readings of a level hover at (0, 0, 10), yaw 0, at the drone rates; optional 50 m east GPS jump."""
  k = np.arange(n)
  gps = np.tile([0.0, 0.0, 10.0], (n, 1))
  if gps_jump_at is not None:
    gps[k >= gps_jump_at, 0] += 50.0
  f = lambda x: jnp.asarray(x, jnp.float32)
  return SensorReadings(gps_pos=f(gps), gps_vel=f(np.zeros((n, 3))), gps_fresh=f(k % 5 == 0),
                        gyro=f(np.zeros((n, 3))), accel=f(np.tile([0.0, 0.0, 9.81], (n, 1))), mag_yaw=f(np.zeros(n)),
                        mag_fresh=f(np.ones(n)), baro_alt=f(np.full(n, 10.0)), baro_fresh=f(k % 2 == 0),
                        flow=f(np.zeros((n, 2))), flow_fresh=f(k % 2 == 0), odom_speed=f(np.zeros(n)),
                        odom_fresh=f(np.zeros(n)))


N_F = 1000  # ticks of the filter-only runs (one compile for all of them)


def test_gate_is_what_rejects_the_jump():
  """Control experiment (so the jump test can fail): with the gate opened up, the same jump is fused at once."""
  r = _hover_readings(N_F, gps_jump_at=100)
  gated = run_filter(DRONE[1], r)
  opened = run_filter(dataclasses.replace(DRONE[1], gps_pos_gate=1e4), r)
  reset = np.flatnonzero(np.asarray(gated.reset))
  assert len(reset) == 1 and 100 + 6.9 / DT <= reset[0] <= 100 + 7.5 / DT, reset  # EKF2-style timeout reset
  assert np.all(np.abs(np.asarray(gated.pos[:reset[0], 0])) < 0.1)
  assert np.all(np.asarray(gated.accepted[110:reset[0], CH["gps_pos_x"]]) == 0.0)
  assert abs(float(gated.pos[-1, 0]) - 50.0) < 0.5
  assert float(opened.pos[150, 0]) > 10.0 and float(opened.accepted[150, CH["gps_pos_x"]]) == 1.0


def test_learns_gyro_bias():
  """A constant gyro bias is estimated (through tilt vs. GPS velocity/flow and heading vs. magnetometer)."""
  bias = np.array([0.02, -0.03, 0.01])
  r = _hover_readings(N_F)
  r = r.replace(gyro=r.gyro + jnp.asarray(bias, jnp.float32))
  h = run_filter(DRONE[1], r)
  np.testing.assert_allclose(np.asarray(h.gyro_bias[-1]), bias, atol=0.003)
  assert np.all(np.abs(np.degrees(np.asarray(jax.vmap(ekf_euler)(_pick(h, slice(-100, None)))))) < 1.0)


def test_init_from_gravity_and_heading():
  e = np.array([0.2, -0.3, 2.5])
  q = euler_to_quat(jnp.asarray(e, jnp.float32))
  spec = quat_to_rot(q).T @ jnp.array([0.0, 0.0, 9.81])
  r = _pick(_hover_readings(1), 0).replace(gps_pos=jnp.array([1.0, 2.0, 3.0]), gps_vel=jnp.array([0.5, 0.0, 0.0]),
                                            accel=spec, mag_yaw=jnp.asarray(2.5), baro_alt=jnp.asarray(3.1))
  s = jax.jit(ekf_init, static_argnums=0)(DRONE[1], r)
  np.testing.assert_allclose(ekf_euler(s), e, atol=1e-5)
  np.testing.assert_allclose(s.pos, [1.0, 2.0, 3.1], atol=1e-6)
  np.testing.assert_allclose(s.vel, [0.5, 0.0, 0.0], atol=1e-6)
  assert s.P.shape == (15, 15) and s.test_ratio.shape == (len(CHANNELS),)
  np.testing.assert_allclose(np.diag(s.P), np.asarray(ekf_std(s)) ** 2, rtol=1e-6)


def test_no_nan_for_extreme_finite_inputs():
  """Garbage (huge but finite) readings, all marked fresh, never produce NaN/inf in the state."""
  n = N_F
  k = jax.random.split(jax.random.PRNGKey(7), 6)
  scale = lambda key, shape: jax.random.normal(key, (n,) + shape) * 10.0 ** jax.random.uniform(
      key, (n,) + (1,) * len(shape), minval=-2, maxval=30)
  one = jnp.ones((n,))
  rs = SensorReadings(gps_pos=scale(k[0], (3,)), gps_vel=scale(k[1], (3,)), gps_fresh=one, gyro=scale(k[2], (3,)),
                      accel=scale(k[3], (3,)), mag_yaw=scale(k[4], ()), mag_fresh=one, baro_alt=scale(k[5], ()),
                      baro_fresh=one, flow=scale(k[0], (2,)), flow_fresh=one, odom_speed=scale(k[1], ()),
                      odom_fresh=one)
  hist = run_filter(DRONE[1], rs)
  for name in ("pos", "vel", "quat", "gyro_bias", "accel_bias", "P", "innov", "test_ratio"):
    assert np.all(np.isfinite(np.asarray(getattr(hist, name)))), name
  np.testing.assert_allclose(np.linalg.norm(np.asarray(hist.quat), axis=-1), 1.0, atol=1e-4)
  # P stays symmetric positive semi-definite
  P = np.asarray(hist.P, np.float64)
  assert np.allclose(P, np.swapaxes(P, -1, -2))
  assert np.all(np.linalg.eigvalsh(P)[:, 0] > -1e-3 * np.abs(P).max(axis=(1, 2)))


# ----------------------------------------------------------------------------------------------------------------------
# the fast covariance algebra against the textbook one


def _random_state(ecfg, key):
  """A random, well-conditioned EKF state (SPD P, tilted attitude, 6 m up) and a set of fresh readings near it."""
  from specguard_jax import ekf as ekf_lib
  k = jax.random.split(key, 6)
  a = jax.random.normal(k[0], (15, 15)) * 0.3
  P = a @ a.T + jnp.diag(jnp.linspace(0.01, 0.5, 15))
  s = ekf_lib.ekf_init(ecfg, SensorReadings(
    gps_pos=jnp.array([3.0, -2.0, 6.0]), gps_vel=jnp.array([1.0, 0.5, -0.2]), gps_fresh=jnp.ones(()),
    gyro=jnp.zeros(3), accel=jnp.array([0.8, -0.5, 9.7]), mag_yaw=jnp.array(0.7), mag_fresh=jnp.ones(()),
    baro_alt=jnp.array(6.0), baro_fresh=jnp.ones(()), flow=jnp.zeros(2), flow_fresh=jnp.ones(()),
    odom_speed=jnp.array(1.0), odom_fresh=jnp.ones(())))
  s = s.replace(P=P, gyro_bias=jax.random.normal(k[1], (3,)) * 0.01, accel_bias=jax.random.normal(k[2], (3,)) * 0.05)
  noise = lambda kk, n, sc: jax.random.normal(kk, (n,)) * sc
  r = SensorReadings(gps_pos=s.pos + noise(k[3], 3, 0.8), gps_vel=s.vel + noise(k[4], 3, 0.4), gps_fresh=jnp.ones(()),
                     gyro=jnp.array([0.05, -0.02, 0.1]), accel=jnp.array([0.8, -0.5, 9.7]),
                     mag_yaw=jnp.array(0.75), mag_fresh=jnp.ones(()), baro_alt=s.pos[2] + 0.3, baro_fresh=jnp.ones(()),
                     flow=noise(k[5], 2, 0.2), flow_fresh=jnp.ones(()), odom_speed=jnp.array(1.1),
                     odom_fresh=jnp.ones(()))
  return s, r


def _dense_sequential_fuse(ecfg, s, z, noise, gate, enable):
  """EKF2's textbook form of `_fuse`: dense H, one scalar row at a time, P <- P - k (P h)' (float64, numpy)."""
  from specguard_jax import ekf as ekf_lib
  pred, H = ekf_lib.linearise(ecfg, s)
  H = np.asarray(H, np.float64)
  innov = np.asarray(z - pred, np.float64)
  innov[ekf_lib._MAG_ROW] = (innov[ekf_lib._MAG_ROW] + np.pi) % (2 * np.pi) - np.pi
  P = np.asarray(s.P, np.float64)
  R = np.asarray(noise, np.float64) ** 2
  S = np.einsum("mi,ij,mj->m", H, P, H) + R
  ratio = innov ** 2 / (np.asarray(gate, np.float64) ** 2 * S)
  en = np.asarray(enable)
  bad = en & ~(ratio <= 1.0)
  groups = np.asarray(ekf_lib.GROUP_OF_ROW)
  accept = en & ~np.isin(groups, groups[bad])
  dx = np.zeros(15)
  for i in np.flatnonzero(accept):
    pht = P @ H[i]
    k = pht / (H[i] @ pht + R[i])
    dx = dx + k * (innov[i] - H[i] @ dx)
    P = P - np.outer(k, pht)
  return P, dx, accept


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
@pytest.mark.parametrize("unrolled", [True, False], ids=["unrolled", "rolled"])
def test_fusion_equals_textbook_sequential_update(vehicle, unrolled):
  """`_fuse` in both forms (accelerators: unrolled low-rank, sparse H, static rows skipped; CPU: rolled dense rows)
  == the dense per-row P -= k (P h)' update, for random states where some rows are gated out; P exactly symmetric."""
  from specguard_jax import ekf as ekf_lib
  ecfg = getattr(EKFConfig, vehicle)()
  fuse = jax.jit(lambda s, z, n, g, e: ekf_lib._fuse(ecfg, s, z, n, g, e, unrolled=unrolled))
  n_rejected = 0
  for seed in range(6):
    s, r = _random_state(ecfg, jax.random.PRNGKey(seed))
    z, noise, gate = ekf_lib.measurement_rows(ecfg, r)
    enable = np.array([ekf_lib.row_used(ecfg, i) for i in range(ekf_lib.N_ROWS)])
    if seed % 2:  # tight gates: some groups fail theirs
      gate = gate * (0.3 if seed % 4 == 1 else 0.05)
    P_ref, dx_ref, acc_ref = _dense_sequential_fuse(ecfg, s, z, noise, gate, enable)
    s2, _, _, acc = fuse(s, z, noise, gate, jnp.asarray(enable))
    np.testing.assert_array_equal(np.asarray(acc), acc_ref)
    n_rejected += int(np.sum(enable & ~acc_ref))
    np.testing.assert_allclose(np.asarray(s2.P), P_ref, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(s2.pos), np.asarray(s.pos) + dx_ref[:3], rtol=0, atol=1e-4)
    np.testing.assert_allclose(np.asarray(s2.vel), np.asarray(s.vel) + dx_ref[3:6], rtol=0, atol=1e-4)
    assert np.array_equal(np.asarray(s2.P), np.asarray(s2.P).T)
  assert n_rejected > 0  # the gating path was exercised


def test_observation_jacobian_support():
  """The columns `_fuse` visits (_H_SUPPORT) hold every non-zero of H, for random states of both vehicles."""
  from specguard_jax import ekf as ekf_lib
  for vehicle in ("drone", "rover"):
    ecfg = getattr(EKFConfig, vehicle)()
    for seed in range(4):
      s, _ = _random_state(ecfg, jax.random.PRNGKey(10 + seed))
      s = s.replace(quat=euler_to_quat(jax.random.uniform(jax.random.PRNGKey(seed), (3,), minval=-1.0, maxval=1.0)))
      H = np.asarray(ekf_lib.linearise(ecfg, s)[1])
      for i, cols in enumerate(ekf_lib.H_SUPPORT):
        off = np.setdiff1d(np.arange(15), cols)
        assert np.all(H[i, off] == 0.0), (ekf_lib._ROWS[i], H[i])
        assert np.any(H[i, list(cols)] != 0.0), ekf_lib._ROWS[i]


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_closed_form_jacobian_equals_jacfwd(vehicle):
  """`_linearise`'s closed-form H == jax.jacfwd of the perturbed observation `_observe_err` at 0 (float32 rounding),
  for random attitudes and velocities, with the flow height above, below and at its floor."""
  from specguard_jax import ekf as ekf_lib
  ecfg = getattr(EKFConfig, vehicle)()
  for seed in range(6):
    s, _ = _random_state(ecfg, jax.random.PRNGKey(20 + seed))
    s = s.replace(quat=euler_to_quat(jax.random.uniform(jax.random.PRNGKey(seed), (3,), minval=-1.5, maxval=1.5)))
    s = s.replace(pos=s.pos.at[2].set((5.0, 0.1, ecfg.flow_min_height)[seed % 3]))
    pred, H = ekf_lib.linearise(ecfg, s)
    ref = jax.jacfwd(lambda dx: ekf_lib._observe_err(ecfg, s, dx))(jnp.zeros(15))
    np.testing.assert_allclose(np.asarray(H), np.asarray(ref), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(pred), np.asarray(ekf_lib._observe_err(ecfg, s, jnp.zeros(15))))


def test_step_keeps_covariance_exactly_symmetric(drone):
  """After every ekf_step P is exactly symmetric (one symmetrisation per tick, symmetric updates after it)."""
  r = _hover_readings(N_F, gps_jump_at=100)
  P = np.asarray(run_filter(DRONE[1], r).P)
  assert np.array_equal(P, np.swapaxes(P, 1, 2))
  assert np.all(np.diagonal(P, axis1=1, axis2=2) > 0)


@pytest.mark.parametrize("unrolled", [True, False], ids=["unrolled", "rolled"])
def test_rejected_nonfinite_reading_does_not_reach_the_state(unrolled):
  """A NaN optical-flow sample fails its gate: the state is exactly what fusing every other row gives, and finite."""
  from specguard_jax import ekf as ekf_lib
  ecfg = EKFConfig.drone()
  s, r = _random_state(ecfg, jax.random.PRNGKey(3))
  z, noise, gate = ekf_lib.measurement_rows(ecfg, r)
  enable = jnp.asarray([ekf_lib.row_used(ecfg, i) for i in range(ekf_lib.N_ROWS)])
  fuse = jax.jit(lambda z, e: ekf_lib._fuse(ecfg, s, z, noise, gate, e, unrolled=unrolled))
  flow = np.array([ekf_lib._ROWS[i].startswith("flow") for i in range(ekf_lib.N_ROWS)])
  bad, _, _, acc = fuse(z.at[flow].set(jnp.nan), enable)
  ref, _, _, _ = fuse(z, enable & ~flow)
  assert not np.any(np.asarray(acc)[flow]) and np.any(np.asarray(acc))
  for name in ("pos", "vel", "quat", "P"):
    assert np.all(np.isfinite(np.asarray(getattr(bad, name)))), name
    np.testing.assert_allclose(np.asarray(getattr(bad, name)), np.asarray(getattr(ref, name)), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("unrolled", [True, False], ids=["unrolled", "rolled"])
def test_stale_gps_rows_left_out_equal_the_full_fusion(unrolled):
  """With no fresh GPS sample, fusing with the GPS rows left out (stale=("gps",), what the env does on the ticks
  between GPS samples) gives the state, records and gates of the full fusion."""
  from specguard_jax import ekf as ekf_lib
  for ecfg in (EKFConfig.drone(), EKFConfig.rover()):
    s, r = _random_state(ecfg, jax.random.PRNGKey(5))
    r = r.replace(gps_fresh=jnp.zeros(()))
    z, noise, gate = ekf_lib.measurement_rows(ecfg, r)
    gps_rows = np.array([n.startswith("gps") for n in ekf_lib._ROWS])
    enable = jnp.asarray([ekf_lib.row_used(ecfg, i) for i in range(ekf_lib.N_ROWS)]) & ~gps_rows
    fuse = jax.jit(lambda stale: ekf_lib._fuse(ecfg, s, z, noise, gate, enable, unrolled=unrolled, stale=stale),
                   static_argnums=0)
    (a, _, ra, acc_a), (b, _, rb, acc_b) = fuse(()), fuse(("gps",))
    np.testing.assert_array_equal(np.asarray(acc_a), np.asarray(acc_b))
    np.testing.assert_allclose(np.asarray(ra)[~gps_rows], np.asarray(rb)[~gps_rows], rtol=1e-6)
    for name in ("pos", "vel", "quat", "gyro_bias", "accel_bias", "P"):   # the two traces round differently
      np.testing.assert_allclose(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), rtol=1e-5, atol=1e-7,
                                 err_msg=name)
    step = jax.jit(lambda stale: ekf_step(ecfg, s, r, DT, stale=stale), static_argnums=0)
    full, fast = step(()), step(("gps",))
    for name in full.__dataclass_fields__:
      np.testing.assert_allclose(np.asarray(getattr(full, name)), np.asarray(getattr(fast, name)), rtol=1e-6,
                                 atol=1e-8, err_msg=name)
