"""ArduRover-style controller (ArduPilot Rover 4.3 AR_AttitudeControl + AR_WPNav, simplified).

Input is the navigator's (or a recovery policy's) world velocity setpoint; its direction is the desired heading
(vector-field line following, the navigator adds the cross-track term) and its norm the desired speed.
Steering: desired turn rate = ATC_STR_ANG_P * heading error, limited by the lateral acceleration ATC_TURN_MAX_G and
the max turn rate; converted to an Ackermann steering angle delta = atan(wheelbase * rate / speed).
Speed: throttle = feed-forward (nominal drive model) + ATC_SPEED_P/I on speed error, with the speed setpoint
rate-limited by ATC_ACCEL_MAX / ATC_DECEL_MAX.
"""

import dataclasses

import jax.numpy as jnp
from flax import struct

from specguard_jax import math3d


@dataclasses.dataclass(frozen=True)
class RoverParams:
  """ArduRover parameters (names in comments) and the nominal drive model the feed-forward assumes."""
  str_ang_p: float = 2.0       # ATC_STR_ANG_P (1/s)
  turn_max_g: float = 0.4      # ATC_TURN_MAX_G (g)
  str_rat_max: float = 2.0     # ATC_STR_RAT_MAX (rad/s)
  speed_p: float = 0.2         # ATC_SPEED_P (throttle per m/s)
  speed_i: float = 0.2         # ATC_SPEED_I
  speed_imax: float = 0.5      # ATC_SPEED_IMAX
  accel_max: float = 2.0       # ATC_ACCEL_MAX (m/s^2)
  decel_max: float = 3.0       # ATC_DECEL_MAX (m/s^2)
  max_steer: float = 0.5       # rad, Ackermann limit
  wheelbase: float = 0.55      # m
  drive_force: float = 70.0    # N at full throttle (nominal)
  rolling: float = 3.0         # N per m/s (nominal)
  drag: float = 0.2            # N per (m/s)^2 (nominal)


@struct.dataclass
class RoverControlState:
  """speed_sp: rate-limited speed setpoint (m/s); speed_int: integrator (throttle units)."""
  speed_sp: jnp.ndarray
  speed_int: jnp.ndarray

  @classmethod
  def zeros(cls):
    return cls(speed_sp=jnp.zeros(()), speed_int=jnp.zeros(()))


def rover_control(p: RoverParams, cs: RoverControlState, vel_sp, yaw, speed, dt, armed):
  """One control tick. vel_sp [3] world m/s; yaw [] rad (estimated); speed [] forward m/s (estimated).

  Returns (state, throttle [] in [-1, 1], steer [] rad).
  """
  v_des = math3d.norm(vel_sp[:2])
  heading = jnp.arctan2(vel_sp[1], vel_sp[0])
  err = math3d.wrap_angle(heading - yaw)
  err = jnp.where(v_des > 0.05, err, 0.0)
  # Steering from a turn-rate demand.
  v_eff = jnp.maximum(jnp.abs(speed), 1.0)
  rate_max = jnp.minimum(p.str_rat_max, p.turn_max_g * 9.81 / v_eff)
  rate = jnp.clip(p.str_ang_p * err, -rate_max, rate_max)
  steer = jnp.clip(jnp.arctan(p.wheelbase * rate / v_eff), -p.max_steer, p.max_steer)
  # Slow down for large heading errors (ArduRover reduces speed in sharp turns).
  v_des = v_des * jnp.clip(jnp.cos(err), 0.2, 1.0)
  # Speed loop.
  dv = v_des - cs.speed_sp
  speed_sp = cs.speed_sp + jnp.clip(dv, -p.decel_max * dt, p.accel_max * dt)
  ff = (p.rolling * speed_sp + p.drag * speed_sp * jnp.abs(speed_sp)) / p.drive_force
  e = speed_sp - speed
  speed_int = jnp.clip(cs.speed_int + p.speed_i * e * dt, -p.speed_imax, p.speed_imax)
  throttle = jnp.clip(ff + p.speed_p * e + speed_int, -1.0, 1.0)
  throttle = jnp.where(armed, throttle, 0.0)
  cs = RoverControlState(speed_sp=jnp.where(armed, speed_sp, 0.0), speed_int=jnp.where(armed, speed_int, 0.0))
  return cs, throttle, steer
