"""PX4-EKF2-style error-state EKF (15 states) for the autopilot's state estimate.

Nominal state: pos[3] (ENU, m), vel[3] (ENU, m/s), quat[4] ((w, x, y, z), body -> world), gyro_bias[3] (rad/s),
accel_bias[3] (m/s^2). Error state dx[15] = (dp, dv, dtheta, dbg, dba) with covariance P[15, 15]; the attitude error
is a small rotation in the world frame: R_true = Exp(dtheta) R_est.

Kept from EKF2:
  * strapdown prediction with the IMU as control input (gyro/accel minus estimated biases; the specific force is
    rotated with the mid-interval attitude), process noise from the
    IMU noise (EKF2_GYR_NOISE, EKF2_ACC_NOISE) and bias random walks (EKF2_GYR_B_NOISE, EKF2_ACC_B_NOISE);
  * sequential scalar fusion of each fresh measurement with EKF2's O(n^2) covariance update P -= K (H P), then
    symmetrised and variance-clamped once per tick (EKF2's fixCovarianceErrors) instead of the O(n^3) Joseph form;
  * per-channel innovation-consistency gates: test ratio = innov^2 / (gate^2 * (H P H' + R)), rejected when > 1;
    a vector observation (GPS horizontal position, GPS velocity, optical flow) is accepted or rejected as a whole, as in
    EKF2 (gates: GPS pos 5, GPS vel 5, baro 5, mag heading 3, flow 3, odometry 5);
  * reset of horizontal position (velocity) to GPS when GPS position (velocity) fusion has been rejected for longer
    than `reset_timeout` (~7 s, EKF2's reset_timeout_max), with the reset states' covariance set to the GPS noise
    and their cross-covariances cleared. Height resets to the barometer (the height reference) only when neither
    GPS height nor baro has been accepted for the timeout, so spoofed GPS height alone never resets. A slow GPS ramp
    keeps its innovations inside the gate and drags the estimate; a large jump is rejected until the timeout reset;
  * the last test ratios and accept flags are stored per channel (see CHANNELS) for detectors.
Simplified vs EKF2:
  * 15 states: no magnetic-field/earth-field states (the magnetometer is a heading, fused like EKF2's yaw fusion), no
    wind, no terrain state (optical flow uses height above flat ground = estimated z), no baro bias state;
  * no delayed-time horizon / output predictor: measurements are fused at the tick they arrive (no sensor latency);
  * all observations of one tick are linearised once at the predicted state and gated against the predicted P, then
    fused one scalar at a time into an accumulated correction injected at the end (one fixed-length loop of 13
    scalar rows per tick, cheap to compile and vmap); EKF2 fuses each sensor group against the then-current state;
  * GPS height and barometer are both fused directly (EKF2 fuses only the chosen height reference);
  * no GPS quality checks, no in-air/on-ground logic, no bias-learning inhibition;
  * rover: wheel-odometry forward speed and a non-holonomic pseudo-measurement (body lateral and vertical velocity
    = 0) in the style of ArduPilot's EKF3 body-odometry fusion; neither exists in EKF2.
Robustness: IMU inputs saturate at the sensor range, biases are clamped, P is symmetrised and its diagonal clamped
(scaling rows/columns so P stays PSD), the quaternion is renormalised; no NaN for finite inputs.
Everything is per vehicle, jittable and vmappable; dt is passed in explicitly.
"""

from __future__ import annotations

import dataclasses
import functools
import operator

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax.math3d import (euler_to_quat, matvec, matvec_t, normalize_quat, quat_mul, quat_to_euler, quat_to_rot,
                                  rotvec_to_quat, with_component, wrap_angle)
from specguard_jax.sensors import ACCEL_RANGE, GRAVITY, GYRO_RANGE
from specguard_jax.types import SensorReadings

# Innovation channels recorded in EKFState (order is part of the API).
CHANNELS = ("gps_pos_x", "gps_pos_y", "gps_pos_z", "gps_vel_x", "gps_vel_y", "gps_vel_z", "baro", "mag",
            "flow_x", "flow_y", "odom")
CH = {name: i for i, name in enumerate(CHANNELS)}
N_CHANNELS = len(CHANNELS)
N_ERR = 15
# slices into the error state
POS, VEL, ATT, GBIAS, ABIAS = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


@dataclasses.dataclass(frozen=True)
class EKFConfig:
  """Process/measurement noise (σ), gates (in σ), reset timeout and initial uncertainty. Units SI, angles rad."""

  # process noise (PX4 EKF2 defaults)
  gyro_noise: float = 0.015  # rad/s            (EKF2_GYR_NOISE)
  accel_noise: float = 0.35  # m/s^2            (EKF2_ACC_NOISE)
  gyro_bias_noise: float = 1e-3  # rad/s^2      (EKF2_GYR_B_NOISE)
  accel_bias_noise: float = 3e-3  # m/s^3       (EKF2_ACC_B_NOISE)
  gyro_bias_limit: float = 0.4  # rad/s, |bias| clamp
  accel_bias_limit: float = 0.4  # m/s^2, |bias| clamp (EKF2_ABL_LIM)
  # measurement noise
  gps_pos_noise_h: float = 0.5  # m             (EKF2_GPS_P_NOISE)
  gps_pos_noise_v: float = 1.0  # m
  gps_vel_noise: float = 0.3  # m/s             (EKF2_GPS_V_NOISE)
  baro_noise: float = 0.4  # m
  mag_heading_noise: float = 0.05  # rad
  flow_noise: float = 0.1  # rad/s
  odom_noise: float = 0.1  # m/s
  nhc_noise: float = 0.1  # m/s, body lateral/vertical velocity pseudo-measurement
  # gates (σ)
  gps_pos_gate: float = 5.0  # EKF2_GPS_P_GATE
  gps_vel_gate: float = 5.0  # EKF2_GPS_V_GATE
  baro_gate: float = 5.0  # EKF2_BARO_GATE
  mag_gate: float = 3.0  # EKF2_MAG_GATE
  flow_gate: float = 3.0  # EKF2_OF_GATE
  odom_gate: float = 5.0
  nhc_gate: float = 5.0
  reset_timeout: float = 7.0  # s of continuous rejection before resetting to the measurement
  # which aiding sources are fused
  fuse_gps_height: bool = True
  use_flow: bool = True
  use_odom: bool = False
  use_nhc: bool = False
  flow_min_height: float = 0.3  # m; no flow fusion below
  # initial uncertainty (σ)
  init_pos_sigma_h: float = 0.5
  init_pos_sigma_v: float = 0.5
  init_vel_sigma: float = 0.5
  init_tilt_sigma: float = 0.1  # rad
  init_yaw_sigma: float = 0.1  # rad
  init_gyro_bias_sigma: float = 0.01  # rad/s
  init_accel_bias_sigma: float = 0.2  # m/s^2   (EKF2_ABIAS_INIT)

  @classmethod
  def drone(cls, **overrides) -> "EKFConfig":
    """Multicopter: GPS + baro + mag + optical flow."""
    return cls(**overrides)

  @classmethod
  def rover(cls, **overrides) -> "EKFConfig":
    """Ground rover: GPS + baro + mag + wheel odometry + non-holonomic constraint; no optical flow."""
    kw = dict(use_flow=False, use_odom=True, use_nhc=True)
    kw.update(overrides)
    return cls(**kw)


RECORD_FIELDS = ("innov", "test_ratio", "accepted", "fresh")
"""EKFState's per-channel records: kept for the residual detector, skipped by `ekf_step(records=False)`."""


@struct.dataclass
class EKFState:
  """Filter state of one vehicle.

  pos[3], vel[3], quat[4], gyro_bias[3], accel_bias[3]: nominal state.  P: the error-state covariance in one of
    `P_LAYOUTS` (`ekf_init(p_layout=...)`): "square" [15, 15] (the XLA filter's); "packed" [121], its upper
    triangle in `TRI` order and a zero (the lanes kernel's, ekf_lanes.py: kept between ticks so that P enters and
    leaves the kernel without a copy). Every function here accepts either (`as_square`, `p_entry`, `p_diag`).
  gps_pos_age, gps_vel_age, hgt_age: [] s since the last accepted horizontal GPS position / GPS velocity /
    height (GPS height or baro) fusion.
  innov: [11] last innovation (measurement - prediction) per channel (CHANNELS), held between samples.
  test_ratio: [11] last innov^2 / (gate^2 * innovation variance); > 1 means rejected. Held between samples.
  accepted: [11] 1.0 if the channel's last sample was fused, 0.0 if it was rejected (held).
  fresh: [11] 1.0 on the tick the channel had a sample.
  reset: [] 1.0 on a tick where a timeout reset happened (horizontal position, velocity or height).
  n_resets: [] number of timeout resets since init.  time: [] s since init.
  """

  pos: jnp.ndarray
  vel: jnp.ndarray
  quat: jnp.ndarray
  gyro_bias: jnp.ndarray
  accel_bias: jnp.ndarray
  P: jnp.ndarray
  gps_pos_age: jnp.ndarray
  gps_vel_age: jnp.ndarray
  hgt_age: jnp.ndarray
  innov: jnp.ndarray
  test_ratio: jnp.ndarray
  accepted: jnp.ndarray
  fresh: jnp.ndarray
  reset: jnp.ndarray
  n_resets: jnp.ndarray
  time: jnp.ndarray


# ----------------------------------------------------------------------------------------------------------------------
# math helpers


def _skew(v):
  return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# ----------------------------------------------------------------------------------------------------------------------
# covariance hygiene

VAR_MIN = np.array([1e-6] * 3 + [1e-6] * 3 + [1e-9] * 3 + [1e-12] * 3 + [1e-10] * 3, np.float32)
_EYE = np.eye(N_ERR, dtype=np.float32)
VAR_MAX = np.array([1e6] * 3 + [1e4] * 3 + [1.0] * 3 + [0.1] * 3 + [1.0] * 3, np.float32)
TRI = tuple((i, j) for i in range(N_ERR) for j in range(i, N_ERR))       # P's upper triangle, 120 entries
TRI_INDEX = {ij: k for k, ij in enumerate(TRI)}


def tri_index(i: int, j: int) -> int:
  """Where P[i, j] (= P[j, i]) sits in the packed layout."""
  return TRI_INDEX[(min(i, j), max(i, j))]


N_PACKED = len(TRI) + 1   # the packed layout: the triangle and a zero (an odd length: ekf_lanes reads it per lane)
P_LAYOUTS = {"square": N_ERR, "packed": N_PACKED}     # layout -> P's last dimension
_TRI_ROW = np.array([i for i, _ in TRI] + [0])          # [121] row / column of each packed entry (the zero: 0, 0)
_TRI_COL = np.array([j for _, j in TRI] + [0])
_TRI_DIAG = np.array([i == j for i, j in TRI] + [False])
_SQUARE_OF_PACKED = np.array([[tri_index(i, j) for j in range(N_ERR)] for i in range(N_ERR)])


def p_layout(P) -> str:
  """The layout (`P_LAYOUTS`) of P [..., n, n] or [..., 121], from its last dimension."""
  for name, n in P_LAYOUTS.items():
    if P.shape[-1] == n:
      return name
  raise ValueError(f"ekf: P of shape {P.shape} is in none of the layouts {P_LAYOUTS}")


def pack_p(P15):
  """P [..., 15, 15] symmetric -> [..., 121] packed: its upper triangle in `TRI` order and a zero."""
  return jnp.concatenate([P15[..., _TRI_ROW[:-1], _TRI_COL[:-1]], jnp.zeros(P15.shape[:-2] + (1,), P15.dtype)], -1)


def as_square(P):
  """P [..., 15, 15] from either layout."""
  return P[..., _SQUARE_OF_PACKED] if p_layout(P) == "packed" else P


def in_layout(P15, layout: str):
  """P15 [..., 15, 15] in `layout`."""
  return pack_p(P15) if layout == "packed" else P15


def layout_like(P15, P_ref):
  """P15 [15, 15] in the layout of P_ref."""
  return in_layout(P15, p_layout(P_ref))


def p_entry(P, i: int, j: int):
  """P[i, j] of one vehicle's P in either layout (static indices: a slice)."""
  return P[tri_index(i, j)] if p_layout(P) == "packed" else P[i, j]


def p_diag(P):
  """[..., 15] P's diagonal, either layout."""
  if p_layout(P) == "packed":
    return P[..., np.flatnonzero(_TRI_DIAG)]
  return jnp.diagonal(P, axis1=-2, axis2=-1) if P.ndim > 2 else _diag(P)


def std_groups(P):
  """[..., 4] 1-sigma of an estimate from its covariance P (either layout): position (m), velocity (m/s), tilt (rad),
  yaw (rad), each the RMS over the group's axes of P's diagonal."""
  d = p_diag(P)
  g = lambda sl: jnp.sqrt(jnp.mean(d[..., sl], axis=-1))  # noqa: E731
  return jnp.stack([g(POS), g(VEL), g(slice(6, 8)), g(slice(8, 9))], axis=-1)


def add_to_diag(P, d):
  """P + diag(d), d [15] (one vehicle's P in either layout; elementwise)."""
  if p_layout(P) == "packed":
    return P + jnp.where(_TRI_DIAG, jnp.pad(d, (0, 1))[_TRI_ROW], 0.0)
  return P + _EYE * d[None, :]


def _diag(P):
  """[n] diagonal of P [n, n] as a strided slice (jnp.diag lowers to a gather, which XLA does not fuse well)."""
  return P.reshape(-1)[::P.shape[-1] + 1]


def condition(P, symmetrise: bool = True, diag=None):
  """Symmetrise (optional), replace non-finite entries, clamp the diagonal while keeping P PSD.

  One elementwise pass over P (the diagonal is read once; the scaled diagonal is d s^2, computed from it), so XLA
  fuses the whole of it into its producer and consumer. Without symmetrisation (no transpose) an exactly symmetric P
  stays exactly symmetric: the scaling multiplies entry (i, j) by the same float s_i s_j as entry (j, i).
  diag: [n] the diagonal of P after the symmetrisation and non-finite clean-up, if known (else read from P).
  """
  if symmetrise:
    P = 0.5 * (P + P.T)
  P = jnp.where(jnp.isfinite(P), P, 0.0)
  d = _diag(P) if diag is None else diag
  # upper clamp: scale row/column i by sqrt(max/var) (a congruence, so PSD is kept)
  s = jnp.sqrt(jnp.minimum(1.0, VAR_MAX / jnp.maximum(d, 1e-30)))
  # lower clamp: adding a nonnegative diagonal keeps PSD
  lift = jnp.maximum(VAR_MIN - d * (s * s), 0.0)
  return P * (s[:, None] * s[None, :]) + _EYE * lift[None, :]


# ----------------------------------------------------------------------------------------------------------------------


def ekf_init(cfg: EKFConfig, readings: SensorReadings, p_layout: str = "square") -> EKFState:
  """Initial state from one set of readings: horizontal position and velocity from GPS, height from the barometer,
  roll/pitch from the accelerometer's gravity direction, yaw from the magnetometer heading; zero biases.
  Use the readings of the first tick after `init_sensors` (every sensor fresh), with the vehicle at rest or nearly.
  p_layout: P's layout (`P_LAYOUTS`): "square", or "packed" for the lanes kernel (ekf_lanes.py).
  """
  if p_layout not in P_LAYOUTS:
    raise ValueError(f"ekf_init: p_layout {p_layout!r} is not one of {tuple(P_LAYOUTS)}")
  f = readings.accel
  roll = jnp.arctan2(f[1], f[2])
  pitch = jnp.arctan2(-f[0], jnp.sqrt(f[1] ** 2 + f[2] ** 2))
  quat = normalize_quat(euler_to_quat(jnp.stack([roll, pitch, readings.mag_yaw])))
  pos = jnp.stack([readings.gps_pos[0], readings.gps_pos[1], readings.baro_alt])
  sig = jnp.array([cfg.init_pos_sigma_h] * 2 + [cfg.init_pos_sigma_v] + [cfg.init_vel_sigma] * 3
                  + [cfg.init_tilt_sigma] * 2 + [cfg.init_yaw_sigma] + [cfg.init_gyro_bias_sigma] * 3
                  + [cfg.init_accel_bias_sigma] * 3, jnp.float32)
  z = jnp.zeros((), jnp.float32)
  zc = jnp.zeros((N_CHANNELS,), jnp.float32)
  return EKFState(pos=pos, vel=readings.gps_vel, quat=quat, gyro_bias=jnp.zeros(3), accel_bias=jnp.zeros(3),
                  P=in_layout(jnp.diag(sig ** 2), p_layout), gps_pos_age=z, gps_vel_age=z,
                  hgt_age=z, innov=zc, test_ratio=zc, accepted=jnp.ones((N_CHANNELS,), jnp.float32), fresh=zc,
                  reset=z, n_resets=z, time=z)


def predict_nominal(cfg: EKFConfig, s: EKFState, gyro, accel, dt):
  """Strapdown propagation of the nominal state over dt. Returns (state with the predicted pos/vel/quat and the old P,
  A [3, 3], B [3, 3]): the non-identity blocks of the error-state transition F = I + E, whose only blocks are
  d(pos)/d(vel) = I dt, d(vel)/d(att) = A = -[R a]x dt, d(vel)/d(accel bias) = d(att)/d(gyro bias) = B = -R dt."""
  w = jnp.clip(gyro, -GYRO_RANGE, GYRO_RANGE) - s.gyro_bias
  a = jnp.clip(accel, -ACCEL_RANGE, ACCEL_RANGE) - s.accel_bias
  # the IMU sample stands for the interval ending now: rotate the specific force with the mid-interval attitude
  quat = normalize_quat(quat_mul(s.quat, rotvec_to_quat(w * dt)))
  r = quat_to_rot(quat_mul(s.quat, rotvec_to_quat(0.5 * w * dt)))
  ra = matvec(r, a)
  acc_w = ra + jnp.array([0.0, 0.0, -GRAVITY])
  pos = s.pos + s.vel * dt + 0.5 * acc_w * dt * dt
  vel = s.vel + acc_w * dt
  return s.replace(pos=pos, vel=vel, quat=quat), -_skew(ra) * dt, -r * dt


def process_noise(cfg: EKFConfig, dt, xp=jnp):
  """[15] process-noise variances added to P's diagonal over one tick of dt (s); xp=np for a static table."""
  sigma = (0.0, cfg.accel_noise, cfg.gyro_noise, cfg.gyro_bias_noise, cfg.accel_bias_noise)
  return xp.concatenate([xp.full(3, (x * dt) ** 2, xp.float32) for x in sigma])


def predict_cov(cfg: EKFConfig, P, A, B, dt):
  """P <- F P F' + Q (F = I + E, see `predict_nominal`), then the tick's one symmetrisation and clamps.

  Written as row/column combinations of P (elementwise for XLA) instead of two dense batched 15x15 matmuls."""

  def rows(X, M, start):  # [3, 15]: M[3, 3] @ X[start:start+3, :]
    return sum(M[:, m, None] * X[start + m][None, :] for m in range(3))

  FP = P + jnp.concatenate([dt * P[VEL], rows(P, A, 6) + rows(P, B, 12), rows(P, B, 9), jnp.zeros((6, N_ERR))])

  def cols(X, M, start):  # [15, 3]: X[:, start:start+3] @ M'
    return sum(X[:, start + m, None] * M[None, :, m] for m in range(3))

  P = FP + jnp.concatenate([dt * FP[:, VEL], cols(FP, A, 6) + cols(FP, B, 12), cols(FP, B, 9),
                            jnp.zeros((N_ERR, 6))], axis=1)
  P = P + _EYE * process_noise(cfg, dt)[None, :]
  # The tick's one symmetrisation (a transpose): every later update of P this tick is exactly symmetric.
  return condition(P)


def _predict(cfg: EKFConfig, s: EKFState, gyro, accel, dt) -> EKFState:
  """Strapdown propagation of the nominal state and P over dt."""
  s, A, B = predict_nominal(cfg, s, gyro, accel, dt)
  return s.replace(P=layout_like(predict_cov(cfg, as_square(s.P), A, B, dt), s.P))


def _inject(cfg: EKFConfig, s: EKFState, dx) -> EKFState:
  """Adds an error-state correction dx[15] to the nominal state."""
  dq = rotvec_to_quat(dx[ATT])
  return s.replace(
    pos=s.pos + dx[POS], vel=s.vel + dx[VEL], quat=normalize_quat(quat_mul(dq, s.quat)),
    gyro_bias=jnp.clip(s.gyro_bias + dx[GBIAS], -cfg.gyro_bias_limit, cfg.gyro_bias_limit),
    accel_bias=jnp.clip(s.accel_bias + dx[ABIAS], -cfg.accel_bias_limit, cfg.accel_bias_limit))


# Scalar observation rows fused each tick: the 11 recorded CHANNELS, then the rover's non-holonomic pseudo-measurement.
_ROWS = CHANNELS + ("nhc_y", "nhc_z")
N_ROWS = len(_ROWS)
# gate groups (EKF2 accepts/rejects these vector observations as a whole): GPS horizontal position, GPS height,
# GPS velocity, baro, mag, flow, odometry, non-holonomic constraint
GROUP_OF_ROW = (0, 0, 1, 2, 2, 2, 3, 4, 5, 5, 6, 7, 7)
_GROUPS = np.array([[float(g == k) for g in GROUP_OF_ROW] for k in range(max(GROUP_OF_ROW) + 1)], np.float32)  # [8,13]
_MAG_ROW = CH["mag"]
# Error-state columns each observation row depends on (the structural non-zeros of H; tests/test_ekf.py checks them):
# GPS position/velocity and baro read one state each, the heading the attitude, flow/odometry/NHC velocity, attitude
# (and flow the height). Products with H only visit these columns.
H_SUPPORT = ((0,), (1,), (2,), (3,), (4,), (5,), (2,), (6, 7, 8), (2, 3, 4, 5, 6, 7, 8), (2, 3, 4, 5, 6, 7, 8),
              (3, 4, 5, 6, 7, 8), (3, 4, 5, 6, 7, 8), (3, 4, 5, 6, 7, 8))
_H_COLS = tuple(sorted(set(sum(H_SUPPORT, ()))))


def _observe(cfg: EKFConfig, pos, vel, r):
  """Predicted observation rows [13] (order `_ROWS`) from position, velocity and rotation body -> world."""
  vb = matvec_t(r, vel)
  flow = vb[:2] / jnp.maximum(pos[2], cfg.flow_min_height)
  yaw = jnp.arctan2(r[1, 0], r[0, 0])
  return jnp.concatenate([pos, vel, pos[2:3], yaw[None], flow, vb[0:1], vb[1:3]])


def _observe_err(cfg: EKFConfig, s: EKFState, dx):
  """Predicted observation rows [13] at the nominal state perturbed by the error state dx [15] (attitude error
  applied on the world side, R' = (I + [theta]x) R): the function `linearise` differentiates at dx = 0."""
  r = quat_to_rot(s.quat)
  return _observe(cfg, s.pos + dx[POS], s.vel + dx[VEL], (jnp.eye(3) + _skew(dx[ATT])) @ r)


def linearise(cfg: EKFConfig, s: EKFState):
  """Predicted observations [13] and their Jacobian H [13, 15] w.r.t. the error state, in closed form (the same as
  jax.jacfwd of `_observe_err` at 0, tests/test_ekf.py; jacfwd pushes 15 tangents through the rotation products,
  a large XLA kernel on a GPU).

  With body velocity vb = R' v: d vb / d vel = R', d vb / d theta = R' [v]x; the heading atan2(R10, R00) has
  d / d theta = (-R00 R20 / n, -R10 R20 / n, 1), n = R00^2 + R10^2; flow = vb[:2] / max(z, h_min)."""
  r = quat_to_rot(s.quat)
  pred = _observe(cfg, s.pos, s.vel, r)
  rt = r.T
  vb = matvec_t(r, s.vel)
  dvb_dv, dvb_dth = rt, jnp.stack([jnp.cross(r[:, k], s.vel) for k in range(3)])   # [3, 3] each
  n = r[0, 0] ** 2 + r[1, 0] ** 2
  dyaw = jnp.stack([-r[0, 0] * r[2, 0] / n, -r[1, 0] * r[2, 0] / n, jnp.ones(())])
  hgt = jnp.maximum(s.pos[2], cfg.flow_min_height)
  # d max(z, h_min) / dz as jax differentiates it (1/2 at the tie)
  dhgt = jnp.where(s.pos[2] > cfg.flow_min_height, 1.0, jnp.where(s.pos[2] == cfg.flow_min_height, 0.5, 0.0))
  z3, z6 = jnp.zeros(3), jnp.zeros(6)
  eye = jnp.eye(3)

  def row(pos=z3, vel=z3, att=z3):
    return jnp.concatenate([pos, vel, att, z6])

  e2 = jnp.array([0.0, 0.0, 1.0])
  rows = ([row(pos=eye[k]) for k in range(3)] + [row(vel=eye[k]) for k in range(3)] + [row(pos=e2), row(att=dyaw)]
          + [row(pos=e2 * (-vb[k] / hgt ** 2 * dhgt), vel=dvb_dv[k] / hgt, att=dvb_dth[k] / hgt) for k in range(2)]
          + [row(vel=dvb_dv[k], att=dvb_dth[k]) for k in range(3)])
  return pred, jnp.stack(rows)


def innovations(cfg: EKFConfig, s: EKFState, z):
  """Innovations [13] of the rows z [13] against the state (heading wrapped to (-pi, pi]) and H [13, 15] there."""
  pred, H = linearise(cfg, s)
  innov = z - pred
  return with_component(innov, _MAG_ROW, wrap_angle(innov[_MAG_ROW])), H


def row_used(cfg: EKFConfig, i: int, stale: tuple = ()) -> bool:
  """Whether observation row i (order `_ROWS`) can be fused with this configuration (static), given the sensors
  `stale` that cannot have a fresh sample this tick."""
  name = _ROWS[i]
  if name.startswith("gps") and "gps" in stale:
    return False
  if name.startswith("flow"):
    return cfg.use_flow
  if name == "odom":
    return cfg.use_odom
  if name.startswith("nhc"):
    return cfg.use_nhc
  if name == "gps_pos_z":
    return cfg.fuse_gps_height
  return True


def innovation_gate(innov, S, gate, enable):
  """EKF2's innovation-consistency gates of one tick's rows against the predicted variances S [13].

  A group is rejected as a whole if any of its rows fails its gate. Returns (test ratio [13], accept [13] bool, the
  innovations to fuse [13]: zero where rejected, so a non-finite rejected one cannot reach the state).
  """
  ratio = innov ** 2 / (gate ** 2 * S)
  ratio = jnp.where(jnp.isfinite(ratio), ratio, 1e6)
  bad = (enable & ~(ratio <= 1.0)).astype(jnp.float32)
  group_bad = (_GROUPS @ bad) > 0
  accept = enable & ~((_GROUPS.T @ group_bad.astype(jnp.float32)) > 0)
  return ratio, accept, jnp.where(accept, innov, 0.0)


def rows_unrolled(cfg: EKFConfig, P0, H, innov, R, gate, enable, stale: tuple = ()):
  """Gating and sequential fusion of the rows, unrolled in low-rank form for accelerators (see `_fuse`).

  Products with H visit only its structural non-zeros (H_SUPPORT), written as sums of scalars times rows of P (P is
  symmetric, so P h = sum_c h_c P[c, :]): elementwise work XLA fuses, where dense batched tiny matmuls are not. Each
  vector's entries are sliced out once and reused. Rows this vehicle never fuses are skipped statically.
  Returns (P [15, 15], dx [15], ratio [13], accept [13] bool).
  """
  hs = [{c: H[i, c] for c in H_SUPPORT[i]} for i in range(N_ROWS)]

  def entries(v):  # the entries of a [15]-vector (or rows of a matrix) that H's support can touch
    return {c: v[c] for c in _H_COLS}

  def hdot(i, ve):  # h_i . v, from v's entries
    return sum(h * ve[c] for c, h in hs[i].items())

  # PHt[i] = P_0 h_i [15]; a stale row is never enabled and its gate record is not kept: left at zero
  PHt = [hdot(i, entries(P0)) if row_used(cfg, i, stale) else jnp.zeros(N_ERR, P0.dtype) for i in range(N_ROWS)]
  S = jnp.stack([hdot(i, entries(PHt[i])) for i in range(N_ROWS)]) + R
  ratio, accept, innov = innovation_gate(innov, S, gate, enable)

  us, ues, cs = [], [], []  # us[j] = P_{j-1} h_j (ues[j] its entries), cs[j] = 1 / (h_j' P_{j-1} h_j + R_j) or 0
  dx = jnp.zeros(N_ERR, P0.dtype)
  for i in range(N_ROWS):
    if not row_used(cfg, i, stale):
      continue
    pht = PHt[i]
    for u, ue, c in zip(us, ues, cs):
      pht = pht - (c * hdot(i, ue)) * u
    pe = entries(pht)
    c = jnp.where(accept[i], 1.0 / (hdot(i, pe) + R[i]), 0.0)
    dx = dx + (c * (innov[i] - hdot(i, entries(dx)))) * pht
    us.append(pht)
    ues.append(pe)
    cs.append(c)
  # P_13 = P_0 - sum_i c_i u_i u_i' as an explicit sum of outer products (one elementwise pass, where a reduce over a
  # stacked [13, 15, 15] product is a costly kernel of its own). u_i u_i' is exactly symmetric, so P stays symmetric.
  P = P0
  for u, c in zip(us, cs):
    P = P - c * (u[:, None] * u[None, :])
  return P, dx, ratio, accept


def rows_rolled(cfg: EKFConfig, P0, H, innov, R, gate, enable, stale: tuple = ()):
  """The same gating and sequential fusion as `rows_unrolled`, one dense row per iteration of a rolled loop: the
  CPU form (small trace, quick to compile; the unrolled form doubles the env's compile time there).
  P_i = P_{i-1} - c_i u_i u_i' with u_i = P_{i-1} h_i, c_i = 1 / (h_i' u_i + R_i) (exactly symmetric).
  Returns (P [15, 15], dx [15], ratio [13], accept [13] bool).
  """
  S = jnp.einsum("mi,ij,mj->m", H, P0, H) + R
  ratio, accept, innov = innovation_gate(innov, S, gate, enable)
  used = jnp.asarray([row_used(cfg, i, stale) for i in range(N_ROWS)]) & accept

  def body(i, carry):
    P, dx = carry
    hi = H[i]
    u = jnp.sum(P * hi[None, :], axis=-1)
    c = jnp.where(used[i], 1.0 / (jnp.sum(hi * u) + R[i]), 0.0)
    return P - c * (u[:, None] * u[None, :]), dx + (c * (innov[i] - jnp.sum(hi * dx))) * u

  P, dx = jax.lax.fori_loop(0, N_ROWS, body, (P0, jnp.zeros(N_ERR, P0.dtype)))
  return P, dx, ratio, accept


def _fuse(cfg: EKFConfig, s: EKFState, z, noise, gate, enable, unrolled: bool | None = None, stale: tuple = ()):
  """Gated sequential scalar fusion of all observation rows of one tick.

  The rows are linearised once at the predicted state; gates use the predicted covariance; a group is rejected as a
  whole if any of its rows fails its gate; accepted rows are fused one scalar at a time into an accumulated
  error-state correction that is injected into the nominal state at the end.
  The covariance update is EKF2's per-row P -= K (H P), in one of two forms equal up to rounding (tests/test_ekf.py
  checks both against the dense textbook update in float64):
  * unrolled (accelerators, default off the CPU), low-rank: P_{i-1} h_i = P_0 h_i - sum_{j<i} c_j u_j (u_j' h_i), so
    the row loop only touches [15]-vectors and P is read once and written once (P_0 - sum_i c_i u_i u_i');
  * rolled (CPU): one dense row update per iteration of a fori_loop, a small trace that compiles quickly.
  Returns (state, innov[13], test_ratio[13], accepted[13] bool).
  """
  innov, H = innovations(cfg, s, z)
  R = noise ** 2
  if unrolled is None:
    unrolled = jax.default_backend() != "cpu"
  rows = rows_unrolled if unrolled else rows_rolled
  P, dx, ratio, accept = rows(cfg, as_square(s.P), H, innov, R, gate, enable, stale)
  return _inject(cfg, s.replace(P=layout_like(P, s.P)), dx), innov, ratio, accept


# Timeout resets (EKF2: reset to the measurement after reset_timeout of rejected fusion), one per block of the error
# state: (its columns, the observation rows whose acceptance counts as fused, whether all or any of them must be
# accepted). A block is reset on a tick where it is due (its sensor has a fresh sample and its age would pass the
# timeout) and its rows were not accepted; its rows and columns of P are cleared and its variance set to
# `reset_variances`.
RESETS = (((0, 1), (0, 1), "all"),        # horizontal position: GPS x, y
           ((3, 4, 5), (3, 4, 5), "all"),  # velocity: GPS velocity
           ((2,), (2, 6), "any"))          # height: GPS height or baro


def reset_variances(cfg: EKFConfig) -> tuple:
  """Variance each `RESETS` block is reset to (its measurement's noise variance)."""
  return (float(cfg.gps_pos_noise_h) ** 2, float(cfg.gps_vel_noise) ** 2, float(cfg.baro_noise) ** 2)


def _blocks_fused(accept):
  """[3] bool: whether each `RESETS` block's measurement counts as fused this tick, from accept [13] bool (static
  slices: no gather under vmap)."""
  return jnp.stack([functools.reduce(operator.and_ if how == "all" else operator.or_, [accept[r] for r in rows])
                    for _, rows, how in RESETS])


def _resets(accept, due):
  """[3] bool: which `RESETS` blocks are reset this tick, from accept [13] bool and due [3] bool."""
  return due & ~_blocks_fused(accept)


def reset_and_condition(cfg: EKFConfig, P, accept, due):
  """P [15, 15] after the fusion: the timeout resets of the blocks `_resets` picks, then the tick's closing clean-up
  (`condition` without symmetrisation: P is exactly symmetric here)."""
  cleared, new_var = jnp.zeros(N_ERR, bool), jnp.zeros(N_ERR, P.dtype)   # the blocks are disjoint: one pass does all
  for (cols, _, _), var, do in zip(RESETS, reset_variances(cfg), _resets(accept, due)):
    block = np.isin(np.arange(N_ERR), cols)
    cleared = cleared | (block & do)
    new_var = jnp.where(block & do, var, new_var)
  P = jnp.where(cleared[:, None] | cleared[None, :], 0.0, P) + _EYE * new_var[None, :]
  return condition(P, symmetrise=False)


def cov_tick(cfg: EKFConfig, P, A, B, dt, H, innov, R, gate, enable, due, stale: tuple = (),
              unrolled: bool | None = None):
  """The tick's covariance work in XLA: prediction of P (`predict_cov`), gates, sequential fusion (`_rows_*`), the
  timeout resets of the blocks that are due ([3] bool, order `RESETS`) and the closing clean-up.
  Returns (P in its layout, dx [15], test ratio [13], accept [13] bool). `ekf_lanes.tick_body` is the same filter
  per GPU lane."""
  if unrolled is None:
    unrolled = jax.default_backend() != "cpu"
  rows = rows_unrolled if unrolled else rows_rolled
  P_new, dx, ratio, accept = rows(cfg, predict_cov(cfg, as_square(P), A, B, dt), H, innov, R, gate, enable, stale)
  return layout_like(reset_and_condition(cfg, P_new, accept, due), P), dx, ratio, accept


def reset_block(P, idx, var, do):
  """Where `do`: clears rows/columns `idx` of one vehicle's P (either layout) and sets their variance to var
  (elementwise: no scatter into P)."""
  if p_layout(P) == "packed":
    mask = np.isin(np.arange(N_ERR), idx)
    hit = mask[_TRI_ROW] | mask[_TRI_COL]
    return jnp.where(hit & do, 0.0, P) + jnp.where(_TRI_DIAG & hit & do, var, 0.0)
  mask = jnp.zeros(N_ERR, bool).at[jnp.asarray(idx)].set(True) & do
  P = jnp.where(mask[:, None] | mask[None, :], 0.0, P)
  return P + _EYE * jnp.where(mask, var, 0.0)[None, :]


def noise_and_gates(cfg: EKFConfig):
  """Measurement noise std [13] and gates [13] (sigma) of the observation rows (order `_ROWS`), as numpy constants."""
  noise = np.array([cfg.gps_pos_noise_h] * 2 + [cfg.gps_pos_noise_v] + [cfg.gps_vel_noise] * 3
                   + [cfg.baro_noise, cfg.mag_heading_noise] + [cfg.flow_noise] * 2 + [cfg.odom_noise]
                   + [cfg.nhc_noise] * 2, np.float32)
  gate = np.array([cfg.gps_pos_gate] * 3 + [cfg.gps_vel_gate] * 3 + [cfg.baro_gate, cfg.mag_gate]
                  + [cfg.flow_gate] * 2 + [cfg.odom_gate] + [cfg.nhc_gate] * 2, np.float32)
  return noise, gate


def measurement_rows(cfg: EKFConfig, readings: SensorReadings):
  """Observation rows of one tick (order `_ROWS`): (z [13], noise std [13], gate [13] sigma)."""
  z = jnp.concatenate([readings.gps_pos, readings.gps_vel, readings.baro_alt[None], readings.mag_yaw[None],
                       readings.flow, readings.odom_speed[None], jnp.zeros(2)]).astype(jnp.float32)
  noise, gate = noise_and_gates(cfg)
  return z, jnp.asarray(noise), jnp.asarray(gate)


def normalized_innovations(cfg: EKFConfig, state: EKFState, readings: SensorReadings):
  """|innovation| / sqrt(H P H' + R) [N_CHANNELS] of every channel's current reading against `state`, without fusing
  anything (whether or not the channel has a fresh sample): how many sigmas a sensor disagrees with this estimate."""
  z, noise, _ = measurement_rows(cfg, readings)
  innov, H = innovations(cfg, state, z)
  S = _hph(H, state.P, N_CHANNELS) + noise[:N_CHANNELS] ** 2
  out = jnp.abs(innov[:N_CHANNELS]) / jnp.sqrt(S)
  return jnp.where(jnp.isfinite(out), out, 1e3)


def _hph(H, P, n_rows: int):
  """h_i' P h_i [n_rows] of the first n_rows rows of H [13, 15], P symmetric (any layout), over H's structural
  non-zeros only (H_SUPPORT): sums of scalar products, which XLA fuses (an einsum is a batched-matmul kernel of its
  own under vmap, every tick on a GPU)."""
  out = []
  for i in range(n_rows):
    sup = H_SUPPORT[i]
    h = [H[i, c] for c in sup]
    out.append(sum(h[a] * h[a] * p_entry(P, sup[a], sup[a]) for a in range(len(sup)))
               + 2.0 * sum(h[a] * h[b] * p_entry(P, sup[a], sup[b]) for a in range(len(sup)) for b in range(a)))
  return jnp.stack(out)


def ekf_step(cfg: EKFConfig, state: EKFState, readings: SensorReadings, dt, stale: tuple = (),
             records: bool = True, prep=None) -> EKFState:
  """One tick: IMU prediction over dt (s), gated fusion of every fresh measurement, timeout resets.

  stale: static names of sensors (only "gps" is recognised) known to have no fresh sample this tick, for every
  vehicle: their observation rows are left out of the traced fusion (cheaper; the same result as the full tick when
  their fresh flags are indeed 0, which the caller guarantees: a fresh sample would be ignored).
  records: False leaves the per-channel records (innov, test_ratio, accepted, fresh) as `state` holds them, for a
  filter whose records nobody reads (static; the env's `EnvConfig.ekf_records`): the same filter otherwise, three
  [11]-float selects and a write fewer per tick.
  prep: None (the XLA filter), or a function that does the tick's prediction, innovations and covariance work in
  its place: prep(cfg, P, quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z [13], enable [13] bool (the flow
  rows before the predicted-height check), due [3] bool, dt, stale) -> (P, dx [15], ratio [13], accept [13] bool,
  innov [13], the predicted pos [3], vel [3], quat [4]). ekf_lanes.ekf_step passes the lanes kernel's (this module
  knows no kernel).
  """
  f32 = jnp.float32
  gps = (readings.gps_fresh > 0.5) & ("gps" not in stale)
  baro = readings.baro_fresh > 0.5
  mag = readings.mag_fresh > 0.5
  flow_pre = (readings.flow_fresh > 0.5) & cfg.use_flow       # before the predicted-height check
  odom = (readings.odom_fresh > 0.5) & cfg.use_odom
  nhc = (readings.odom_fresh > 0.5) & cfg.use_nhc

  def fresh_rows(flow):
    return jnp.stack([gps, gps, gps, gps, gps, gps, baro, mag, flow, flow, odom, nhc, nhc])

  z, noise, gate = measurement_rows(cfg, readings)
  # timeout resets due this tick if the block's rows are not accepted (`RESETS` order; applied to P in the cov tick)
  ages = jnp.stack([state.gps_pos_age, state.gps_vel_age, state.hgt_age]) + dt
  due = jnp.stack([gps, gps, baro]) & (ages > cfg.reset_timeout)
  if prep is not None:   # the prediction, H, the innovations and the covariance work elsewhere (a kernel)
    enable = with_component(fresh_rows(flow_pre), 2, gps & cfg.fuse_gps_height)
    P, dx, ratio, accept, innov, pos, vel, quat = prep(
      cfg, state.P, state.quat, state.vel, state.pos, state.gyro_bias, state.accel_bias, readings.gyro,
      readings.accel, z, enable, due, dt, tuple(stale))
    s = state.replace(pos=pos, vel=vel, quat=quat)
    fresh = fresh_rows(flow_pre & (s.pos[2] >= cfg.flow_min_height))
  else:
    s, A, B = predict_nominal(cfg, state, readings.gyro, readings.accel, dt)
    fresh = fresh_rows(flow_pre & (s.pos[2] >= cfg.flow_min_height))
    enable = with_component(fresh, 2, gps & cfg.fuse_gps_height)
    innov, H = innovations(cfg, s, z)
    P, dx, ratio, accept = cov_tick(cfg, state.P, A, B, dt, H, innov, noise ** 2, gate, enable, due, tuple(stale))
  s = _inject(cfg, s.replace(P=P), dx)

  # per-channel records (held while a channel is not fresh)
  fc = fresh[:N_CHANNELS]
  if records:
    rec = dict(innov=jnp.where(fc, innov[:N_CHANNELS], state.innov),
               test_ratio=jnp.where(fc, ratio[:N_CHANNELS], state.test_ratio),
               accepted=jnp.where(fc, accept[:N_CHANNELS].astype(f32), state.accepted), fresh=fc.astype(f32))
  else:
    rec = {name: getattr(state, name) for name in RECORD_FIELDS}

  # timeout bookkeeping and the nominal state's side of the resets (P's side was done in the cov tick)
  reset_pos, reset_vel, reset_hgt = _resets(accept, due)
  gps_pos_age, gps_vel_age, hgt_age = jnp.where(_blocks_fused(accept), 0.0, ages)
  horizontal = jnp.arange(3) < 2
  pos = jnp.where(reset_pos & horizontal, readings.gps_pos, s.pos)
  pos = jnp.where(reset_hgt, with_component(pos, 2, readings.baro_alt), pos)
  vel = jnp.where(reset_vel, readings.gps_vel, s.vel)
  any_reset = reset_pos | reset_vel | reset_hgt

  return s.replace(
    pos=jnp.where(jnp.isfinite(pos), pos, 0.0), vel=jnp.where(jnp.isfinite(vel), vel, 0.0),
    gps_pos_age=jnp.where(reset_pos, 0.0, gps_pos_age),
    gps_vel_age=jnp.where(reset_vel, 0.0, gps_vel_age),
    hgt_age=jnp.where(reset_hgt, 0.0, hgt_age),
    **rec, reset=any_reset.astype(f32), n_resets=state.n_resets + any_reset, time=state.time + dt)


def on_gps_schedule(step, gps_due):
  """step(stale) -> the tick's EKF state, for a tick whose GPS freshness is known for every vehicle: gps_due None (not
  known: the full tick, step(())), a Python bool (static: step(()) or step(("gps",)), the GPS rows left out), or an
  unbatched traced bool (a lax.cond between the two: only one branch runs)."""
  if gps_due is None:
    return step(())
  if isinstance(gps_due, (bool, np.bool_)):
    return step(()) if gps_due else step(("gps",))
  return jax.lax.cond(gps_due, lambda: step(()), lambda: step(("gps",)))


# ----------------------------------------------------------------------------------------------------------------------
# accessors


def ekf_euler(state: EKFState):
  """[3] estimated (roll, pitch, yaw), rad (ZYX)."""
  return quat_to_euler(state.quat)


def ekf_body_rates(state: EKFState, readings: SensorReadings):
  """[3] body angular rate (rad/s): gyro minus the estimated bias."""
  return jnp.clip(readings.gyro, -GYRO_RANGE, GYRO_RANGE) - state.gyro_bias


def ekf_rotmat(state: EKFState):
  """[3, 3] estimated rotation body -> world."""
  return quat_to_rot(state.quat)


def ekf_body_velocity(state: EKFState):
  """[3] estimated velocity in the body frame (FLU), m/s."""
  return matvec_t(quat_to_rot(state.quat), state.vel)


def ekf_std(state: EKFState):
  """[15] 1-σ of the error state (pos m, vel m/s, attitude rad, gyro bias rad/s, accel bias m/s^2)."""
  return jnp.sqrt(jnp.maximum(p_diag(state.P), 0.0))
