"""Model-based residual detector (PID-Piper style CUSUM), sensor diagnosis, recovery switch and an oracle.

Per autopilot tick the detector compares what the vehicle model predicts with what each sensor measures:

  * EKF channels 0-10 (specguard_jax.ekf.CHANNELS): GPS position/velocity, baro, mag heading, optical flow and
    odometry against the IMU-propagated EKF prediction. Their normalised residual is the EKF innovation in sigma,
    |innov| / sqrt(H P H' + R) = sqrt(test_ratio) * gate, fed only on ticks where the channel had a fresh sample.
  * IMU channels 11-16 (accel x/y/z, gyro x/y/z) against the commanded actuation:
      drone: body specific force predicted from the rotor thrusts and a drag model, f = (sum(T) e_z + D(v_b)) / m;
        body rates from a leaky observer driven by the angular acceleration of the commanded torques,
        w_dot = I^-1 (E_tau T - w x I w), pulled to the gyro with time constant `rate_tau`.
      rover: forward specific force from throttle (drive force - rolling - drag) / m and yaw rate from the kinematic
        bicycle model u tan(steer) / wheelbase (other IMU channels unused).
    The IMU residuals have a slow baseline removed (EMA, `baseline_tau`) that absorbs the per-episode mass / thrust
    / wind errors of the nominal model, and are fed only while airborne (drone) after `warmup_s`.
Each channel c runs a CUSUM on its residual normalised by `scale[c]`: S = min(cap h, max(0, S + |r| / scale - k)),
score = S / h[c]; the alarm is raised when any used channel's score exceeds 1. `calibrate` sets scale (a quantile of
attack-free |r|, so k = 1 is "above the usual noise") and h (from the per-mission maxima of S on attack-free
missions, for a target per-mission false-positive rate).

Diagnosis (DeLorean-style attribution over the causal graph IMU -> EKF prediction -> every aiding innovation): the
per-sensor evidence is the peak score of the sensor's channels during the first `diag_window_s` after the alarm.
IMU-model channels can only be explained by the IMU, so an IMU alarm is blamed on the gyro/accel first; otherwise the
aiding sensor with the largest evidence is blamed, where a purely vertical GPS/baro disagreement (GPS horizontal
channels quiet) is attributed to the baro and a GPS attack that moves the horizontal channels explains the baro's.

Recovery switch: the alarm clears (control handed back) once every score stays below `clear_frac` for `hold_s`.

Everything is per vehicle, pure and jittable; vmap over vehicles.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import ekf as ekf_lib
from specguard_jax.attacks import attacks as attacks_lib
from specguard_jax.math3d import quat_to_rot
from specguard_jax.types import SENSOR_NAMES, SensorReadings

CHANNELS = ekf_lib.CHANNELS + ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
N_CHANNELS = len(CHANNELS)
N_SENSORS = len(SENSOR_NAMES)
_S = {n: i for i, n in enumerate(SENSOR_NAMES)}
# Sensor (index into SENSOR_NAMES) whose attack a channel measures directly; -1: none (odometry is not attackable).
CHANNEL_SENSOR = (0, 0, 0, 0, 0, 0, _S["baro"], _S["mag"], _S["flow"], _S["flow"], -1,
                  _S["accel"], _S["accel"], _S["accel"], _S["gyro"], _S["gyro"], _S["gyro"])
_GPS_H = np.array([1, 1, 0, 1, 1, 1] + [0] * 11, np.float32)   # GPS horizontal position + velocity channels
_GPS_Z = 2
_IMU0 = len(ekf_lib.CHANNELS)
_GROUND_Z_DRONE = 0.12
_ASSETS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "assets")


def _ekf_gates(e: ekf_lib.EKFConfig):
  return ((e.gps_pos_gate,) * 3 + (e.gps_vel_gate,) * 3 + (e.baro_gate, e.mag_gate) + (e.flow_gate,) * 2
          + (e.odom_gate,))


@dataclasses.dataclass(frozen=True)
class DetectorConfig:
  """Static detector configuration (hashable). Units SI; tuples are per channel (CHANNELS order) unless noted.

  vehicle: 'drone' | 'rover'.  used: 0/1 per channel.  gates: EKF gate (sigma) of each EKF channel [11].
  scale: residual normalisation (channel units: sigma for EKF channels, m/s^2 accel, rad/s gyro).
  h: CUSUM threshold in normalised units.  k: CUSUM drift (normalised).  cap: S is clipped at cap * h.
  clear_frac, hold_s: recovery switch (scores below clear_frac for hold_s s -> alarm clears).
  diag_window_s: evidence for the diagnosis is collected for this long after the alarm is raised.
  Vehicle model: mass (kg), inertia [3] (kg m^2), rotor_xy [n][2] (m), yaw_coef [n] (m) (drone); drag_lin (N s/m),
  drag_quad (N s^2/m^2); wheelbase (m), drive_force (N), rolling (N s/m) (rover).
  min_height: drone IMU channels need the EKF height above the ground by this much (m).  ground_z: body origin
  height when standing (m).  warmup_s: airborne time before IMU channels are fed (s).  baseline_tau, warmup_tau:
  time constants (s) of the IMU residual baseline in flight / during warm-up.  rate_tau: gyro observer leak (s).
  Calibration: k_quantile (scale = this quantile of attack-free |r|), h_margin, h_min.
  """
  vehicle: str = "drone"
  used: tuple = (1.0,) * 10 + (0.0,) * 3 + (1.0,) * 4   # drone: no odometry; accel x/y (drag model) off
  gates: tuple = _ekf_gates(ekf_lib.EKFConfig.drone())
  scale: tuple = (1.0,) * 11 + (0.5,) * 3 + (0.05,) * 3
  h: tuple = (20.0,) * N_CHANNELS
  k: float = 1.0
  cap: float = 2.0
  clear_frac: float = 0.3
  hold_s: float = 3.0
  diag_window_s: float = 1.0
  mass: float = 1.5
  inertia: tuple = (0.029125, 0.029125, 0.055225)
  rotor_xy: tuple = ()
  yaw_coef: tuple = ()
  drag_lin: float = 0.10
  drag_quad: float = 0.025
  wheelbase: float = 0.55
  drive_force: float = 70.0
  rolling: float = 3.0
  min_height: float = 1.0
  ground_z: float = _GROUND_Z_DRONE
  warmup_s: float = 3.0
  baseline_tau: float = 2.0
  warmup_tau: float = 0.5
  rate_tau: float = 0.5
  k_quantile: float = 0.999
  h_margin: float = 3.0
  h_min: float = 8.0

  @classmethod
  def drone(cls, **overrides) -> "DetectorConfig":
    """Quadrotor (assets/drone.xml): rotor geometry read from the MJCF; all channels but odometry and accel x/y
    (the drag-model residual had heavy-tailed false alarms in turns; accel_z from the rotor thrusts is kept)."""
    import mujoco  # noqa: PLC0415
    from specguard_jax.autopilot import px4  # noqa: PLC0415
    af = px4.Airframe.from_mjcf(mujoco.MjModel.from_xml_path(os.path.join(_ASSETS, "drone.xml")))
    kw = dict(vehicle="drone", mass=float(af.mass), rotor_xy=tuple(tuple(float(v) for v in r) for r in af.rotor_xy),
              yaw_coef=tuple(float(v) for v in af.yaw_coef))
    kw.update(overrides)
    return cls(**kw)

  @classmethod
  def rover(cls, **overrides) -> "DetectorConfig":
    """Ground rover: GPS, baro, mag, odometry; IMU channels accel_x (throttle model) and gyro_z (bicycle model)."""
    used = [1.0] * 8 + [0.0, 0.0, 1.0] + [1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    kw = dict(vehicle="rover", used=tuple(used), gates=_ekf_gates(ekf_lib.EKFConfig.rover()), mass=10.0,
              inertia=(0.12, 0.35, 0.40), drag_lin=0.0, drag_quad=0.2, ground_z=0.2, min_height=-1.0,
              scale=(1.0,) * 11 + (0.5,) * 3 + (0.1,) * 3)
    kw.update(overrides)
    return cls(**kw)


@struct.dataclass
class DetectorState:
  """Per-vehicle detector state.

  cusum: [C] CUSUM statistic (normalised units).  scores: [C] cusum / h (alarm when any > 1).
  residual: [C] last normalised |residual| (held on channels without a fresh sample).
  peak: [C] max score during the diagnosis window of the current alarm.
  alarm: [] bool.  diagnosis: [] int32 index into SENSOR_NAMES (-1: none).  mask: [6] 0/1 diagnosed sensors.
  time_since_alarm: [] s since the current alarm was raised (0 without alarm).  quiet_time: [] s all scores have
  been below clear_frac.  n_alarms: [] int32 alarms raised so far.  time: [] s since init.
  Model state: baseline [6] (IMU residual baseline), rate_model [3] (gyro observer, rad/s), airborne_time [] s.
  """
  cusum: jnp.ndarray
  scores: jnp.ndarray
  residual: jnp.ndarray
  peak: jnp.ndarray
  alarm: jnp.ndarray
  diagnosis: jnp.ndarray
  mask: jnp.ndarray
  time_since_alarm: jnp.ndarray
  quiet_time: jnp.ndarray
  n_alarms: jnp.ndarray
  time: jnp.ndarray
  baseline: jnp.ndarray
  rate_model: jnp.ndarray
  airborne_time: jnp.ndarray


def detector_init(cfg: DetectorConfig) -> DetectorState:
  z = jnp.zeros((), jnp.float32)
  zc = jnp.zeros((N_CHANNELS,), jnp.float32)
  return DetectorState(cusum=zc, scores=zc, residual=zc, peak=zc, alarm=jnp.zeros((), bool),
                       diagnosis=jnp.full((), -1, jnp.int32), mask=jnp.zeros((N_SENSORS,), jnp.float32),
                       time_since_alarm=z, quiet_time=z, n_alarms=jnp.zeros((), jnp.int32), time=z,
                       baseline=jnp.zeros(6), rate_model=jnp.zeros(3), airborne_time=z)


# ----------------------------------------------------------------------------------------------------------------------
# residuals


def _imu_prediction(cfg: DetectorConfig, state: DetectorState, readings: SensorReadings, ekf, actuation, dt):
  """Model-predicted (specific force [3] m/s^2, body rate [3] rad/s), IMU channel mask [6], airborne [] bool."""
  r = quat_to_rot(ekf.quat)
  vb = r.T @ ekf.vel
  gyro = readings.gyro
  if cfg.vehicle == "drone":
    t = jnp.asarray(actuation, jnp.float32)
    xy = np.asarray(cfg.rotor_xy, np.float32)
    tau = jnp.stack([jnp.sum(xy[:, 1] * t), -jnp.sum(xy[:, 0] * t), jnp.sum(np.asarray(cfg.yaw_coef) * t)])
    inertia = jnp.asarray(cfg.inertia, jnp.float32)
    w = state.rate_model
    w_dot = (tau - jnp.cross(w, inertia * w)) / inertia
    rate_pred = w + w_dot * dt
    drag = -(cfg.drag_lin * vb + cfg.drag_quad * jnp.linalg.norm(vb) * vb)
    f_pred = (jnp.array([0.0, 0.0, 1.0]) * jnp.sum(t) + drag) / cfg.mass
    airborne = ekf.pos[2] > cfg.ground_z + cfg.min_height
    ch = jnp.ones(6, bool)
  else:
    steer, throttle = actuation[0], actuation[1]
    u = vb[0]
    fx = (throttle * cfg.drive_force - cfg.rolling * u - cfg.drag_quad * u * jnp.abs(u)) / cfg.mass
    f_pred = jnp.stack([fx, readings.accel[1], readings.accel[2]])
    rate_pred = jnp.stack([gyro[0], gyro[1], u * jnp.tan(steer) / cfg.wheelbase])
    airborne = jnp.ones((), bool)
    ch = jnp.array([True, False, False, False, False, True])
  return f_pred, rate_pred, ch, airborne


def residuals(cfg: DetectorConfig, state: DetectorState, readings: SensorReadings, ekf, actuation, dt):
  """Raw residual magnitudes of one tick.

  readings: the (possibly attacked) SensorReadings the EKF fused this tick; ekf: the EKFState after this tick's
  `ekf_step`; actuation: what drove the physics step that produced these readings (drone: rotor thrusts [n] N,
  i.e. sim['vehicle']['rotors'] before this tick's vehicle step; rover: [steer rad, throttle]); dt: tick (s).
  Returns (|r| [C] in channel units, fresh [C] bool: channel has a new sample to feed, new model state).
  """
  gates = jnp.asarray(cfg.gates, jnp.float32)
  r_ekf = jnp.sqrt(jnp.clip(ekf.test_ratio, 0.0, 1e6)) * gates
  fresh_ekf = ekf.fresh > 0.5
  f_pred, rate_pred, ch, airborne = _imu_prediction(cfg, state, readings, ekf, actuation, dt)
  e = jnp.concatenate([readings.accel - f_pred, readings.gyro - rate_pred])
  e = jnp.where(jnp.isfinite(e), e, 0.0)
  airborne_time = jnp.where(airborne, state.airborne_time + dt, 0.0)
  warm = airborne_time >= cfg.warmup_s
  out = jnp.abs(e - state.baseline)
  tau = jnp.where(warm, cfg.baseline_tau, cfg.warmup_tau)
  baseline = jnp.where(airborne, state.baseline + (e - state.baseline) * jnp.minimum(1.0, dt / tau), e)
  rate_model = rate_pred + (readings.gyro - rate_pred) * min(1.0, dt / cfg.rate_tau)
  rate_model = jnp.where(airborne & jnp.all(jnp.isfinite(rate_model)), rate_model, readings.gyro)
  fresh = jnp.concatenate([fresh_ekf, ch & warm])
  new = state.replace(baseline=baseline, rate_model=rate_model, airborne_time=airborne_time)
  return jnp.concatenate([r_ekf, out]), fresh, new


def cusum_step(cfg: DetectorConfig, s, r, fresh):
  """S = min(cap h, max(0, S + |r| / scale - k)) on fresh channels; [C] each. Returns (S, normalised |r|)."""
  scale = jnp.asarray(cfg.scale, jnp.float32)
  h = jnp.asarray(cfg.h, jnp.float32)
  z = r / scale
  s_new = jnp.minimum(cfg.cap * h, jnp.maximum(0.0, s + z - cfg.k))
  return jnp.where(fresh, s_new, s), z


# ----------------------------------------------------------------------------------------------------------------------
# diagnosis and switch


def diagnose(cfg: DetectorConfig, peak):
  """Sensor index (int32 []) blamed for per-channel evidence `peak` [C] (scores); see module docstring."""
  used = jnp.asarray(cfg.used, jnp.float32)
  p = peak * used
  sensor = np.asarray(CHANNEL_SENSOR)
  onehot = np.stack([(sensor == i) for i in range(N_SENSORS)]).astype(np.float32)   # [6, C]
  ev = jnp.max(onehot * p[None, :], axis=-1)                                        # [6]
  gps_h = jnp.max(p * _GPS_H)
  # A purely vertical GPS/baro disagreement is the baro's; GPS horizontal evidence explains the baro's.
  vertical_only = gps_h < 1.0
  ev = ev.at[_S["baro"]].set(jnp.where(vertical_only, jnp.maximum(ev[_S["baro"]], p[_GPS_Z]),
                                       jnp.where(ev[_S["gps"]] >= ev[_S["baro"]], 0.0, ev[_S["baro"]])))
  ev = ev.at[_S["gps"]].set(jnp.where(vertical_only, gps_h, ev[_S["gps"]]))
  imu = jnp.array([_S["gyro"], _S["accel"]])
  imu_ev = ev[imu]
  imu_alarm = jnp.max(imu_ev) > 1.0
  return jnp.where(imu_alarm, imu[jnp.argmax(imu_ev)], jnp.argmax(ev)).astype(jnp.int32)


def _switch(cfg: DetectorConfig, state: DetectorState, scores, raised, dt):
  """Alarm latch + diagnosis window + recovery hold. Returns the updated alarm-related fields."""
  start = raised & ~state.alarm
  quiet = jnp.all(scores < cfg.clear_frac)
  quiet_time = jnp.where(state.alarm & quiet, state.quiet_time + dt, 0.0)
  clear = state.alarm & (quiet_time >= cfg.hold_s)
  alarm = (state.alarm | start) & ~clear
  tsa = jnp.where(start, 0.0, jnp.where(alarm, state.time_since_alarm + dt, 0.0))
  in_window = alarm & (tsa <= cfg.diag_window_s)
  peak = jnp.where(start, scores, jnp.where(in_window, jnp.maximum(state.peak, scores),
                                            jnp.where(alarm, state.peak, 0.0)))
  diag = jnp.where(alarm, diagnose(cfg, peak), -1).astype(jnp.int32)
  mask = jnp.where(alarm, jax.nn.one_hot(jnp.maximum(diag, 0), N_SENSORS), 0.0)
  return dict(alarm=alarm, peak=peak, diagnosis=diag, mask=mask, time_since_alarm=tsa,
              quiet_time=jnp.where(clear, 0.0, quiet_time), n_alarms=state.n_alarms + start.astype(jnp.int32))


def detector_update(cfg: DetectorConfig, state: DetectorState, readings: SensorReadings, ekf_state, actuation,
                    dt) -> DetectorState:
  """One tick of the residual detector (see `residuals` for the arguments). Returns the new DetectorState."""
  r, fresh, state = residuals(cfg, state, readings, ekf_state, actuation, dt)
  used = jnp.asarray(cfg.used) > 0
  fresh = fresh & used
  s, z = cusum_step(cfg, state.cusum, r, fresh)
  scores = s / jnp.asarray(cfg.h, jnp.float32) * used
  raised = jnp.any(scores > 1.0)
  sw = _switch(cfg, state, scores, raised, dt)
  return state.replace(cusum=s, scores=scores, residual=jnp.where(fresh, z, state.residual), time=state.time + dt,
                       **sw)


def oracle_update(state: DetectorState, attack: attacks_lib.AttackSchedule, t, dt, delay: float = 0.0,
                  hold_s: float = 0.0) -> DetectorState:
  """Oracle detector for training: alarm = attack active at t - delay (s); diagnosis = the true target (first
  attacked sensor; `mask` = the full true mask). hold_s > 0 keeps the alarm that long after the delayed attack
  ends (a recovery hold like the residual detector's)."""
  on = attacks_lib.attack_active(attack, t - delay)
  if hold_s > 0:
    on = on | ((t - delay >= attack.onset + attack.duration) & (t - delay < attack.onset + attack.duration + hold_s)
               & (jnp.sum(attack.mask) > 0))
  start = on & ~state.alarm
  diag = jnp.where(on, jnp.argmax(attack.mask), -1).astype(jnp.int32)
  tsa = jnp.where(start, 0.0, jnp.where(on, state.time_since_alarm + dt, 0.0))
  return state.replace(alarm=on, diagnosis=diag, mask=jnp.where(on, attack.mask, 0.0).astype(jnp.float32),
                       time_since_alarm=tsa, n_alarms=state.n_alarms + start.astype(jnp.int32),
                       time=state.time + dt)


# ----------------------------------------------------------------------------------------------------------------------
# calibration


@jax.jit
def _calibration_stats(r, fresh, k_quantile, fpr_q):
  """r, fresh: [M, T, C] raw |residual| and feed mask of attack-free missions. Returns (scale [C], h_raw [C],
  max_s [M, C], n_fresh [C])."""
  n_fresh = jnp.sum(fresh, axis=(0, 1))
  flat = jnp.where(fresh, r, jnp.nan).reshape(-1, r.shape[-1])
  scale = jnp.nanquantile(flat, k_quantile, axis=0)
  scale = jnp.where(jnp.isfinite(scale), jnp.maximum(scale, 1e-4), 1.0)

  def one(rm, fm):
    def body(s, x):
      ri, fi = x
      s = jnp.where(fi, jnp.maximum(0.0, s + ri / scale - 1.0), s)
      return s, s
    _, ss = jax.lax.scan(body, jnp.zeros(r.shape[-1]), (rm, fm))
    return jnp.max(ss, axis=0)

  max_s = jax.vmap(one)(r, fresh)
  h_raw = jnp.quantile(max_s, fpr_q, axis=0, method="higher")
  return scale, h_raw, max_s, n_fresh


def calibrate(cfg: DetectorConfig, residual_traces, fresh, target_fpr: float = 0.05) -> DetectorConfig:
  """Calibrate `scale` and `h` on attack-free missions (drift k fixed at 1 normalised unit).

  residual_traces: [M, T, C] raw |r| (from `residuals`, e.g. specguard_jax.detection.traces.residual_trace);
  fresh: [M, T, C] bool, the samples a channel was fed (mask out ticks after a mission ended).
  scale[c] = the k_quantile of |r_c|; h[c] = max(h_min, h_margin * the (1 - target_fpr / n_used) quantile of the
  per-mission maximum of S_c): with independent channels, a mission raises a false alarm with probability
  <= target_fpr (per mission). Channels never fed are switched off (`used` = 0).
  """
  used = np.asarray(cfg.used, np.float32)
  n_used = max(1.0, float(used.sum()))
  q = float(np.clip(1.0 - target_fpr / n_used, 0.0, 1.0))
  scale, h_raw, _, n_fresh = jax.device_get(_calibration_stats(jnp.asarray(residual_traces, jnp.float32),
                                                               jnp.asarray(fresh, bool), cfg.k_quantile, q))
  used = used * (np.asarray(n_fresh) > 0)
  h = np.maximum(cfg.h_min, cfg.h_margin * np.asarray(h_raw))
  return dataclasses.replace(cfg, scale=tuple(float(x) for x in scale), h=tuple(float(x) for x in h),
                             used=tuple(float(x) for x in used), k=1.0)
