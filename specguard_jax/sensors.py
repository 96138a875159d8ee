"""Sensor models: truth (`TrueState`) -> noisy, rate-limited `SensorReadings`, once per autopilot tick.

Models (per vehicle; all draws from the `rng` argument, everything jittable and vmappable). Every parameter is a
`SensorConfig` field, with its source beside it; "per episode" errors are drawn once by `init_sensors`.
  * GPS (10 Hz): position = truth + a first-order Gauss-Markov error (correlated random walk: σ ~2 m per horizontal
    axis, τ 60 s, a u-blox M8/M9-class receiver) + white noise; velocity = truth + white noise.
  * gyroscope (every tick): body rate + bias + white noise; the bias random-walks.
  * accelerometer (every tick): body specific force R^T (acc - g), g = (0, 0, -9.81), + bias + white noise; the bias
    random-walks.
  * magnetometer (50 Hz): delivered as a heading `mag_yaw` (wrapped to (-pi, pi]) computed from the horizontal field
    in the body frame, in units of the Earth field's horizontal strength H: the Earth field (unit, along the yaw
    reference) plus a local disturbance near structures (a world-fixed 2-D vector per episode, falling off as a dipole,
    (d_ref / d)^3, with the distance d to the nearest obstacle), rotated into the body frame, then distorted by the
    per-episode soft-iron matrix (I + E, E symmetric) and hard-iron offset (2-D), + white heading noise. The heading
    error is therefore a function of the heading (one cycle per turn from hard iron, two from soft iron) and of the
    distance to structures.
  * barometer (25 Hz): altitude above the ground plane + white noise + a slowly random-walking drift.
  * optical flow (25 Hz, drone only): (1 + per-episode scale-factor error per axis) (v_body_x, v_body_y) / height
    above ground (flat terrain at z = 0) + white noise; flow[0] pairs with forward, flow[1] with leftward body velocity
    (rad/s, already gyro-compensated). A sample is invalid (zeros, flow_fresh = 0) outside the valid height range
    [flow_min_height, flow_max_height] and during a quality dropout: a two-state Markov chain per sample whose
    stationary dropout rate is set by the ground's texture (`SURFACES`, a world property the env passes to
    `init_sensors`) and whose consecutive samples are correlated (`flow_dropout_tau`).
  * wheel odometry (25 Hz, rover only): forward body speed x (1 + per-episode scale error) x (1 + slip) + white noise;
    the slip ratio grows with the lateral acceleration's share of the tyre friction, slip = κ_peak |a_lat| / (μ g).
  * IMU samples saturate at the sensor range (accel ±16 g, gyro ±2000 deg/s) like real parts.
A sensor with rate r is fresh on ticks k with k % round(tick_rate / r) == 0 (tick 0 is fresh for all); between fresh
ticks it holds its last sample. `check_rates(cfg, dt)` raises if a rate does not divide the tick rate.
Noise σ are per sample; random walks are given as densities (unit/sqrt(s)) and discretised with the tick dt.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from specguard_jax.math3d import matvec_t, quat_to_euler, quat_to_rot, wrap_angle
from specguard_jax.types import SensorReadings, TrueState

GRAVITY = 9.81  # m/s^2; world gravity vector is (0, 0, -GRAVITY)
ACCEL_RANGE = 16.0 * GRAVITY  # m/s^2, IMU saturation
GYRO_RANGE = math.radians(2000.0)  # rad/s, IMU saturation
SURFACES = ("grass", "gravel", "asphalt", "concrete", "indoor_floor", "sand", "snow", "water")
"""Ground textures (index = `envs.worlds.World.surface`), ordered from rich to poor texture for an optical-flow
sensor; `SensorConfig.flow_dropout` gives each its dropout rate."""


@dataclasses.dataclass(frozen=True)
class SensorConfig:
  """Rates (Hz) and noise of the sensor suite. σ are per-sample standard deviations (per-episode errors: σ of the
  value drawn at `init_sensors`)."""

  # GPS: u-blox NEO-M8N (datasheet UBX-15031086: 2.5 m CEP horizontal, GPS+GLONASS; NEO-M9N: 2.0 m CEP). For a
  # circular Gaussian CEP = 1.1774 σ, so 2.5 m CEP is σ ~2.1 m per horizontal axis, almost all of it slowly correlated
  # (ionosphere, troposphere, orbit and clock, multipath): 2.0 m Gauss-Markov + 0.5 m white gives 2.43 m CEP. Vertical:
  # not in the datasheet; ~1.5x horizontal, the usual ratio for single-frequency GNSS (GPS SPS Performance Standard).
  # τ 60 s: the autocorrelation of consumer-receiver horizontal errors bends at ~1 min (D. L. Wilson, "Correlation of
  # errors", Garmin 12XL 20-day test) and the PX4 SITL GPS plugin's gps_corellation_time is 60 s; single-frequency
  # errors are Ornstein-Uhlenbeck-like (Kalyanasundaram et al., Sensors 20(21) 6050, 2020).
  gps_rate: float = 10.0
  gps_pos_sigma_h: float = 0.5  # m, white, per horizontal axis
  gps_pos_sigma_v: float = 0.8  # m, white, vertical
  gps_drift_sigma_h: float = 2.0  # m, stationary σ of the Gauss-Markov error, per horizontal axis
  gps_drift_sigma_v: float = 3.0  # m, same, vertical
  gps_drift_tau: float = 60.0  # s, correlation time of the Gauss-Markov error
  gps_vel_sigma_h: float = 0.15  # m/s
  gps_vel_sigma_v: float = 0.2  # m/s
  # gyroscope (sampled every tick)
  gyro_sigma: float = 0.005  # rad/s
  gyro_bias_init: float = 0.003  # rad/s, σ of the turn-on bias per axis
  gyro_bias_walk: float = 1e-4  # rad/s/sqrt(s)
  # accelerometer (sampled every tick)
  accel_sigma: float = 0.08  # m/s^2
  accel_bias_init: float = 0.05  # m/s^2, σ of the turn-on bias per axis
  accel_bias_walk: float = 1e-3  # m/s^2/sqrt(s)
  # magnetometer heading. Error model (hard iron b, soft iron I + E on the horizontal field in units of the Earth
  # field's horizontal strength H): Vasconcelos et al., "Geometric approach to strapdown magnetometer calibration in
  # sensor frame", IEEE TAES 47(2), 2011; Kok & Schön, "Magnetometer calibration using inertial sensors", IEEE Sensors
  # J. 16(14), 2016. Uncalibrated, on-board hard iron is of the order of H itself, tens of degrees of heading error; no
  # autopilot flies that: PX4 refuses to arm without a compass calibration and EKF2 learns the body field in flight,
  # ArduPilot fits offsets, diagonals and off-diagonals (COMPASS_OFS*, COMPASS_DIA*, COMPASS_ODI*) before flight and
  # can learn offsets in flight. So b and E are the RESIDUALS after that calibration, sized by the heading accuracy
  # quoted for a hard- and soft-iron compensated strapdown compass, about 1 deg RMS (Caruso, "Applications of magnetic
  # sensors for low cost compass systems", IEEE PLANS 2000; Gebre-Egziabher et al., "Calibration of strapdown
  # magnetometers in magnetic field domain", J. Aerosp. Eng. 19(2), 2006). It is also what ArduPilot's fit accepts:
  # RMS residual <= 16 mGauss (COMPASS_CAL_FIT default) over >= 300 samples (CompassCalibrator), so an offset's
  # standard error is ~16 sqrt(3 / 300) = 1.6 mGauss, ~0.01 H for H ~ 0.2 Gauss at mid latitudes (WMM). The heading
  # error of small b and E is b_perp + E12 cos 2psi + (E22 - E11) / 2 sin 2psi (psi the heading): RMS over headings and
  # episodes sqrt(σ_b^2 + 0.75 σ_E^2), 0.0173 rad (0.99 deg) with the σ below; hard iron takes the larger share (offsets
  # drift with temperature and in-flight currents, the fitted scale factors do not). The EKF has no magnetometer-bias
  # state (ekf.py: the heading is fused like EKF2's yaw fusion): these residuals reach its heading unestimated.
  mag_rate: float = 50.0
  mag_sigma: float = 0.03  # rad, white heading noise
  mag_hard_iron_sigma: float = 0.015  # H, σ per horizontal axis of the residual hard-iron offset (per episode)
  mag_soft_iron_sigma: float = 0.01  # σ of each entry of the symmetric residual soft-iron error E (per episode)
  # Local disturbance near structures (steel frames, rebar, poles, vehicles): a dipole's field falls off as 1/d^3.
  # Ferrous structures perturb the field by tens of µT within ~1 m (Afzal, Renaudin & Lachapelle, "Magnetic field
  # based heading estimation for pedestrian navigation environments", IPIN 2011), i.e. of the order of H (~20 µT at
  # mid latitudes, WMM): σ of the per-episode 2-D disturbance at mag_dist_ref, in H; d is floored at mag_dist_min.
  mag_dist_sigma: float = 1.0  # H at mag_dist_ref, σ per horizontal axis (per episode)
  mag_dist_ref: float = 1.0  # m
  mag_dist_min: float = 0.5  # m (the vehicle's size: closer, the structure is hit)
  # barometer
  baro_rate: float = 25.0
  baro_sigma: float = 0.3  # m
  baro_drift_walk: float = 0.01  # m/sqrt(s)
  # optical flow: a PMW3901 / PAA3905-class flow sensor with a time-of-flight range finder (ARK Flow: PAA3905 +
  # Broadcom AFBR-S50LV85D, typical range up to 30 m). Valid heights: from 0.3 m (the PX4FLOW driver's
  # PX4FLOW_MIN_DISTANCE; the flow sensors focus from 80 mm, PixArt PMW3901MB datasheet / PX4 SENS_FLOW_MINHGT 0.08 m,
  # but the range finder and the EKF (EKFConfig.flow_min_height) and detector use 0.3 m) to the range finder's reach
  # (PX4 SENS_FLOW_MAXHGT: above it the estimator cannot scale the flow).
  has_flow: bool = True
  flow_rate: float = 25.0
  flow_sigma: float = 0.05  # rad/s
  flow_min_height: float = 0.3  # m
  flow_max_height: float = 30.0  # m
  # Scale-factor error per axis (lens focal length, mounting, range-finder scale): ArduPilot exposes FLOW_FXSCALER /
  # FLOW_FYSCALER with a ±200 ‰ range to correct it; σ 5 % is an assumed residual of a typical setup.
  flow_scale_sigma: float = 0.05  # fraction, per axis (per episode)
  # Quality dropouts (the sensor's SQUAL / PX4 EKF2_OF_QMIN rejects the sample) over low-texture ground: rate per
  # sample for each of SURFACES. Flow sensors need surface texture and fail over water, snow and uniform floors
  # (PX4 optical-flow guide; ArduPilot optical-flow wiki; Honegger et al., ICRA 2013, PX4FLOW over indoor / outdoor
  # surfaces): the rates are assumed, ordered by texture, not measured figures.
  flow_dropout: tuple = (("grass", 0.02), ("gravel", 0.02), ("asphalt", 0.10), ("concrete", 0.15),
                         ("indoor_floor", 0.30), ("sand", 0.20), ("snow", 0.60), ("water", 0.90))
  flow_dropout_tau: float = 0.2  # s, correlation time of the dropout state (ground patches ~1-2 m at 5-10 m/s)
  # wheel odometry: per-episode scale error from the effective wheel radius (load, pressure, wear: Borenstein & Feng,
  # "Measurement and correction of systematic odometry errors in mobile robots", IEEE T-RA 12(6), 1996, unequal and
  # uncertain wheel diameters of ~1 %); slip ratio κ_peak |a_lat| / (μ g): a tyre's longitudinal slip at its friction
  # peak is ~0.1 on dry asphalt (Pacejka, "Tire and Vehicle Dynamics", 3rd ed. 2012), reached when the lateral
  # acceleration uses all of the friction μ g (friction circle); the wheel then turns faster than the ground moves.
  has_odom: bool = False
  odom_rate: float = 25.0
  odom_sigma: float = 0.05  # m/s
  odom_scale_sigma: float = 0.01  # fraction (per episode)
  odom_slip_peak: float = 0.10  # slip ratio at full friction use
  odom_slip_mu: float = 0.9  # tyre-road friction coefficient (dry asphalt)

  @classmethod
  def drone(cls, **overrides) -> "SensorConfig":
    """Multicopter (PX4-class): GPS, IMU, mag, baro, optical flow."""
    return cls(**overrides)

  @classmethod
  def rover(cls, **overrides) -> "SensorConfig":
    """Ground rover (ArduRover-class): GPS, IMU, mag, baro, wheel odometry; no optical flow."""
    kw = dict(has_flow=False, has_odom=True)
    kw.update(overrides)
    return cls(**kw)

  def noiseless(self) -> "SensorConfig":
    """Same rates and valid ranges, every noise, bias, drift and per-episode error set to zero, no flow dropouts and
    no odometry slip (for tests and debugging)."""
    zero = {f.name: 0.0 for f in dataclasses.fields(self)
            if f.name.endswith(("_sigma", "_sigma_h", "_sigma_v", "_init", "_walk"))}
    zero.update(flow_dropout=tuple((name, 0.0) for name, _ in self.flow_dropout), odom_slip_peak=0.0)
    return dataclasses.replace(self, **zero)

  def flow_dropout_rate(self, surface) -> jax.Array:
    """[] dropout rate of a flow sample over `surface` (int index into SURFACES, may be traced)."""
    table = dict(self.flow_dropout)
    return jnp.asarray([table[name] for name in SURFACES], jnp.float32)[surface]


@struct.dataclass
class SensorState:
  """Per-vehicle sensor memory.

  tick: [] int32 ticks since init.  gyro_bias, accel_bias: [3] current IMU biases (rad/s, m/s^2).
  gps_drift: [3] current correlated GPS position error (m).  baro_drift: [] barometer drift (m).
  Per-episode errors (drawn by init_sensors): flow_scale [2] scale-factor error per flow axis (fraction);
  flow_dropout [] dropout rate per flow sample over this episode's ground; mag_hard [2] hard-iron offset and
  mag_soft [2, 2] soft-iron matrix (I + E) on the body-frame horizontal field (units of H); mag_dist [2] world-frame
  disturbance at mag_dist_ref from the nearest structure (H); odom_scale [] wheel-odometry scale error (fraction).
  flow_bad: [] bool, the flow sensor is in a quality dropout (Markov state, updated on flow samples).
  held: SensorReadings, the last delivered readings (stale sensors repeat them).
  """

  tick: jnp.ndarray
  gyro_bias: jnp.ndarray
  accel_bias: jnp.ndarray
  gps_drift: jnp.ndarray
  baro_drift: jnp.ndarray
  flow_scale: jnp.ndarray
  flow_dropout: jnp.ndarray
  flow_bad: jnp.ndarray
  mag_hard: jnp.ndarray
  mag_soft: jnp.ndarray
  mag_dist: jnp.ndarray
  odom_scale: jnp.ndarray
  held: SensorReadings


def quat_yaw(q):
  """[4] -> [] yaw (rad) of a body->world quaternion (ZYX Euler yaw)."""
  return quat_to_euler(q)[2]


def mag_heading(yaw, hard, soft, dist_w):
  """Heading (rad, unwrapped offset from atan2) the magnetometer reports at true yaw (rad): the horizontal field
  e_w + dist_w ([2], units of H, e_w = (1, 0) along the yaw reference) in the body frame, through the soft-iron
  matrix soft [2, 2] plus the hard-iron offset hard [2]. Identity soft, zero hard and dist_w: returns yaw (wrapped)."""
  c, s = jnp.cos(yaw), jnp.sin(yaw)
  fx, fy = 1.0 + dist_w[0], dist_w[1]
  f_b = jnp.stack([c * fx + s * fy, -s * fx + c * fy])   # R_z(yaw)^T f_w
  f_m = soft @ f_b + hard
  return jnp.arctan2(-f_m[1], f_m[0])


def mag_disturbance(cfg: "SensorConfig", mag_dist, obstacle_distance):
  """[2] world-frame disturbance field (H) at `obstacle_distance` (m) from the nearest structure: dipole falloff."""
  d = jnp.maximum(obstacle_distance, cfg.mag_dist_min)
  return mag_dist * (cfg.mag_dist_ref / d) ** 3


# ----------------------------------------------------------------------------------------------------------------------


def _periods(cfg: SensorConfig, dt):
  """Ticks between samples of each slow sensor (int32, >= 1); dt may be traced."""
  tick_rate = 1.0 / dt
  per = lambda rate: jnp.maximum(jnp.round(tick_rate / rate), 1.0).astype(jnp.int32)
  return dict(gps=per(cfg.gps_rate), mag=per(cfg.mag_rate), baro=per(cfg.baro_rate),
              flow=per(cfg.flow_rate), odom=per(cfg.odom_rate))


def check_rates(cfg: SensorConfig, dt: float) -> None:
  """Raises ValueError unless every sensor rate divides the tick rate 1/dt (call with a concrete dt)."""
  tick_rate = 1.0 / float(dt)
  for name in ("gps_rate", "mag_rate", "baro_rate", "flow_rate", "odom_rate"):
    rate = getattr(cfg, name)
    n = tick_rate / rate
    if rate <= 0 or rate > tick_rate + 1e-9 or abs(n - round(n)) > 1e-6:
      raise ValueError(f"{name}={rate} Hz does not divide the tick rate {tick_rate} Hz")


_N_MEAS_NOISE = 17  # standard-normal draws per _measure call
_N_EPISODE = 11     # standard-normal draws for the per-episode errors and the first dropout state


def _measure(cfg: SensorConfig, truth: TrueState, st: SensorState, obstacle_distance, n):
  """Fresh samples of every sensor (no rate logic) from the biases, drifts, per-episode errors and dropout state in
  `st` (its `held` is not read), the nearest obstacle's distance (m) and n [17] standard-normal draws.

  Returns a SensorReadings with all fresh flags 1 (flow: validity, odom: presence).
  """
  f32 = jnp.float32
  r = quat_to_rot(truth.quat)
  vel_b = matvec_t(r, truth.vel)
  sig_p = jnp.array([cfg.gps_pos_sigma_h, cfg.gps_pos_sigma_h, cfg.gps_pos_sigma_v], f32)
  sig_v = jnp.array([cfg.gps_vel_sigma_h, cfg.gps_vel_sigma_h, cfg.gps_vel_sigma_v], f32)
  gps_pos = truth.pos + st.gps_drift + sig_p * n[0:3]
  gps_vel = truth.vel + sig_v * n[3:6]
  gyro = truth.ang_vel + st.gyro_bias + cfg.gyro_sigma * n[6:9]
  g = jnp.array([0.0, 0.0, -GRAVITY], f32)
  accel = matvec_t(r, truth.acc - g) + st.accel_bias + cfg.accel_sigma * n[9:12]
  gyro = jnp.clip(gyro, -GYRO_RANGE, GYRO_RANGE)
  accel = jnp.clip(accel, -ACCEL_RANGE, ACCEL_RANGE)
  heading = mag_heading(quat_yaw(truth.quat), st.mag_hard, st.mag_soft,
                        mag_disturbance(cfg, st.mag_dist, obstacle_distance))
  mag_yaw = wrap_angle(heading + cfg.mag_sigma * n[12])
  height = truth.pos[2]
  baro_alt = height + st.baro_drift + cfg.baro_sigma * n[13]
  flow_valid = (height >= cfg.flow_min_height) & (height <= cfg.flow_max_height) & ~st.flow_bad & cfg.has_flow
  flow = (1.0 + st.flow_scale) * vel_b[:2] / jnp.maximum(height, cfg.flow_min_height) + cfg.flow_sigma * n[14:16]
  flow = jnp.where(flow_valid, flow, 0.0)
  a_lat = matvec_t(r, truth.acc)[1]   # body-frame lateral acceleration, m/s^2
  slip = cfg.odom_slip_peak * jnp.abs(a_lat) / (cfg.odom_slip_mu * GRAVITY)
  odom = jnp.where(cfg.has_odom, vel_b[0] * (1.0 + st.odom_scale) * (1.0 + slip) + cfg.odom_sigma * n[16], 0.0)
  one = jnp.ones((), f32)
  return SensorReadings(
    gps_pos=gps_pos, gps_vel=gps_vel, gps_fresh=one, gyro=gyro, accel=accel, mag_yaw=mag_yaw, mag_fresh=one,
    baro_alt=baro_alt, baro_fresh=one, flow=flow, flow_fresh=flow_valid.astype(f32),
    odom_speed=odom, odom_fresh=one * cfg.has_odom)


def init_sensors(cfg: SensorConfig, truth: TrueState, rng, surface=0, obstacle_distance=jnp.inf) -> SensorState:
  """Draws turn-on biases, an initial GPS error, the per-episode errors (flow scale, hard / soft iron, the structures'
  magnetic disturbance, odometry scale) and the first flow-dropout state; `held` gets a first sample of everything.
  surface: index into SURFACES of the ground under the mission (int, may be traced; sets the flow dropout rate).
  obstacle_distance: [] m from the vehicle to the nearest obstacle (magnetic disturbance). tick = 0."""
  f32 = jnp.float32
  n = jax.random.normal(rng, (9 + _N_EPISODE + _N_MEAS_NOISE,))  # one draw: cheap to compile
  e = n[9:9 + _N_EPISODE]
  sig_d = jnp.array([cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_v], f32)
  si = cfg.mag_soft_iron_sigma
  p_drop = cfg.flow_dropout_rate(surface)
  st = SensorState(
    tick=jnp.zeros((), jnp.int32), gyro_bias=cfg.gyro_bias_init * n[0:3], accel_bias=cfg.accel_bias_init * n[3:6],
    gps_drift=sig_d * n[6:9], baro_drift=jnp.zeros((), f32),
    flow_scale=cfg.flow_scale_sigma * e[0:2], flow_dropout=p_drop,
    flow_bad=jax.scipy.special.ndtr(e[10]) < p_drop,
    mag_hard=cfg.mag_hard_iron_sigma * e[2:4],
    mag_soft=jnp.eye(2, dtype=f32) + si * jnp.array([[e[4], e[6]], [e[6], e[5]]]),
    mag_dist=cfg.mag_dist_sigma * e[7:9], odom_scale=cfg.odom_scale_sigma * e[9], held=None)
  held = _measure(cfg, truth, st, obstacle_distance, n[9 + _N_EPISODE:])
  return st.replace(held=held)


def sense(cfg: SensorConfig, state: SensorState, truth: TrueState, rng, dt,
          obstacle_distance=jnp.inf) -> tuple[SensorState, SensorReadings]:
  """One autopilot tick: advance biases/drifts by dt (s), sample fresh sensors, hold stale ones.
  obstacle_distance: [] m from the vehicle to the nearest obstacle (the magnetometer's local disturbance).

  Returns (new state, readings). The first call after `init_sensors` (tick 0) has every sensor fresh.
  """
  n = jax.random.normal(rng, (11 + _N_MEAS_NOISE,))  # one draw: cheap to compile
  sqdt = jnp.sqrt(dt)
  per = _periods(cfg, dt)
  due = {name: (jnp.mod(state.tick, p) == 0) for name, p in per.items()}
  # first-order Gauss-Markov GPS error with stationary σ_d: x' = a x + σ_d sqrt(1 - a^2) n
  a = jnp.exp(-dt / cfg.gps_drift_tau)
  sig_d = jnp.array([cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_v], jnp.float32)
  # Flow dropouts: a two-state Markov chain per flow sample with stationary rate p and lag-1 correlation
  # ρ = exp(-T / flow_dropout_tau) (T the flow period): P(bad | bad) = p + ρ (1 - p), P(bad | good) = p (1 - ρ).
  p = state.flow_dropout
  rho = jnp.exp(-per["flow"] * dt / cfg.flow_dropout_tau)
  p_bad = jnp.where(state.flow_bad, p + rho * (1.0 - p), p * (1.0 - rho))
  flow_bad = jnp.where(due["flow"], jax.scipy.special.ndtr(n[10]) < p_bad, state.flow_bad)
  nxt = state.replace(
    gyro_bias=state.gyro_bias + cfg.gyro_bias_walk * sqdt * n[0:3],
    accel_bias=state.accel_bias + cfg.accel_bias_walk * sqdt * n[3:6],
    gps_drift=a * state.gps_drift + sig_d * jnp.sqrt(1.0 - a * a) * n[6:9],
    baro_drift=state.baro_drift + cfg.baro_drift_walk * sqdt * n[9], flow_bad=flow_bad)
  new = _measure(cfg, truth, nxt, obstacle_distance, n[11:])

  held = state.held
  f32 = jnp.float32

  def pick(fresh, a_new, a_old):
    return jnp.where(fresh, a_new, a_old)

  flow_fresh = due["flow"] & (new.flow_fresh > 0)
  readings = SensorReadings(
    gps_pos=pick(due["gps"], new.gps_pos, held.gps_pos),
    gps_vel=pick(due["gps"], new.gps_vel, held.gps_vel),
    gps_fresh=due["gps"].astype(f32),
    gyro=new.gyro,
    accel=new.accel,
    mag_yaw=pick(due["mag"], new.mag_yaw, held.mag_yaw),
    mag_fresh=due["mag"].astype(f32),
    baro_alt=pick(due["baro"], new.baro_alt, held.baro_alt),
    baro_fresh=due["baro"].astype(f32),
    # an invalid flow sample (out of the height range, or a dropout) reads zero even on a due tick
    flow=jnp.where(due["flow"], new.flow, held.flow),
    flow_fresh=flow_fresh.astype(f32),
    odom_speed=pick(due["odom"], new.odom_speed, held.odom_speed),
    odom_fresh=(due["odom"] & cfg.has_odom).astype(f32),
  )
  return nxt.replace(tick=state.tick + 1, held=readings), readings
