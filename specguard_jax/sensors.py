"""Sensor models: truth (`TrueState`) -> noisy, rate-limited `SensorReadings`, once per autopilot tick.

Models (per vehicle; all draws from the `rng` argument, everything jittable and vmappable):
  * GPS (10 Hz): position = truth + white noise (σ 0.5 m horizontal / 0.8 m vertical) + a first-order Gauss-Markov
    wander (slowly correlated error, τ ~ 60 s); velocity = truth + white noise (σ 0.15 / 0.2 m/s).
  * gyroscope (every tick): body rate + bias + white noise; the bias random-walks.
  * accelerometer (every tick): body specific force R^T (acc - g), g = (0, 0, -9.81), + bias + white noise; the bias
    random-walks.
  * magnetometer (50 Hz): delivered as a heading `mag_yaw` = true yaw + white noise, wrapped to (-pi, pi].
  * barometer (25 Hz): altitude above the ground plane + white noise + a slowly random-walking drift.
  * optical flow (25 Hz, drone only): (v_body_x, v_body_y) / height above ground (flat terrain at z = 0) + white noise;
    flow[0] pairs with forward, flow[1] with leftward body velocity (rad/s, already gyro-compensated). Below
    `flow_min_height` the sample is invalid: zeros and flow_fresh = 0.
  * wheel odometry (25 Hz, rover only): forward body speed + white noise.
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


@dataclasses.dataclass(frozen=True)
class SensorConfig:
  """Rates (Hz) and noise of the sensor suite. σ are per-sample standard deviations."""

  # GPS
  gps_rate: float = 10.0
  gps_pos_sigma_h: float = 0.5  # m, white, per horizontal axis
  gps_pos_sigma_v: float = 0.8  # m, white, vertical
  gps_drift_sigma_h: float = 0.2  # m, stationary σ of the correlated wander, horizontal
  gps_drift_sigma_v: float = 0.3  # m, same, vertical
  gps_drift_tau: float = 60.0  # s, correlation time of the wander
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
  # magnetometer heading
  mag_rate: float = 50.0
  mag_sigma: float = 0.03  # rad
  # barometer
  baro_rate: float = 25.0
  baro_sigma: float = 0.3  # m
  baro_drift_walk: float = 0.01  # m/sqrt(s)
  # optical flow
  has_flow: bool = True
  flow_rate: float = 25.0
  flow_sigma: float = 0.05  # rad/s
  flow_min_height: float = 0.3  # m
  # wheel odometry
  has_odom: bool = False
  odom_rate: float = 25.0
  odom_sigma: float = 0.05  # m/s

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
    """Same rates, every noise, bias and drift set to zero (for tests and debugging)."""
    zero = {f.name: 0.0 for f in dataclasses.fields(self)
            if f.name.endswith(("_sigma", "_sigma_h", "_sigma_v", "_init", "_walk"))}
    return dataclasses.replace(self, **zero)


@struct.dataclass
class SensorState:
  """Per-vehicle sensor memory.

  tick: [] int32 ticks since init.  gyro_bias, accel_bias: [3] current IMU biases (rad/s, m/s^2).
  gps_drift: [3] current correlated GPS position error (m).  baro_drift: [] barometer drift (m).
  held: SensorReadings, the last delivered readings (stale sensors repeat them).
  """

  tick: jnp.ndarray
  gyro_bias: jnp.ndarray
  accel_bias: jnp.ndarray
  gps_drift: jnp.ndarray
  baro_drift: jnp.ndarray
  held: SensorReadings


def quat_yaw(q):
  """[4] -> [] yaw (rad) of a body->world quaternion (ZYX Euler yaw)."""
  return quat_to_euler(q)[2]


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


def _measure(cfg: SensorConfig, truth: TrueState, gyro_bias, accel_bias, gps_drift, baro_drift, n):
  """Fresh samples of every sensor (no rate logic) given n [17] standard-normal draws.

  Returns a SensorReadings with all fresh flags 1 (flow: validity, odom: presence).
  """
  f32 = jnp.float32
  r = quat_to_rot(truth.quat)
  vel_b = matvec_t(r, truth.vel)
  sig_p = jnp.array([cfg.gps_pos_sigma_h, cfg.gps_pos_sigma_h, cfg.gps_pos_sigma_v], f32)
  sig_v = jnp.array([cfg.gps_vel_sigma_h, cfg.gps_vel_sigma_h, cfg.gps_vel_sigma_v], f32)
  gps_pos = truth.pos + gps_drift + sig_p * n[0:3]
  gps_vel = truth.vel + sig_v * n[3:6]
  gyro = truth.ang_vel + gyro_bias + cfg.gyro_sigma * n[6:9]
  g = jnp.array([0.0, 0.0, -GRAVITY], f32)
  accel = matvec_t(r, truth.acc - g) + accel_bias + cfg.accel_sigma * n[9:12]
  gyro = jnp.clip(gyro, -GYRO_RANGE, GYRO_RANGE)
  accel = jnp.clip(accel, -ACCEL_RANGE, ACCEL_RANGE)
  mag_yaw = wrap_angle(quat_yaw(truth.quat) + cfg.mag_sigma * n[12])
  height = truth.pos[2]
  baro_alt = height + baro_drift + cfg.baro_sigma * n[13]
  flow_valid = height >= cfg.flow_min_height
  flow = vel_b[:2] / jnp.maximum(height, cfg.flow_min_height) + cfg.flow_sigma * n[14:16]
  flow = jnp.where(flow_valid & cfg.has_flow, flow, 0.0)
  odom = jnp.where(cfg.has_odom, vel_b[0] + cfg.odom_sigma * n[16], 0.0)
  one = jnp.ones((), f32)
  return SensorReadings(
    gps_pos=gps_pos, gps_vel=gps_vel, gps_fresh=one, gyro=gyro, accel=accel, mag_yaw=mag_yaw, mag_fresh=one,
    baro_alt=baro_alt, baro_fresh=one, flow=flow, flow_fresh=(flow_valid & cfg.has_flow).astype(f32),
    odom_speed=odom, odom_fresh=one * cfg.has_odom)


def init_sensors(cfg: SensorConfig, truth: TrueState, rng) -> SensorState:
  """Draws turn-on biases and an initial GPS wander; `held` gets a first sample of everything. tick = 0."""
  n = jax.random.normal(rng, (9 + _N_MEAS_NOISE,))  # one draw: cheap to compile
  gyro_bias = cfg.gyro_bias_init * n[0:3]
  accel_bias = cfg.accel_bias_init * n[3:6]
  sig_d = jnp.array([cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_v], jnp.float32)
  gps_drift = sig_d * n[6:9]
  baro_drift = jnp.zeros((), jnp.float32)
  held = _measure(cfg, truth, gyro_bias, accel_bias, gps_drift, baro_drift, n[9:])
  return SensorState(tick=jnp.zeros((), jnp.int32), gyro_bias=gyro_bias, accel_bias=accel_bias,
                     gps_drift=gps_drift, baro_drift=baro_drift, held=held)


def sense(cfg: SensorConfig, state: SensorState, truth: TrueState, rng, dt) -> tuple[SensorState, SensorReadings]:
  """One autopilot tick: advance biases/drifts by dt (s), sample fresh sensors, hold stale ones.

  Returns (new state, readings). The first call after `init_sensors` (tick 0) has every sensor fresh.
  """
  n = jax.random.normal(rng, (10 + _N_MEAS_NOISE,))  # one draw: cheap to compile
  sqdt = jnp.sqrt(dt)
  gyro_bias = state.gyro_bias + cfg.gyro_bias_walk * sqdt * n[0:3]
  accel_bias = state.accel_bias + cfg.accel_bias_walk * sqdt * n[3:6]
  # first-order Gauss-Markov wander with stationary σ_d: x' = a x + σ_d sqrt(1 - a^2) n
  a = jnp.exp(-dt / cfg.gps_drift_tau)
  sig_d = jnp.array([cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_h, cfg.gps_drift_sigma_v], jnp.float32)
  gps_drift = a * state.gps_drift + sig_d * jnp.sqrt(1.0 - a * a) * n[6:9]
  baro_drift = state.baro_drift + cfg.baro_drift_walk * sqdt * n[9]
  new = _measure(cfg, truth, gyro_bias, accel_bias, gps_drift, baro_drift, n[10:])

  per = _periods(cfg, dt)
  due = {name: (jnp.mod(state.tick, p) == 0) for name, p in per.items()}
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
    # an invalid flow sample (too low) reads zero even on a due tick
    flow=jnp.where(due["flow"], new.flow, held.flow),
    flow_fresh=flow_fresh.astype(f32),
    odom_speed=pick(due["odom"], new.odom_speed, held.odom_speed),
    odom_fresh=(due["odom"] & cfg.has_odom).astype(f32),
  )
  state = SensorState(tick=state.tick + 1, gyro_bias=gyro_bias, accel_bias=accel_bias, gps_drift=gps_drift,
                      baro_drift=baro_drift, held=readings)
  return state, readings
