"""Selective state reconstruction (SpecGuard Sec. 4.5 / DeLorean): Checkpointer + Estimator.

SpecGuard's state input (per vehicle, INPUT_NAMES order) x'_t [15] =
  pos [3] world m | vel [3] world m/s | acc [3] world m/s^2 (no gravity) | euler [3] rad (roll, pitch, yaw) |
  rate [3] body rad/s.
It is computed from the EKF and the readings (`input_vector`), exactly as envs.base._observation does for the first 12.

While the detector's alarm is down, the Checkpointer records trusted states and controls. When the alarm rises, the
Estimator starts from the checkpoint `lag` entries before the newest (margin for detection delay), rolls it forward
with the fitted dynamics model (dynamics.py) over the buffered commanded controls up to the previous tick, and from
then on runs a shadow EKF (the autopilot's own filter, ekf.ekf_step) on the UNCOMPROMISED sensors only:
  * a compromised GPS / magnetometer / barometer / optical flow is simply not fused (its fresh flag is cleared), so
    e.g. under GPS spoofing position is dead-reckoned from IMU + flow velocity + baro height + mag heading;
  * a compromised gyroscope is replaced by the model's body rate, integrated from the predicted angular acceleration
    (rotor-thrust torques), which the shadow EKF then corrects with the remaining aiding (GPS velocity, mag, flow)
    through its attitude / gyro-bias states (the latter folded into the model rate every tick); when the gyro is
    newly blamed, the attitude its spoofed rates dragged the shadow to is re-levelled (`_relevel`: gravity reference
    from the GPS velocity and the model's specific force, magnetometer yaw), and a gyro blamed for `sticky_after_s`
    stays replaced until the hand-back;
  * a compromised accelerometer is replaced by the model's specific force (thrust / mass along body z, drag); the
    shadow's accel-bias state then restarts and tracks the model's error (mass / thrust-gain uncertainty, larger
    clamp `model_accel_limit`), and returns to the last trusted sensor-bias estimate on hand-back. A ground vehicle
    (rover) uses a physical level-vehicle force instead of the fitted one (`_model_force`: it ran away);
Selective output: only the components of x'_t that derive from a compromised sensor (SENSOR_DEPS) are replaced by
the shadow estimate; the rest stays as measured (EKF). Everything is pure JAX, jittable and vmappable.

The above is ReconConfig.mode "fused" (the default). Mode "paper" is the reconstruction as the SpecGuard paper
(Sec. 4.5, App. A.4) and DeLorean describe it: a Checkpointer of trusted states and an Estimator that is the fitted
system-identification model alone. When the alarm rises, the checkpoint `lag` entries before the newest is rolled
forward through the model over the buffered commanded controls, and from then on the model is integrated OPEN LOOP
over the commanded controls, every tick, with no correction from any sensor (`_paper_tick`). The compromised
components of x'_t (SENSOR_DEPS of the diagnosis mask) are the model's; the uncompromised ones stay the autopilot
EKF's / the readings' (selective output as above), and are the model's inputs for them at the next step. The checkpoint lag must cover the detector's delay, or the
checkpoint already holds the attack (`check_lag`). The model's uncertainty grows with the time since the checkpoint
(ReconState.ckpt_age; `_paper_variances`), and is carried in the trusted estimate's covariance (`recon_std`).

Mode "oracle" is no method but a bound: the fused mode runs underneath, and while it is active its outputs are the
truth (`oracle_outputs`: the true position, velocity and attitude, the sensors' readings without the attack). The
unchanged autopilot flown on it shows what perfect reconstruction would give: what is left is the detector's delay,
what happens before the alarm and after the hand-back, and the control authority.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import attacks as attacks_lib
from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes
from specguard_jax import math3d
from specguard_jax.detection.detector import CHANNEL_SENSOR
from specguard_jax.estimation import checkpointer as ck
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.estimation import traces
from specguard_jax.types import RECON_MODES, SENSOR_NAMES

INPUT_NAMES = ("pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z", "acc_x", "acc_y", "acc_z",
               "roll", "pitch", "yaw", "rate_x", "rate_y", "rate_z")
N_INPUT = len(INPUT_NAMES)
POS, VEL, ACC, EULER, RATE = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


def _deps():
  d = {n: np.zeros(N_INPUT, bool) for n in SENSOR_NAMES}
  d["gps"][POS] = d["gps"][VEL] = True
  d["gyro"][:] = True                     # strapdown: attitude, then rotated specific force -> vel -> pos
  d["accel"][:RATE.start] = True          # specific force -> acc, vel, pos; tilt through velocity fusion
  d["mag"][EULER] = d["mag"][ACC] = True  # heading -> yaw -> world-frame acceleration
  d["baro"][[2, 5]] = True                # height, vertical speed
  d["flow"][[0, 1, 3, 4]] = True          # horizontal velocity and position
  return np.stack([d[n] for n in SENSOR_NAMES])


SENSOR_DEPS = _deps()
_GBIAS_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.GBIAS]   # error-state rows of the gyro / accel bias
_ABIAS_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.ABIAS]
_VEL_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.VEL]
_TILT_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.ATT][:2]   # world-frame attitude error: x, y (tilt), z (yaw)
_YAW_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.ATT][2:]
_POS_H_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.POS][:2]   # error-state rows of the horizontal position / velocity
_VEL_H_IDX = list(range(ekf_lib.N_ERR))[ekf_lib.VEL][:2]
_Z_IDX = [list(range(ekf_lib.N_ERR))[ekf_lib.POS][2], list(range(ekf_lib.N_ERR))[ekf_lib.VEL][2]]   # height, vz
# [11, 6] EKF channel (ekf.CHANNELS) -> the sensor it measures (the detector's map; odometry: none).
_CHANNEL_MASK = (np.asarray(CHANNEL_SENSOR[:len(ekf_lib.CHANNELS)])[:, None]
                 == np.arange(len(SENSOR_NAMES))[None, :]).astype(np.float32)
"""[6, 15] bool: SENSOR_DEPS[s, i] = component i of x'_t derives from sensor s (SENSOR_NAMES order)."""

# Checkpoint entry layout: pos 3, vel 3, acc 3, quat 4, rate 3, gyro_bias 3, accel_bias 3.
CKPT_SIZES = (("pos", 3), ("vel", 3), ("acc", 3), ("quat", 4), ("rate", 3), ("gyro_bias", 3), ("accel_bias", 3))
N_CKPT = sum(n for _, n in CKPT_SIZES)


def _unpack(v):
  out, i = {}, 0
  for name, n in CKPT_SIZES:
    out[name] = v[..., i:i + n]
    i += n
  return out


@dataclasses.dataclass(frozen=True)
class ReconConfig:
  """window: checkpoint ring size (ticks).  lag: checkpoint age used when the alarm rises (ticks; >= the detector's
  delay, < window).  n_controls: 4 (drone rotor thrusts) or 2 (rover throttle, steer).  ekf: the shadow EKF's
  EKFConfig (the vehicle's, e.g. EKFConfig.drone()); None -> EKFConfig.drone().
  mode: "fused" (closed-loop shadow EKF on the uncompromised sensors), "paper" (open-loop model roll-out from the
  checkpoint) or "oracle" (the truth while active, an upper bound: `oracle_outputs`); module docstring. The other
  fields below are the fused mode's (oracle's too), except window / lag / n_controls / ekf / ground_drive / sticky_*
  (all modes) and paper_* (the paper mode's uncertainty model, `_paper_variances`)."""
  window: int = 50
  lag: int = 10
  n_controls: int = 4
  ekf: Any = None
  model_rate_noise: float = 0.3   # rad/s^2/sqrt(Hz): random walk of the model-rate error (shadow gyro-bias state)
  model_rate_limit: float = 3.0   # rad/s: clamp of that state
  # A newly blamed gyroscope (_relevel): the attitude its spoofed rates dragged the shadow to is dropped.
  relevel_tilt_sigma: float = 0.2  # rad: roll/pitch uncertainty of the shadow then
  relevel_rate_sigma: float = 0.2  # rad/s: uncertainty of its model-rate error (gyro-bias) state then
  relevel_min_tilt: float = 0.15   # rad: roll/pitch are re-levelled from the gravity reference when the shadow's tilt
                                   # disagrees with it by more than this (else the shadow's are kept)
  relevel_alpha: float = 0.3       # EMA weight per GPS sample of the gravity reference (ReconState gvel..f_lp)
  relevel_mag_gate: float = 1.05   # rad (60 deg): the heading is taken from a magnetometer the diagnosis clears only
                                   # when it is within this of the shadow's. A gyro ramp below the detector's threshold
                                   # drags the heading 10-50 deg before the alarm (an honest magnetometer there); the
                                   # paper's magnetometer spoofs are 90-180 deg (Table 3), and a gyro + magnetometer
                                   # attack whose diagnosis names only the gyro otherwise hands the shadow the spoofed
                                   # heading (the red team's attack on DeLorean: reversed heading, flipped in ~1.4 s)
  sticky_gyro: bool = True         # a gyroscope blamed once stays replaced until the hand-back, even when the diagnosis
                                   # moves on to another sensor (flying on the spoofed rates again flips the vehicle)
  sticky_after_s: float = 0.5      # s; ... once it has been blamed this long without a break (a transient gyro blame
                                   # of a GPS ramp's first ticks kept the shadow on the model rate for the whole alarm)
  # With the accelerometer replaced by the model's specific force, the shadow's accel-bias state tracks the model's
  # error (mass and thrust-gain uncertainty: up to ~2 m/s^2 vertically), not the sensor's bias:
  model_accel_sigma: float = 1.0  # m/s^2: its standard deviation when the accelerometer is (newly) replaced
  model_accel_noise: float = 0.05  # m/s^3/sqrt(Hz): its random walk while replaced
  model_accel_limit: float = 3.0  # m/s^2: clamp of the shadow's accel-bias state
  consistency_sigma: float = 3.0  # a compromised aiding sensor further than this (innovation sigmas) from the shadow
                                  # estimate is still under attack: `suspect` (holds the recovery switch)
  anchor_pos_sigma: float = 2.0   # m: horizontal position uncertainty of the GPS-free anchor (recon_tick `anchor`)
  anchor_vel_sigma: float = 0.5   # m/s: its horizontal velocity uncertainty
  baro_z_sigma: float = 3.0       # m: height uncertainty of the shadow when the barometer is newly blamed (a ramp
  baro_vz_sigma: float = 0.5      # m/s: and vertical speed)   dragged the EKF's height before the alarm: the GPS
                                  # height pulls it back within ~1 s instead of ~10 s)
  # Ground vehicle (ekf use_nhc): longitudinal force model of a replaced accelerometer (`_model_force`): drive force
  # at full throttle (N), rolling resistance (N s/m), drag (N s^2/m^2), mass (kg); the rover's nominal values
  # (autopilot.ardurover.RoverParams, assets/rover.xml).
  ground_drive: tuple = (70.0, 3.0, 0.2, 10.0)
  mode: str = "fused"
  # Paper mode's model uncertainty (`_paper_variances`): the fitted model's training residuals (DynParams.rms_lin /
  # rms_ang) act as white errors per tick; on top, a persistent specific-force error over one reconstruction: the
  # per-episode randomisation the fit averages over (mass +-10 %, thrust gain +-8 %: uniform, ~0.7 m/s^2 at hover
  # combined; drag +-30 %, wind), and a persistent angular-acceleration error (inertia +-10 % of the commanded torques).
  paper_accel_bias_sigma: float = 0.2   # m/s^2 (after paper_calibrate; 0.7 without it)
  paper_alpha_bias_sigma: float = 0.05  # rad/s^2
  # The fitted model is the fleet's (fitted over randomised vehicles), the paper's / DeLorean's the vehicle's own: the
  # paper mode identifies this vehicle's specific-force offset (body frame, m/s^2) from the model on the trusted
  # ring entries up to the checkpoint (`_paper_force_bias`; the env's ring holds paper_calib_s of them before it).
  paper_calibrate: bool = True
  paper_calib_s: float = 2.0
  # Body-rate clamp of the paper mode's model (rad/s): PX4's MC_ROLLRATE_MAX / MC_PITCHRATE_MAX 220 deg/s; the
  # autopilot never commands more, and the fitted polynomial (|w| w terms) runs away to inf outside that envelope.
  paper_rate_limit: float = 3.84
  # ... and speed clamp (m/s): above the envelope (PX4 MPC_XY_VEL_MAX 12 m/s horizontally, MPC_Z_VEL_MAX_UP 3 m/s);
  # the fitted |v| v and u |v| terms feed back positively outside the training data (the rover's did, `_model_force`).
  paper_speed_limit: float = 20.0

  def __post_init__(self):
    if self.mode not in RECON_MODES:
      raise ValueError(f"unknown reconstruction mode {self.mode!r}; choose one of {RECON_MODES}")

  @property
  def lag_ticks(self) -> int:
    """Ticks between the checkpoint rolled forward and the tick before the alarm (the ring holds window entries)."""
    return min(self.lag, self.window - 1)

  def ekf_cfg(self):
    return dataclasses.replace(self.ekf or ekf_lib.EKFConfig.drone(), gyro_bias_limit=self.model_rate_limit,
                               accel_bias_limit=self.model_accel_limit)

  @property
  def ground_vehicle(self) -> bool:
    """A ground vehicle (its shadow EKF fuses the non-holonomic constraint: the rover); static."""
    return self.ekf_cfg().use_nhc


@struct.dataclass
class ReconState:
  """ckpt: CheckpointState.  shadow: EKFState of the shadow filter (meaningful while active).
  rate: [3] model body rate (rad/s).  active: [] bool, reconstruction running (alarm up).
  since: [] s since the alarm rose (0 while inactive).  suspect: [] bool, a compromised GPS / baro / magnetometer /
  optical-flow reading disagrees with the shadow estimate by more than `consistency_sigma` (latest fresh sample;
  False while inactive): the attack is still on, so the recovery switch must not hand control back yet.
  blamed: [6] 0/1 the compromised mask of the last tick (zeros while inactive).
  Gravity reference (_relevel; updated every tick): gvel [3] GPS velocity of the last sample (m/s, NaN before the
  first), gage [] s since it, f_sum [3] the model's specific force integrated since it (m/s), acc_w [3] EMA of the
  world acceleration between GPS samples (m/s^2), f_lp [3] EMA of the mean model specific force over the same
  intervals (m/s^2, body).  gyro_t: [] s the gyroscope has been blamed without a break in this alarm
  (`sticky_after_s`).  model: dyn.DynState, the paper mode's open-loop model state (this tick's; its initial value
  outside the alarm; unused by the fused mode).  ckpt_age: [] s since the checkpoint the reconstruction started from
  (the replay's length plus the alarm's; 0 while inactive)."""
  ckpt: ck.CheckpointState
  shadow: Any
  rate: jnp.ndarray
  active: jnp.ndarray
  since: jnp.ndarray
  suspect: jnp.ndarray
  blamed: jnp.ndarray
  gvel: jnp.ndarray
  gage: jnp.ndarray
  f_sum: jnp.ndarray
  acc_w: jnp.ndarray
  f_lp: jnp.ndarray
  gyro_t: jnp.ndarray
  model: Any
  ckpt_age: jnp.ndarray


def input_vector(ekf_state, readings) -> jax.Array:
  """x'_t [15] from an EKF state and the readings it fused (see module docstring)."""
  r = math3d.quat_to_rot(ekf_state.quat)
  acc = math3d.matvec(r, readings.accel - ekf_state.accel_bias) + dyn.G
  rate = ekf_lib.ekf_body_rates(ekf_state, readings)
  return jnp.concatenate([ekf_state.pos, ekf_state.vel, acc, ekf_lib.ekf_euler(ekf_state), rate])


def true_input_vector(truth) -> jax.Array:
  """x'_t [15] of a TrueState (ground truth for scoring)."""
  return jnp.concatenate([truth.pos, truth.vel, truth.acc, math3d.quat_to_euler(truth.quat), truth.ang_vel])


def oracle_outputs(active, trusted, trusted_readings, x_rec, truth, clean_readings):
  """Mode "oracle" (module docstring): recon_tick's (trusted EKFState, trusted SensorReadings, x_reconstructed [15])
  with, while `active` ([] bool, ReconState.active), the true position, velocity and attitude in the estimate (its
  bias states kept), the readings without the attack (`clean_readings`: the sensors' noisy readings before the
  attack entered) and x'_t of the truth (`true_input_vector`)."""
  perfect = trusted.replace(pos=truth.pos, vel=truth.vel, quat=truth.quat)
  pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(active, x, y), a, b)
  return (pick(perfect, trusted), pick(clean_readings, trusted_readings),
          jnp.where(active, true_input_vector(truth), x_rec))


def _entry(ekf_state, readings):
  x = input_vector(ekf_state, readings)
  return jnp.concatenate([ekf_state.pos, ekf_state.vel, x[ACC], ekf_state.quat, x[RATE], ekf_state.gyro_bias,
                          ekf_state.accel_bias])


def recon_init(cfg: ReconConfig, ekf_state) -> ReconState:
  """Empty checkpoint, inactive; `ekf_state` is a template for the shadow filter (e.g. the env's initial EKF)."""
  return ReconState(ckpt=ck.ckpt_init(cfg.window, N_CKPT, cfg.n_controls), shadow=ekf_state, rate=jnp.zeros(3),
                    active=jnp.zeros((), bool), since=jnp.zeros(()), suspect=jnp.zeros((), bool),
                    blamed=jnp.zeros((len(SENSOR_NAMES),), jnp.float32), gvel=jnp.full(3, jnp.nan, jnp.float32),
                    gage=jnp.zeros(()), f_sum=jnp.zeros(3), acc_w=jnp.zeros(3), f_lp=jnp.zeros(3),
                    gyro_t=jnp.zeros(()), model=_model_init(), ckpt_age=jnp.zeros(()))


def _model_init() -> dyn.DynState:
  return dyn.DynState(pos=jnp.zeros(3), vel=jnp.zeros(3), quat=jnp.array([1.0, 0.0, 0.0, 0.0]), rate=jnp.zeros(3))


def check_lag(cfg: ReconConfig, delay_s: float, dt: float) -> None:
  """One-line ValueError unless the checkpoint lag (cfg.lag_ticks ticks of dt s) covers a detection delay of
  `delay_s` s: the paper mode rolls forward from that checkpoint with no sensor correction, so one that the attack
  had already reached when it was recorded would be replayed as trusted."""
  if cfg.lag_ticks * dt + 1e-9 < delay_s:
    raise ValueError(f"reconstruction checkpoint lag {cfg.lag_ticks} ticks x {dt} s = {cfg.lag_ticks * dt:.3g} s is "
                     f"shorter than the detector's delay {delay_s:.3g} s (raise ReconConfig.lag / window)")


def recon_std(state: ReconState) -> jax.Array:
  """[4] 1-sigma per axis of the estimate the autopilot flies on (ReconState.shadow: the reconstruction's while the
  alarm is up, else the autopilot EKF's): position (m), velocity (m/s), tilt (rad), yaw (rad); RMS over the axes of
  each group, from its covariance (fused: the shadow filter's; paper: the EKF's with the model-propagated components'
  rows replaced by `_paper_variances`)."""
  return ekf_lib.std_groups(state.shadow.P)


def _gravity_ref(cfg: ReconConfig, state: ReconState, readings, f_model, dt):
  """The gravity reference's fields after this tick (ReconState docstring): a GPS sample closes an interval, whose
  world acceleration dv / interval and mean model specific force (thrust and drag, so neither IMU sensor) are EMA'd."""
  fresh = readings.gps_fresh > 0.5
  gage = state.gage + dt
  f_sum = state.f_sum + f_model * dt
  ok = fresh & jnp.all(jnp.isfinite(state.gvel)) & (gage > 0.5 * dt)
  a_in = (readings.gps_vel - state.gvel) / jnp.maximum(gage, dt)
  f_in = f_sum / jnp.maximum(gage, dt)
  al = cfg.relevel_alpha
  acc_w = jnp.where(ok, state.acc_w + al * (a_in - state.acc_w), state.acc_w)
  f_lp = jnp.where(ok, jnp.where(jnp.any(state.f_lp != 0), state.f_lp + al * (f_in - state.f_lp), f_in), state.f_lp)
  return dict(gvel=jnp.where(fresh, readings.gps_vel, state.gvel), gage=jnp.where(fresh, 0.0, gage),
              f_sum=jnp.where(fresh, 0.0, f_sum), acc_w=acc_w, f_lp=f_lp)


def _relevel(cfg: ReconConfig, state: ReconState, shadow, rate, readings, mask, do, switch):
  """Where `do` (gyroscope newly blamed): drop the attitude the spoofed rates dragged the shadow to.

  A slow gyro ramp below the detector's threshold (or a first diagnosis that blamed another sensor) leaves 10-50 deg
  of attitude error in the checkpoint and so in the shadow; its aiding cannot pull that back (the 3-sigma
  magnetometer and 5-sigma GPS-velocity gates reject it), so the autopilot held a wrong attitude and the vehicle
  flipped ~1.5 s later. Here: yaw from the magnetometer if the diagnosis clears it and it is within
  relevel_mag_gate of the shadow's heading (else the shadow's heading is kept: a magnetometer spoofed in the same
  attack, not yet named), or from it anyway while the ring holds no checkpoint `lag` entries old; roll/pitch from the
  gravity reference (the GPS-derived world acceleration a and the model's specific force f over the last ~0.3 s
  satisfy R f = a - g: the shortest tilt mapping f onto a - g under that yaw) where the shadow's tilt disagrees with
  it by more than relevel_min_tilt; velocity from the (trusted) GPS; the attitude / velocity / model-rate-error
  covariance blocks reset so the aiding is accepted again; the model rate restarts at zero where the diagnosis
  switched to the gyro during the alarm (`switch`: it was the spoofed gyro's; a rising alarm's comes from the
  checkpoint's model roll).
  Returns (shadow, rate)."""
  ecfg = cfg.ekf_cfg()
  gps_ok = do & ~mask[SENSOR_NAMES.index("gps")]
  e = math3d.quat_to_euler(shadow.quat)
  mag_off = jnp.abs(math3d.wrap_angle(readings.mag_yaw - e[2]))   # rad, [0, pi]
  # The shadow's heading is a trusted reference only once the ring holds a checkpoint `lag` entries old: an alarm in
  # a mission's first lag ticks replays from an entry the attack may already have dragged (onset at take-off). An
  # attack from take-off detected later than that still drags the checkpoint; the gate then keeps the dragged heading.
  ckpt_trusted = state.ckpt.count > cfg.lag_ticks
  mag_ok = do & ~mask[SENSOR_NAMES.index("mag")] & ((mag_off <= cfg.relevel_mag_gate) | ~ckpt_trusted)
  yaw = jnp.where(mag_ok, readings.mag_yaw, e[2])
  quat = math3d.euler_to_quat(jnp.stack([e[0], e[1], yaw]))
  u, f = state.acc_w - dyn.G, state.f_lp
  nu, nf = math3d.norm(u), math3d.norm(f)
  uh, fh = u / jnp.maximum(nu, 1e-6), f / jnp.maximum(nf, 1e-6)
  qz = jnp.stack([jnp.cos(0.5 * yaw), 0.0, 0.0, jnp.sin(0.5 * yaw)])
  uy = math3d.matvec_t(math3d.quat_to_rot(qz), uh)                                             # a - g in the yaw frame
  qt = jnp.concatenate([jnp.reshape(1.0 + math3d.dot(fh, uy), (1,)), jnp.cross(fh, uy)])   # shortest rotation fh -> uy
  q_acc = math3d.quat_mul(qz, qt / jnp.maximum(math3d.norm(qt), 1e-6))
  off = jnp.arccos(jnp.clip(math3d.dot(math3d.matvec(math3d.quat_to_rot(quat), fh), uh), -1.0, 1.0))   # shadow's tilt
  acc_ok = (gps_ok & jnp.all(jnp.isfinite(state.gvel)) & (nf > 3.0) & (nu > 3.0) & (math3d.dot(fh, uy) > 0.0)
            & (off > cfg.relevel_min_tilt))
  quat = jnp.where(acc_ok, q_acc / math3d.norm(q_acc), quat)
  p = ekf_lib.reset_block(shadow.P, _TILT_IDX, cfg.relevel_tilt_sigma ** 2, do)
  p = ekf_lib.reset_block(p, _YAW_IDX, jnp.where(mag_ok, ecfg.mag_heading_noise ** 2, ecfg.init_yaw_sigma ** 2), do)
  p = ekf_lib.reset_block(p, _VEL_IDX, jnp.where(gps_ok, ecfg.gps_vel_noise ** 2, ecfg.init_vel_sigma ** 2), do)
  p = ekf_lib.reset_block(p, _GBIAS_IDX, cfg.relevel_rate_sigma ** 2, do)
  shadow = shadow.replace(quat=jnp.where(mag_ok | acc_ok, quat, shadow.quat),
                          vel=jnp.where(gps_ok, readings.gps_vel, shadow.vel),
                          gyro_bias=jnp.where(do, 0.0, shadow.gyro_bias), P=p)
  return shadow, jnp.where(do & switch, 0.0, rate)


def _model_rate(cfg: ReconConfig, rate):
  """The model body rate (rad/s [3]) the shadow replays / flies on. Ground vehicle (the shadow EKF has the
  non-holonomic constraint: rover): no roll / pitch rate, yaw rate clamped to model_rate_limit. The rover's fitted
  angular model has no roll / pitch dynamics to speak of (trained on ~0 rates; |w| w terms of +-50..350), so a
  checkpoint that a spoofed gyro x/y bias had given a few rad/s of roll rate blew its replay up to NaN within 5 ticks
  (the shadow's state then read zeros for the whole alarm). Drone: unchanged."""
  if not cfg.ground_vehicle:
    return rate
  return jnp.stack([jnp.zeros_like(rate[0]), jnp.zeros_like(rate[1]),
                    jnp.clip(rate[2], -cfg.model_rate_limit, cfg.model_rate_limit)])


def _model_force(cfg: ReconConfig, f_b, s: dyn.DynState, controls):
  """The model body specific force (m/s^2 [3]) that stands in for a replaced accelerometer. Ground vehicle (use_nhc:
  rover, controls = (throttle, steer)): the drive force minus rolling resistance and drag over the mass
  (`ground_drive`) longitudinally, the centripetal force (body forward speed x the model yaw rate) laterally and
  gravity vertically. The rover's fitted linear model has positive velocity feedback outside its training data
  (lateral / vertical speed, braking at speed: throttle x speed), so a shadow flying on it ran away within 1-3 s
  (hundreds of m/s, kilometres of reconstruction error; its GPS innovations then fell outside the gates). The
  shadow's accel-bias state absorbs the per-episode drive-gain / mass error as before. Drone: unchanged."""
  if not cfg.ground_vehicle:
    return f_b
  drive, rolling, drag, mass = cfg.ground_drive
  u = math3d.matvec_t(math3d.quat_to_rot(s.quat), s.vel)[0]
  fx = (controls[0] * drive - rolling * u - drag * u * jnp.abs(u)) / mass
  return jnp.stack([fx, u * s.rate[2], jnp.full_like(fx, -dyn.G[2])])


def dependent_components(compromised_mask) -> jax.Array:
  """[15] bool: components of x'_t derived from any sensor in compromised_mask ([6] 0/1, SENSOR_NAMES order)."""
  m = jnp.asarray(compromised_mask) > 0
  return jnp.any(m[:, None] & jnp.asarray(SENSOR_DEPS), axis=0)


def _ring_reads(cfg: ReconConfig, c: ck.CheckpointState):
  """What a tick reads from the checkpoint ring, one entry per read (not the whole ring in order): (start [] int32,
  the ordered index of the replay's checkpoint `lag` entries before the newest; its entry [N_CKPT]; the replay's
  controls [lag, n_u] (those stored with entries start + 1 .. start + lag, clipped to the newest); the oldest trusted
  entry [N_CKPT])."""
  w = cfg.window
  lag = min(cfg.lag, w - 1)
  start = jnp.maximum(w - 1 - lag, w - c.count)  # ordered index of the checkpoint (newest = w - 1)
  return (start, c.states[ck.ckpt_slot(c, start)], c.controls[ck.ckpt_slot(c, start + 1 + jnp.arange(lag))],
          ck.ckpt_get(c, w - 1)[0])


def _start(cfg: ReconConfig, params: dyn.DynParams, start, entry, controls, ekf_state, dt):
  """Shadow filter and model rate at the PREVIOUS tick, rolled forward from the checkpoint entry at ordered index
  `start` over the controls stored after it ([lag, n_u]; see `_ring_reads`)."""
  w = cfg.window
  lag = controls.shape[0]
  e = _unpack(entry)
  s0 = dyn.DynState(pos=e["pos"], vel=e["vel"], quat=e["quat"], rate=_model_rate(cfg, e["rate"]))

  def body(i, s):
    j = start + 1 + i  # controls stored with entry j moved the vehicle from entry j-1 to entry j
    s_new = dyn.step(params, s, controls[i], dt)
    s_new = s_new.replace(rate=_model_rate(cfg, s_new.rate))
    return jax.tree.map(lambda a, b: jnp.where(j <= w - 1, a, b), s_new, s)

  # Unrolled on accelerators: a device while-loop costs a launch and a host sync per iteration (tens of us each on a
  # GPU), and this replay runs every tick for every env (a vmapped branch computes both sides).
  s = jax.lax.fori_loop(0, lag, body, s0, unroll=max(lag, 1) if jax.default_backend() != "cpu" else 1)
  shadow = ekf_state.replace(pos=s.pos, vel=s.vel, quat=s.quat, gyro_bias=e["gyro_bias"],
                             accel_bias=e["accel_bias"], gps_pos_age=jnp.zeros(()), gps_vel_age=jnp.zeros(()),
                             hgt_age=jnp.zeros(()))
  return shadow, s.rate


def recon_update(cfg: ReconConfig, params: dyn.DynParams, state: ReconState, ekf_state, readings, controls,
                 compromised_mask, alarm, dt, anchor=None):
  """One autopilot tick; see recon_tick. Returns (new ReconState, x_reconstructed [15])."""
  new, x_rec, _, _ = recon_tick(cfg, params, state, ekf_state, readings, controls, compromised_mask, alarm, dt,
                                anchor)
  return new, x_rec


def recon_tick(cfg: ReconConfig, params: dyn.DynParams, state: ReconState, ekf_state, readings, controls,
               compromised_mask, alarm, dt, anchor=None, gps_due=None, kernel: str = "xla",
               records: bool = True):
  """One autopilot tick of dt (s).

  kernel: the shadow filter's tick, "xla" or "lanes" (ekf_lanes.ekf_step's, resolved: ekf_lanes.resolve_ekf_kernel;
  "lanes" under vmap, dt a Python float): the same filter to float32 rounding. records: False leaves the shadow
  filter's per-channel records as they were (ekf.ekf_step's `records`; an env whose detector does not read them,
  EnvConfig.ekf_records).

  gps_due: optional bool, the same for every vehicle (a Python bool, or [] unbatched under vmap): False on a tick where
  no GPS sample can be fresh (envs/base.py's schedule); the shadow filter then leaves the GPS rows out
  (ekf.on_gps_schedule). None: every tick may carry one.

  anchor: optional [4] GPS-free horizontal position (m) and velocity (m/s) of this tick (the detector's dead
  reckoning, detection.detector.position_check: dr[0], aid_vel); when the GPS becomes compromised (the alarm rises
  blaming it, or the diagnosis turns to it) the shadow filter's horizontal position and velocity restart there
  (uncertainty anchor_pos_sigma / anchor_vel_sigma) instead of at the checkpoint, which a stealthy GPS ramp has
  already dragged. None: the checkpoint's.

  ekf_state: the autopilot's EKFState after fusing `readings` (possibly attacked).  readings: SensorReadings of this
  tick.  controls: [n_u] controls applied during the previous tick (drone: sim['vehicle']['rotors'] before the tick's
  vehicle update).  compromised_mask: [6] 0/1 (SENSOR_NAMES order) from the diagnosis.  alarm: [] 0/1 detector flag.
  Returns (new ReconState, x_reconstructed [15] (INPUT_NAMES), trusted EKFState, trusted SensorReadings): with the
  alarm down x_reconstructed = x'_t measured and the trusted estimate/readings are the inputs; with it up they are
  the shadow filter and the readings it fused (compromised gyro/accel replaced by the model), which a controller can
  fly on (DeLorean: the autopilot runs on reconstructed states). On the tick the alarm falls (hand-back) the
  estimate is still the shadow's, for the caller to re-sync the autopilot's EKF to (envs/base.py does), with the
  bias states of a replaced gyro/accelerometer back at their last trusted (pre-alarm) values, and the readings are the
  sensors' again.
  """
  alarm = jnp.asarray(alarm) > 0
  mask = jnp.asarray(compromised_mask) > 0
  gi, ai = SENSOR_NAMES.index("gyro"), SENSOR_NAMES.index("accel")
  if cfg.sticky_gyro:   # a gyroscope blamed for sticky_after_s in this alarm stays replaced until the hand-back
    mask = mask.at[gi].set(mask[gi] | (alarm & (state.blamed[gi] > 0) & (state.gyro_t >= cfg.sticky_after_s)))
  x_meas = input_vector(ekf_state, readings)
  rising = alarm & ~state.active
  falling = state.active & ~alarm   # the recovery switch hands back on this tick
  start, entry, replay_controls, oldest = _ring_reads(cfg, state.ckpt)
  # Every read of the old ring before this tick's entry is written into it in place (ckpt_update below): without
  # the ordering XLA would copy the whole ring every tick to keep the old one alive for a late read.
  ring, (entry, replay_controls, oldest) = jax.lax.optimization_barrier(
      (state.ckpt, (entry, replay_controls, oldest)))
  e_old = _unpack(oldest)   # oldest trusted entry
  if cfg.mode == "paper":
    return _paper_tick(cfg, params, state, ekf_state, readings, controls, mask, alarm, dt, x_meas, rising, falling,
                       start, entry, replay_controls, ring)
  with jax.named_scope("recon_replay"):   # (a profiling scope: bench/gpu_profile.py's stages)
    shadow0, rate0 = _start(cfg, params, start, entry, replay_controls, ekf_state, dt)
  shadow = jax.tree.map(lambda a, b: jnp.where(rising, a, b), shadow0, state.shadow)
  rate = jnp.where(rising, rate0, state.rate)
  # A newly replaced accelerometer: the accel-bias state restarts (zero, model_accel_sigma) to learn the model's error.
  new_accel = mask[ai] & ~(state.blamed[ai] > 0)
  shadow = shadow.replace(accel_bias=jnp.where(new_accel, 0.0, shadow.accel_bias),
                          P=ekf_lib.reset_block(shadow.P, _ABIAS_IDX, cfg.model_accel_sigma ** 2, new_accel))
  # ... and one no longer blamed while the alarm stays up (the diagnosis changed): the sensor is back, its bias state
  # returns to the last trusted estimate (the model-error state it held drove a GPS-free shadow off course).
  un_accel = alarm & ~rising & ~mask[ai] & (state.blamed[ai] > 0)
  shadow = shadow.replace(accel_bias=jnp.where(un_accel, e_old["accel_bias"], shadow.accel_bias),
                          P=ekf_lib.reset_block(shadow.P, _ABIAS_IDX, cfg.ekf_cfg().init_accel_bias_sigma ** 2,
                                                un_accel))
  # Likewise a gyroscope un-blamed before it stuck (sticky_after_s: a transient blame): the gyro-bias state, zeroed
  # every tick while the model rate stood in for it, returns to the last trusted estimate.
  un_gyro = alarm & ~rising & ~mask[gi] & (state.blamed[gi] > 0)
  shadow = shadow.replace(gyro_bias=jnp.where(un_gyro, e_old["gyro_bias"], shadow.gyro_bias),
                          P=ekf_lib.reset_block(shadow.P, _GBIAS_IDX, cfg.ekf_cfg().init_gyro_bias_sigma ** 2,
                                                un_gyro))
  # A newly blamed barometer (the EKF's height reference): the height / vertical speed are uncertain by what it dragged.
  bi = SENSOR_NAMES.index("baro")
  new_baro = mask[bi] & ~(state.blamed[bi] > 0)
  shadow = shadow.replace(P=ekf_lib.reset_block(ekf_lib.reset_block(shadow.P, _Z_IDX[:1], cfg.baro_z_sigma ** 2,
                                                                    new_baro), _Z_IDX[1:], cfg.baro_vz_sigma ** 2,
                                                new_baro))
  if anchor is not None:   # a newly compromised GPS: horizontal position / velocity from the GPS-free anchor
    gpi = SENSOR_NAMES.index("gps")
    anchor = jnp.asarray(anchor, jnp.float32)
    new_gps = alarm & mask[gpi] & ~(state.blamed[gpi] > 0) & jnp.all(jnp.isfinite(anchor))
    p = ekf_lib.reset_block(shadow.P, _POS_H_IDX, cfg.anchor_pos_sigma ** 2, new_gps)
    shadow = shadow.replace(pos=shadow.pos.at[:2].set(jnp.where(new_gps, anchor[:2], shadow.pos[:2])),
                            vel=shadow.vel.at[:2].set(jnp.where(new_gps, anchor[2:4], shadow.vel[:2])),
                            P=ekf_lib.reset_block(p, _VEL_H_IDX, cfg.anchor_vel_sigma ** 2, new_gps))

  # A newly blamed gyroscope (the alarm rises blaming it, or the diagnosis turns to it): see _relevel.
  new_gyro = alarm & mask[gi] & ~(state.blamed[gi] > 0)
  shadow, rate = _relevel(cfg, state, shadow, rate, readings, mask, new_gyro, ~rising)

  # model-predicted rate and specific force for this tick
  rate = _model_rate(cfg, rate)
  s = dyn.DynState(pos=shadow.pos, vel=shadow.vel, quat=shadow.quat, rate=rate)
  _, alpha = dyn.derivatives(params, s, controls)
  f_b = _model_force(cfg, dyn.specific_force(params, s, controls), s, controls)
  rate_new = _model_rate(cfg, rate + alpha * dt)
  gps, mag, baro, flow = (mask[SENSOR_NAMES.index(n)] for n in ("gps", "mag", "baro", "flow"))
  zero = jnp.zeros(())
  rd = readings.replace(
      gyro=jnp.where(mask[gi], rate_new + shadow.gyro_bias, readings.gyro),
      # (the model's specific force as the measurement: the shadow subtracts its accel-bias state, which so learns
      # the model's error; adding that state here too would cancel it and leave the model error uncorrected)
      accel=jnp.where(mask[ai], f_b, readings.accel),
      gps_fresh=jnp.where(gps, zero, readings.gps_fresh), mag_fresh=jnp.where(mag, zero, readings.mag_fresh),
      baro_fresh=jnp.where(baro, zero, readings.baro_fresh), flow_fresh=jnp.where(flow, zero, readings.flow_fresh))
  # With a model gyro / accelerometer the shadow's gyro- / accel-bias state tracks the model's error: inflate its
  # process noise (the accel-bias state restarts when the accelerometer is newly replaced, above).
  q = jnp.where(mask[gi], cfg.model_rate_noise ** 2 * dt, 0.0)
  qa = jnp.where(mask[ai], cfg.model_accel_noise ** 2 * dt, 0.0)
  gb, ab = (np.isin(np.arange(ekf_lib.N_ERR), _GBIAS_IDX), np.isin(np.arange(ekf_lib.N_ERR), _ABIAS_IDX))
  q_diag = jnp.where(gb, q, jnp.where(ab, qa, 0.0))
  shadow = shadow.replace(P=ekf_lib.add_to_diag(shadow.P, q_diag))   # P in any layout, elementwise (no scatter)
  shadow_step = lambda stale: ekf_lanes.ekf_step(cfg.ekf_cfg(), shadow, rd, dt, stale=stale, kernel=kernel,
                                                 records=records)
  with jax.named_scope("shadow_ekf"):
    shadow = ekf_lib.on_gps_schedule(shadow_step, gps_due)
  # the model rate follows the shadow filter's corrected rate (gyro-bias state absorbs model error)
  rate_new = rd.gyro - shadow.gyro_bias
  # ... with the correction folded into it: the gyro-bias state (the model rate's error) restarts at zero every tick,
  # so a persistent model error does not walk it into its clamp (model_rate_limit) over a long alarm.
  shadow = shadow.replace(gyro_bias=jnp.where(mask[gi], 0.0, shadow.gyro_bias))
  rd = rd.replace(gyro=jnp.where(mask[gi], rate_new, rd.gyro))
  x_shadow = input_vector(shadow, rd)
  use = (alarm & dependent_components(mask)) | falling
  x_rec = jnp.where(use, x_shadow, x_meas)

  # Is a compromised aiding sensor still far from the shadow estimate (the attack still on)?
  suspect = _suspect(cfg, state, shadow, readings, mask, alarm)

  ckpt = ck.ckpt_update(ring, _entry(ekf_state, readings), controls, alarm)
  # On the hand-back tick the trusted estimate is still the shadow's (the env re-syncs the autopilot's EKF to it,
  # so the autopilot does not resume on a filter that fused the attack); its gating timers start afresh.
  on = alarm | falling
  zero = jnp.zeros(())
  # A replaced gyro / accelerometer comes back on the hand-back tick: its bias states return to the last trusted
  # (pre-alarm) estimate with their initial uncertainty (the shadow's described the model's error, not the sensor's).
  back_g, back_a = falling & (state.blamed[gi] > 0), falling & (state.blamed[ai] > 0)
  ecfg = cfg.ekf_cfg()
  p_back = ekf_lib.reset_block(shadow.P, _GBIAS_IDX, ecfg.init_gyro_bias_sigma ** 2, back_g)
  p_back = ekf_lib.reset_block(p_back, _ABIAS_IDX, ecfg.init_accel_bias_sigma ** 2, back_a)
  shadow_out = shadow.replace(gps_pos_age=jnp.where(falling, zero, shadow.gps_pos_age),
                              gps_vel_age=jnp.where(falling, zero, shadow.gps_vel_age),
                              hgt_age=jnp.where(falling, zero, shadow.hgt_age),
                              gyro_bias=jnp.where(back_g, e_old["gyro_bias"], shadow.gyro_bias),
                              accel_bias=jnp.where(back_a, e_old["accel_bias"], shadow.accel_bias), P=p_back)
  trusted = jax.tree.map(lambda a, b: jnp.where(on, a, b), shadow_out, ekf_state)
  trusted_rd = jax.tree.map(lambda a, b: jnp.where(alarm, a, b), rd, readings)   # sensors back on hand-back
  new = ReconState(**_gravity_ref(cfg, state, readings, f_b, dt), ckpt=ckpt, shadow=trusted,
                   rate=jnp.where(alarm, rate_new, x_meas[RATE]), active=alarm,
                   since=jnp.where(alarm, state.since + dt, 0.0), suspect=suspect,
                   blamed=jnp.where(alarm, mask.astype(jnp.float32), 0.0),
                   gyro_t=jnp.where(alarm & mask[gi], state.gyro_t + dt, 0.0), model=state.model,
                   ckpt_age=_ckpt_age(cfg, state, start, alarm, rising, dt))
  return new, x_rec, trusted, trusted_rd


def _suspect(cfg: ReconConfig, state: ReconState, est, readings, mask, alarm):
  """[] bool: a compromised (`mask` [6] bool) aiding sensor's latest fresh sample is more than consistency_sigma
  innovation sigmas from the estimate `est` (EKFState; its covariance P), i.e. the attack is still on; held between
  samples; False with the alarm down."""
  z = ekf_lib.normalized_innovations(cfg.ekf_cfg(), est, readings)
  fresh = jnp.stack([readings.gps_fresh] * 6 + [readings.baro_fresh, readings.mag_fresh] + [readings.flow_fresh] * 2
                    + [jnp.zeros(())]) > 0.5
  sampled = (math3d.matvec(jnp.asarray(_CHANNEL_MASK), mask.astype(jnp.float32)) > 0) & fresh
  bad = jnp.any(sampled & (z > cfg.consistency_sigma))
  # (held between samples; a diagnosis that changes drops what the previous mask's sensors said)
  same = jnp.all(mask == (state.blamed > 0))
  return alarm & jnp.where(jnp.any(sampled), bad, state.suspect & same)


def _ckpt_age(cfg: ReconConfig, state: ReconState, start, alarm, rising, dt):
  """[] s since the checkpoint (ReconState.ckpt_age): on the rising tick the replay from ordered index `start` to the
  newest entry (the previous tick) and this tick, (window - start) ticks; then + dt per tick of the alarm."""
  age0 = (cfg.window - start).astype(jnp.float32) * dt
  return jnp.where(alarm, jnp.where(rising, age0, state.ckpt_age + dt), 0.0)


def _paper_variances(cfg: ReconConfig, params: dyn.DynParams, tau, p0, dt):
  """Variances of the paper mode's open-loop model state `tau` s after the checkpoint: [9] error-state rows
  pos x/y/z (m^2), vel x/y/z (m^2/s^2), tilt x/y, yaw (rad^2).

  p0 [15]: the variances at the checkpoint (the autopilot EKF's diagonal). Error sources, independent: the fitted
  model's residuals (rms_lin m/s^2, rms_ang rad/s^2: RMS over the axes) white per tick of dt, so the n-fold integral
  of a white error of intensity q = sigma^2 dt has variance q tau^(2n-1) / ((n-1)!^2 (2n-1)); the persistent errors
  paper_accel_bias_sigma / paper_alpha_bias_sigma (integral n of a constant: tau^n / n!); the checkpoint's own
  velocity / tilt errors; a tilt error theta tilts the thrust and so accelerates the vehicle by g theta horizontally.
  All grow with tau (tau^2 .. tau^8 terms): an upper-bound-like spread, not a filter's."""
  g = dyn.GRAVITY
  qa = jnp.mean(params.rms_lin ** 2) * dt
  qw = jnp.mean(params.rms_ang ** 2) * dt
  ba, bw = cfg.paper_accel_bias_sigma, cfg.paper_alpha_bias_sigma
  t = jnp.maximum(tau, 0.0)
  att = qw * t ** 3 / 3.0 + (bw * t ** 2 / 2.0) ** 2                                   # from the angular model error
  tilt0 = jnp.mean(p0[6:8])
  vel = (p0[3:6] + qa * t + (ba * t) ** 2
         + g ** 2 * (tilt0 * t ** 2 + qw * t ** 5 / 20.0 + (bw * t ** 3 / 6.0) ** 2))
  pos = (p0[0:3] + p0[3:6] * t ** 2 + qa * t ** 3 / 3.0 + (ba * t ** 2 / 2.0) ** 2
         + g ** 2 * (tilt0 * t ** 4 / 4.0 + qw * t ** 7 / 252.0 + (bw * t ** 4 / 24.0) ** 2))
  return jnp.concatenate([pos, vel, p0[6:9] + att])


def _paper_rate(cfg: ReconConfig, rate):
  """The paper mode's model body rate: `_model_rate`, clamped to paper_rate_limit (rad/s)."""
  return jnp.clip(_model_rate(cfg, rate), -cfg.paper_rate_limit, cfg.paper_rate_limit)


def _paper_force(cfg: ReconConfig, params: dyn.DynParams, s: dyn.DynState, u, f_bias):
  """[3] the paper mode's model body specific force (m/s^2) at state s under controls u: the fitted one (a ground
  vehicle's: `_model_force`) plus the vehicle's identified offset f_bias [3]."""
  return _model_force(cfg, dyn.specific_force(params, s, u), s, u) + f_bias


def _paper_step(cfg: ReconConfig, params: dyn.DynParams, s: dyn.DynState, u, dt, f_bias) -> dyn.DynState:
  s = dyn.step(params, s, u, dt, specific_force=_paper_force(cfg, params, s, u, f_bias))
  vel = s.vel * jnp.minimum(1.0, cfg.paper_speed_limit / jnp.maximum(math3d.norm(s.vel), 1e-6))
  return s.replace(vel=vel, rate=_paper_rate(cfg, s.rate))


def _paper_force_bias(cfg: ReconConfig, params: dyn.DynParams, ring: ck.CheckpointState, start):
  """[3] mean body-frame specific force measured minus the model's over the trusted ring entries up to the checkpoint
  (ordered index `start`; zeros without paper_calibrate or data). Entry j's world acceleration was produced by the
  controls stored with it at the state of entry j - 1 (as the fit pairs them, dynamics._fit)."""
  if not cfg.paper_calibrate:
    return jnp.zeros(3)
  states, controls, valid = ck.ckpt_ordered(ring)
  e = _unpack(states)
  prev = dyn.DynState(pos=e["pos"][:-1], vel=e["vel"][:-1], quat=e["quat"][:-1], rate=e["rate"][:-1])
  f_mod = jax.vmap(lambda st, u: _paper_force(cfg, params, st, u, jnp.zeros(3)))(prev, controls[1:])
  r = jax.vmap(math3d.quat_to_rot)(e["quat"][1:])
  f_meas = jnp.einsum("nji,nj->ni", r, e["acc"][1:] - dyn.G)
  j = jnp.arange(1, states.shape[0])
  w = (valid[1:] & valid[:-1] & (j <= start)).astype(jnp.float32)
  return jnp.sum(w[:, None] * (f_meas - f_mod), 0) / jnp.maximum(jnp.sum(w), 1.0)


def _paper_start(cfg: ReconConfig, params: dyn.DynParams, start, entry, controls, dt, f_bias) -> dyn.DynState:
  """The model state at the PREVIOUS tick: the checkpoint entry at ordered index `start` rolled forward over the
  controls stored after it ([lag, n_u]; see `_ring_reads`), as `_start` for the fused mode."""
  w = cfg.window
  e = _unpack(entry)
  s0 = dyn.DynState(pos=e["pos"], vel=e["vel"], quat=e["quat"], rate=_paper_rate(cfg, e["rate"]))

  def body(i, s):
    s_new = _paper_step(cfg, params, s, controls[i], dt, f_bias)
    return jax.tree.map(lambda a, b: jnp.where(start + 1 + i <= w - 1, a, b), s_new, s)

  lag = controls.shape[0]
  return jax.lax.fori_loop(0, lag, body, s0, unroll=max(lag, 1) if jax.default_backend() != "cpu" else 1)


def _paper_tick(cfg: ReconConfig, params: dyn.DynParams, state: ReconState, ekf_state, readings, controls, mask,
                alarm, dt, x_meas, rising, falling, start, entry, replay_controls, ring):
  """recon_tick of the paper mode (module docstring); the same inputs and outputs.

  The model state (ReconState.model) is this tick's: on the rising tick the checkpoint rolled forward to the previous
  tick (`_paper_start`, as `_start` for the fused mode), then one model step over `controls` (which moved the vehicle
  from the previous tick to this one); each later tick of the alarm one more step. The model is the fitted one with
  the vehicle's specific-force offset identified before the checkpoint (`_paper_force_bias`) and the clamps
  paper_rate_limit / paper_speed_limit. Selective (DeLorean): each step's uncompromised components are the autopilot EKF's, so e.g.
  under a GPS attack position and velocity are integrated open loop from the model's thrust along the EKF's attitude;
  the compromised ones get no correction from any sensor until the hand-back. x'_t's model components: pos, vel, the
  world acceleration R f + g of the model's specific force f at this state and controls, Euler angles, body rate.
  The trusted estimate (what the autopilot flies on) is the autopilot EKF's with the compromised components replaced
  by the model's (Euler angles recomposed into the quaternion), the replaced sensors' bias states at the checkpoint's
  (trusted) values, and the covariance rows of the replaced components at `_paper_variances`; the trusted readings
  have a compromised gyroscope / accelerometer replaced by the model's rate / specific force (plus those bias
  states) and a compromised aiding sensor's sample dropped (fresh flag cleared). Hand-back (the tick the alarm falls):
  the trusted estimate is still the reconstruction under the last diagnosis, with its model-grown covariance and
  fresh gating timers, for the env to re-sync the autopilot's EKF to (the returning sensors then pull it back
  through the ordinary gates); the readings are the sensors' again."""
  gi, ai = SENSOR_NAMES.index("gyro"), SENSOR_NAMES.index("accel")
  on = alarm | falling
  f_bias = _paper_force_bias(cfg, params, ring, start)
  with jax.named_scope("recon_replay"):
    s0 = _paper_start(cfg, params, start, entry, replay_controls, dt, f_bias)
  s_prev = jax.tree.map(lambda a, b: jnp.where(rising, a, b), s0, state.model)
  s = _paper_step(cfg, params, s_prev, controls, dt, f_bias)    # the model's prediction of this tick
  use_mask = jnp.where(alarm, mask, state.blamed > 0)          # hand-back: the last alarm tick's diagnosis
  dep = dependent_components(use_mask) & on
  # Selective: the uncompromised components are the EKF's, also as the model's starting point for the next tick.
  ea = dep[EULER]
  quat = jnp.where(jnp.all(ea), s.quat, jnp.where(
      jnp.any(ea), math3d.euler_to_quat(jnp.where(ea, math3d.quat_to_euler(s.quat), x_meas[EULER])), ekf_state.quat))
  s = dyn.DynState(pos=jnp.where(dep[POS], s.pos, ekf_state.pos), vel=jnp.where(dep[VEL], s.vel, ekf_state.vel),
                   quat=quat, rate=jnp.where(dep[RATE], s.rate, x_meas[RATE]))
  f_b = _paper_force(cfg, params, s, controls, f_bias)
  x_model = jnp.concatenate([s.pos, s.vel, math3d.matvec(math3d.quat_to_rot(s.quat), f_b) + dyn.G,
                             math3d.quat_to_euler(s.quat), s.rate])
  x_rec = jnp.where(dep, x_model, x_meas)

  # trusted estimate: the EKF's with the replaced components
  e_ck = _unpack(entry)
  gyro_bias = jnp.where(use_mask[gi], e_ck["gyro_bias"], ekf_state.gyro_bias)
  accel_bias = jnp.where(use_mask[ai], e_ck["accel_bias"], ekf_state.accel_bias)
  age = _ckpt_age(cfg, state, start, alarm, rising, dt)
  var = _paper_variances(cfg, params, jnp.where(falling, state.ckpt_age + dt, age), ekf_lib.p_diag(ekf_state.P),
                         dt)
  rows = jnp.concatenate([dep[POS], dep[VEL], jnp.stack([ea[0] | ea[1]] * 2), ea[2:3]])
  P = ekf_state.P
  for i in range(9):   # static rows: elementwise resets in either P layout
    P = ekf_lib.reset_block(P, [i], var[i], rows[i])
  zero = jnp.zeros(())
  est = ekf_state.replace(pos=x_rec[POS], vel=x_rec[VEL], quat=quat, gyro_bias=gyro_bias, accel_bias=accel_bias, P=P,
                          gps_pos_age=jnp.where(falling, zero, ekf_state.gps_pos_age),
                          gps_vel_age=jnp.where(falling, zero, ekf_state.gps_vel_age),
                          hgt_age=jnp.where(falling, zero, ekf_state.hgt_age))
  trusted = jax.tree.map(lambda a, b: jnp.where(on, a, b), est, ekf_state)
  gps, mag, baro, flow = (mask[SENSOR_NAMES.index(n)] for n in ("gps", "mag", "baro", "flow"))
  rd = readings.replace(
      gyro=jnp.where(mask[gi], s.rate + gyro_bias, readings.gyro),
      accel=jnp.where(mask[ai], f_b + accel_bias, readings.accel),
      gps_fresh=jnp.where(gps, zero, readings.gps_fresh), mag_fresh=jnp.where(mag, zero, readings.mag_fresh),
      baro_fresh=jnp.where(baro, zero, readings.baro_fresh), flow_fresh=jnp.where(flow, zero, readings.flow_fresh))
  trusted_rd = jax.tree.map(lambda a, b: jnp.where(alarm, a, b), rd, readings)
  suspect = _suspect(cfg, state, trusted, readings, mask, alarm)
  ckpt = ck.ckpt_update(ring, _entry(ekf_state, readings), controls, alarm)
  new = ReconState(ckpt=ckpt, shadow=trusted, rate=jnp.where(alarm, s.rate, x_meas[RATE]), active=alarm,
                   since=jnp.where(alarm, state.since + dt, 0.0), suspect=suspect,
                   blamed=jnp.where(alarm, mask.astype(jnp.float32), 0.0), gvel=state.gvel, gage=state.gage,
                   f_sum=state.f_sum, acc_w=state.acc_w, f_lp=state.f_lp,
                   gyro_t=jnp.where(alarm & mask[gi], state.gyro_t + dt, 0.0),
                   model=jax.tree.map(lambda a, b: jnp.where(alarm, a, b), s, _model_init()), ckpt_age=age)
  return new, x_rec, trusted, trusted_rd


def recon_scan(cfg: ReconConfig, params: dyn.DynParams, ekf_states, readings, controls, compromised_mask, alarms,
               dt):
  """recon_update over a [T] sequence of one vehicle (lax.scan). Returns x_reconstructed [T, 15]."""
  init = recon_init(cfg, jax.tree.map(lambda a: a[0], ekf_states))

  def body(st, xs):
    e, r, u, a = xs
    st, x = recon_update(cfg, params, st, e, r, u, compromised_mask, a, dt)
    return st, x

  return jax.lax.scan(body, init, (ekf_states, readings, controls, alarms))[1]


def replay_under_attack(cfg: ReconConfig, params, ekf_cfg, trace, schedule, dt):
  """Replay one recorded attack-free mission (envs.record of traces.RECORD_FIELDS, unbatched: leaves [T, ...]) with
  `schedule` applied to its sensor stream and an oracle alarm (the attack window, diagnosis = its mask).

  Returns (x_ekf [T, 15] of a fresh EKF on the attacked readings, x_rec [T, 15] selective reconstruction,
  x_true [T, 15], alarm [T] bool).
  """
  rd = traces.attacked_readings(trace["readings"], schedule, trace["time"])
  ek = traces.replay_ekf(ekf_cfg, jax.tree.map(lambda a: a[0], trace["ekf"]), rd, dt)
  alarm = jax.vmap(lambda t: attacks_lib.attack_active(schedule, t))(trace["time"])
  x_rec = recon_scan(cfg, params, ek, rd, trace["controls"], schedule.mask, alarm, dt)
  x_ekf = jax.vmap(input_vector)(ek, rd)
  x_true = jax.vmap(true_input_vector)(trace["truth"])
  return x_ekf, x_rec, x_true, alarm
