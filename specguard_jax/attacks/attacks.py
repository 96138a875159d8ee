"""Sensor-spoofing attacks (SpecGuard Sec. 5.3, Table 3) injected at the sensor interface, before the EKF.

Bias per sensor (units of the `SensorReadings` field it enters; the paper's Table 3 ranges, converted):
  gps   [3] m on gps_pos (1-50 m). A ramping spoofer also moves the fake velocity consistently: gps_vel += db/dt.
  gyro  [3] rad/s on gyro (0.5-9.47; the paper's "attitude" bias on the gyroscope, read as a rate bias).
  accel [3] m/s^2 on accel (0.5-6.2).
  mag   [1] rad on mag_yaw (90-180 deg).
  baro  [1] m on baro_alt (0.1 kPa ~ 8.3 m of altitude at sea level: dh = dP / (rho g), rho = 1.225 kg/m^3).
  flow  [2] rad/s on flow (1-7.07 px/frame x 0.0209 rad/px (PMW3901, 42 deg / 35 px) x 25 frames/s = 0.52-3.7).
Profiles: OVERT = constant bias from onset; STEALTHY = linear ramp from 0 reaching the full bias after `ramp_time`
(slow enough to stay inside the EKF gates / the detector's threshold for a while; a negative bias direction gives the
paper's "gradually decreasing" case). The bias is applied for onset <= t < onset + duration.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import math3d
from specguard_jax.types import SENSOR_NAMES, SensorReadings  # noqa: F401 (re-exported)

OVERT, STEALTHY = 0, 1
PROFILES = ("overt", "stealthy")
ONSET_MODES = ("random", "given")
UNTIL_END = 1e9   # duration (s) of an attack that lasts until the episode ends
N_SENSORS = len(SENSOR_NAMES)
BIAS_DIMS = {"gps": 3, "gyro": 3, "accel": 3, "mag": 1, "baro": 1, "flow": 2}
_BARO_M_PER_KPA = 1000.0 / (1.225 * 9.81)
_FLOW_RAD_S_PER_PX_FRAME = 0.0209 * 25.0
# Magnitude range (|b|) per sensor in the units above.
BIAS_RANGES = {
    "gps": (1.0, 50.0),
    "gyro": (0.5, 9.47),
    "accel": (0.5, 6.2),
    "mag": (float(np.deg2rad(90.0)), float(np.deg2rad(180.0))),
    "baro": (0.05 * _BARO_M_PER_KPA, 0.1 * _BARO_M_PER_KPA),
    "flow": (1.0 * _FLOW_RAD_S_PER_PX_FRAME, 7.07 * _FLOW_RAD_S_PER_PX_FRAME),
}


@struct.dataclass
class AttackSchedule:
  """One episode's attack. mask [6] 0/1 per sensor (SENSOR_NAMES order); bias [6, 3] full bias per sensor (unused
  components 0); onset, duration, ramp_time [] s; profile [] int32 (OVERT | STEALTHY)."""
  mask: jnp.ndarray
  bias: jnp.ndarray
  onset: jnp.ndarray
  duration: jnp.ndarray
  ramp_time: jnp.ndarray
  profile: jnp.ndarray


def no_attack() -> AttackSchedule:
  z = jnp.zeros(())
  return AttackSchedule(mask=jnp.zeros(N_SENSORS), bias=jnp.zeros((N_SENSORS, 3)), onset=jnp.full((), 1e9),
                        duration=z, ramp_time=jnp.ones(()), profile=jnp.zeros((), jnp.int32))


def schedule_for(sensor: str, bias, onset: float, duration: float, profile: str = "overt",
                 ramp_time: float = 10.0) -> AttackSchedule:
  """A scripted single-sensor attack, e.g. schedule_for('gps', [20, 0, 0], onset=10, duration=30)."""
  if sensor not in SENSOR_NAMES:
    raise ValueError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSOR_NAMES)}")
  if profile not in PROFILES:
    raise ValueError(f"unknown attack profile {profile!r}; choose one of {PROFILES}")
  b = np.zeros((N_SENSORS, 3), np.float32)
  v = np.atleast_1d(np.asarray(bias, np.float32))
  if v.shape != (BIAS_DIMS[sensor],):
    raise ValueError(f"{sensor} bias must have {BIAS_DIMS[sensor]} component(s), got {v.shape[0]}")
  i = SENSOR_NAMES.index(sensor)
  b[i, :v.shape[0]] = v
  return AttackSchedule(mask=jnp.asarray(np.eye(N_SENSORS, dtype=np.float32)[i]), bias=jnp.asarray(b),
                        onset=jnp.asarray(onset, jnp.float32), duration=jnp.asarray(duration, jnp.float32),
                        ramp_time=jnp.asarray(max(ramp_time, 1e-3), jnp.float32),
                        profile=jnp.asarray(PROFILES.index(profile), jnp.int32))


def attack_active(s: AttackSchedule, t):
  """[] bool: the attack is on at time t (s)."""
  return (t >= s.onset) & (t < s.onset + s.duration) & (jnp.sum(s.mask) > 0)


def bias_at(s: AttackSchedule, t):
  """(bias [6, 3], bias rate [6, 3] per s) at time t; zero outside the attack window and on untargeted sensors."""
  on = attack_active(s, t)
  frac = jnp.where(s.profile == STEALTHY, jnp.clip((t - s.onset) / s.ramp_time, 0.0, 1.0), 1.0)
  ramping = (s.profile == STEALTHY) & (t - s.onset < s.ramp_time)
  m = s.mask[:, None] * on
  return s.bias * frac * m, jnp.where(ramping, s.bias / s.ramp_time, 0.0) * m


def apply_attack(readings: SensorReadings, s: AttackSchedule, t) -> SensorReadings:
  """Spoofed readings y + b(t) (see module docstring); untargeted sensors are returned unchanged."""
  b, rate = bias_at(s, t)
  i = {n: k for k, n in enumerate(SENSOR_NAMES)}
  return readings.replace(
      gps_pos=readings.gps_pos + b[i["gps"]],
      gps_vel=readings.gps_vel + rate[i["gps"]],
      gyro=readings.gyro + b[i["gyro"]],
      accel=readings.accel + b[i["accel"]],
      mag_yaw=jnp.where(b[i["mag"], 0] != 0, math3d.wrap_angle(readings.mag_yaw + b[i["mag"], 0]), readings.mag_yaw),
      baro_alt=readings.baro_alt + b[i["baro"], 0],
      flow=readings.flow + b[i["flow"], :2] * readings.flow_fresh,
  )


@dataclasses.dataclass(frozen=True)
class AttackConfig:
  """Distribution of per-episode attacks (random campaigns for evaluation and phase-2 training).

  sensors: attackable sensor names.  profiles: 'overt' and/or 'stealthy'.  n_sensors: how many sensors one attack
  targets at once (2 for the paper's GPS + gyroscope multi-sensor experiment).  p_attack: probability an episode is
  attacked.  onset_frac: onset as a fraction of the mission's nominal duration.  duration_s: attack length.
  ramp_s: stealthy ramp time.  scale: multiplies BIAS_RANGES (1.0 = the paper's Table 3).
  until_end: the attack lasts until the episode ends (duration UNTIL_END) instead of duration_s.
  onset: 'random' (onset_frac) | 'given' (the caller computes the onset per episode, e.g. a lead time before a hazard
  of the mission in its world, and hands it to `sample_attack`; attack scheduling knows no missions or worlds).
  ramp_rate: per-sensor stealthy ramp rates ((sensor, |db/dt| in the sensor's bias units per s), ...), e.g. designed
  against a detector (calibration.stealthy.design_rates): a sensor listed ramps at its rate (ramp time |b| / rate)
  instead of over ramp_s.
  """
  sensors: tuple = SENSOR_NAMES
  profiles: tuple = PROFILES
  n_sensors: int = 1
  p_attack: float = 1.0
  onset_frac: tuple = (0.15, 0.5)
  duration_s: tuple = (15.0, 40.0)
  ramp_s: tuple = (10.0, 30.0)
  scale: float = 1.0
  until_end: bool = False
  onset: str = "random"
  ramp_rate: tuple = ()

  def __post_init__(self):
    bad = [x for x in self.sensors if x not in SENSOR_NAMES]
    if bad or not self.sensors:
      raise ValueError(f"unknown or no attack sensor(s) {bad}; choose from {', '.join(SENSOR_NAMES)}")
    badp = [x for x in self.profiles if x not in PROFILES]
    if badp or not self.profiles:
      raise ValueError(f"unknown or no attack profile(s) {badp}; choose from {PROFILES}")
    if not 1 <= self.n_sensors <= len(self.sensors):
      raise ValueError(f"n_sensors must be in 1..{len(self.sensors)}")
    if not 0.0 <= self.p_attack <= 1.0:
      raise ValueError("p_attack must be in [0, 1]")
    if self.onset not in ONSET_MODES:
      raise ValueError(f"unknown onset mode {self.onset!r}; choose from {ONSET_MODES}")
    bad = [x for x, r in self.ramp_rate if x not in SENSOR_NAMES or not r > 0]
    if bad:
      raise ValueError(f"ramp_rate needs known sensors and rates > 0, got {bad}")

  def rates(self) -> np.ndarray:
    """[6] stealthy ramp rate per sensor (SENSOR_NAMES order; 0 = ramp over ramp_s)."""
    d = dict(self.ramp_rate)
    return np.asarray([float(d.get(n, 0.0)) for n in SENSOR_NAMES], np.float32)


def sample_attack(cfg: AttackConfig, rng, nominal_duration, onset=None) -> AttackSchedule:
  """Draw one episode's attack: sensors, profile, bias (uniform magnitude in range, random direction), timing.

  nominal_duration: [] s, the mission's.  onset: [] s, the onset when cfg.onset == 'given' (required then, ignored
  otherwise). The random draws are the same whatever the timing options, so campaigns that differ only in timing
  attack the same sensors with the same biases."""
  ks = jax.random.split(rng, 8)
  allowed = jnp.asarray([float(n in cfg.sensors) for n in SENSOR_NAMES])
  # n distinct sensors among the allowed ones: top-n of random keys.
  keys = jnp.where(allowed > 0, jax.random.uniform(ks[0], (N_SENSORS,)), -1.0)
  kth = jnp.sort(keys)[-cfg.n_sensors]
  mask = (keys >= kth).astype(jnp.float32) * allowed
  lo = jnp.asarray([BIAS_RANGES[n][0] for n in SENSOR_NAMES]) * cfg.scale
  hi = jnp.asarray([BIAS_RANGES[n][1] for n in SENSOR_NAMES]) * cfg.scale
  mag = lo + jax.random.uniform(ks[1], (N_SENSORS,)) * (hi - lo)
  dims = jnp.asarray([BIAS_DIMS[n] for n in SENSOR_NAMES])
  d = jax.random.normal(ks[2], (N_SENSORS, 3)) * (jnp.arange(3)[None, :] < dims[:, None])
  # GPS spoofing moves the fake position mostly horizontally (vertical third as large).
  d = d.at[0, 2].multiply(1.0 / 3.0)
  d = d / (jnp.linalg.norm(d, axis=-1, keepdims=True) + 1e-9)
  bias = d * mag[:, None] * mask[:, None]
  profiles = jnp.asarray([PROFILES.index(p) for p in cfg.profiles], jnp.int32)
  profile = profiles[jax.random.randint(ks[3], (), 0, len(cfg.profiles))]
  frac_onset = nominal_duration * jax.random.uniform(ks[4], (), minval=cfg.onset_frac[0], maxval=cfg.onset_frac[1])
  if cfg.onset == "given":
    if onset is None:
      raise ValueError("AttackConfig.onset == 'given' needs the onset (s) passed to sample_attack")
    frac_onset = jnp.maximum(jnp.asarray(onset, jnp.float32), 0.0)
  duration = jax.random.uniform(ks[5], (), minval=cfg.duration_s[0], maxval=cfg.duration_s[1])
  if cfg.until_end:
    duration = jnp.full((), UNTIL_END, jnp.float32)
  ramp = jax.random.uniform(ks[6], (), minval=cfg.ramp_s[0], maxval=cfg.ramp_s[1])
  if cfg.ramp_rate:   # the designed rate of the (first) attacked sensor that has one
    rates = jnp.asarray(cfg.rates()) * mask
    k = jnp.argmax(rates > 0)
    ramp = jnp.where(rates[k] > 0, mag[k] / jnp.maximum(rates[k], 1e-9), ramp)
  attacked = jax.random.uniform(ks[7]) < cfg.p_attack
  s = AttackSchedule(mask=mask, bias=bias, onset=frac_onset, duration=duration, ramp_time=ramp,
                     profile=profile.astype(jnp.int32))
  return jax.tree.map(lambda a, b: jnp.where(attacked, a, b), s, no_attack())
