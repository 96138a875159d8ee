"""PX4-style multicopter control cascade (PX4 v1.13 mc_pos_control / mc_att_control / mc_rate_control + mixer).

velocity setpoint --(velocity PID, MPC_*_VEL_*_ACC)--> acceleration setpoint --(thrust vector, tilt limit
MPC_TILTMAX_AIR, hover thrust MPC_THR_HOVER)--> attitude + collective thrust --(attitude P, MC_*_P, geometric error with
yaw de-prioritised by the rate limits)--> body-rate setpoint --(rate PID, MC_*RATE_P/I/D)--> normalised torques
--(mixer with PX4-style desaturation: yaw gives way first, then thrust shifts, roll/pitch kept)--> rotor thrusts (N).

The position loop (MPC_XY_P, MPC_Z_P) lives in the navigator, which hands this module a velocity setpoint; a recovery
policy overrides that velocity setpoint (see envs/drone.py). Gains default to PX4's (shared/reference/NOTES.md).

Horizontal authority (a deviation from PX4): the velocity PID's horizontal output is capped at `acc_hor_max` = 7 m/s^2
(~35 deg of tilt), the integrator inside the cap. PX4 bounds that output by the tilt limit only (MPC_TILTMAX_AIR, 45
deg) and applies MPC_ACC_HOR_MAX (5 m/s^2) to its smoothed setpoint. The old 5 m/s^2 cap on the output (integrator
held at 3) could not hold 5 m/s ground speed against drag in an 8 m/s headwind with gusts (S7 in ~0.7 % of attack-free
missions); the full 45 deg doubled the flips of SpecGuard-RC (trained with the 5 m/s^2 cap) under gyroscope attacks,
where the autopilot flies a reconstructed attitude for tens of seconds (CPU, 100 missions: overt 14 -> 36 %).
Normalised torque 1.0 equals the full-scale differential of PX4's quad_x mixer (0.707 * T_max per rotor on roll/pitch,
T_max per rotor on yaw), so PX4's rate gains keep their meaning on this airframe.

Deviation from PX4: every loop runs at the env tick (50 Hz) instead of 250-1000 Hz; the gains are stable at that rate
for this airframe (tests/test_drone.py checks step responses), but the D terms see a coarser derivative.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import math3d

G = 9.81


@dataclasses.dataclass(frozen=True)
class MulticopterParams:
  """PX4 parameters used by the cascade (PX4 names in comments; SI units, radians)."""
  xy_vel_p: float = 1.8        # MPC_XY_VEL_P_ACC
  xy_vel_i: float = 0.4        # MPC_XY_VEL_I_ACC
  xy_vel_d: float = 0.2        # MPC_XY_VEL_D_ACC
  z_vel_p: float = 4.0         # MPC_Z_VEL_P_ACC
  z_vel_i: float = 2.0         # MPC_Z_VEL_I_ACC
  z_vel_d: float = 0.0         # MPC_Z_VEL_D_ACC
  acc_hor_max: float = 7.0     # cap on the horizontal acceleration setpoint (m/s^2), see the module docstring
  tilt_max: float = float(np.deg2rad(45.0))  # MPC_TILTMAX_AIR
  thr_min: float = 0.08        # MPC_THR_MIN
  thr_max: float = 1.0         # MPC_THR_MAX
  roll_p: float = 4.0          # MC_ROLL_P
  pitch_p: float = 4.0         # MC_PITCH_P
  yaw_p: float = 2.8           # MC_YAW_P
  rollrate_max: float = float(np.deg2rad(220.0))   # MC_ROLLRATE_MAX
  pitchrate_max: float = float(np.deg2rad(220.0))  # MC_PITCHRATE_MAX
  yawrate_max: float = float(np.deg2rad(200.0))    # MC_YAWRATE_MAX
  rollrate_pid: tuple = (0.15, 0.2, 0.003)   # MC_ROLLRATE_P/I/D
  pitchrate_pid: tuple = (0.15, 0.2, 0.003)  # MC_PITCHRATE_P/I/D
  yawrate_pid: tuple = (0.2, 0.1, 0.0)       # MC_YAWRATE_P/I/D
  rate_int_lim: float = 0.3    # MC_RR_INT_LIM
  vel_int_lim: float = 5.0     # horizontal acceleration authority of the velocity integrator (m/s^2): wind + drag
  vel_int_lim_z: float = 3.0   # vertical acceleration authority of the velocity integrator (m/s^2): hover trim


@dataclasses.dataclass(frozen=True)
class Airframe:
  """Rotor geometry read from the MJCF (numpy, static).

  rotor_xy: [n, 2] rotor positions in the body frame (m).  yaw_coef: [n] reaction torque per newton (m), signed.
  thrust_max: N per rotor.  mass: kg.  alloc: [n, 4] maps physical (tau_x, tau_y, tau_z, F) to rotor thrusts (N).
  torque_scale: [3] N·m per unit normalised torque.
  """
  rotor_xy: np.ndarray
  yaw_coef: np.ndarray
  thrust_max: float
  mass: float

  @property
  def n_rotors(self):
    return self.rotor_xy.shape[0]

  @property
  def effectiveness(self):
    """[4, n]: rows tau_x, tau_y, tau_z, F per newton of each rotor."""
    x, y = self.rotor_xy[:, 0], self.rotor_xy[:, 1]
    return np.stack([y, -x, self.yaw_coef, np.ones_like(x)])

  @property
  def alloc(self):
    return np.linalg.pinv(self.effectiveness)

  @property
  def torque_scale(self):
    x, y = self.rotor_xy[:, 0], self.rotor_xy[:, 1]
    t = self.thrust_max
    return np.array([0.707 * t * np.abs(y).sum(), 0.707 * t * np.abs(x).sum(), t * np.abs(self.yaw_coef).sum()])

  @property
  def hover_thrust(self):
    """Normalised collective thrust that holds the nominal mass (MPC_THR_HOVER)."""
    return self.mass * G / (self.n_rotors * self.thrust_max)

  @classmethod
  def from_mjcf(cls, mj_model):
    """Reads rotor sites, gears and ctrl ranges of every actuator of a MuJoCo model."""
    xy, yc, tmax = [], [], []
    for i in range(mj_model.nu):
      site = mj_model.actuator_trnid[i, 0]
      xy.append(np.array(mj_model.site_pos[site][:2]))
      gear = np.array(mj_model.actuator_gear[i])
      yc.append(gear[5] / gear[2])
      tmax.append(mj_model.actuator_ctrlrange[i, 1] * gear[2])
    body = mj_model.site_bodyid[mj_model.actuator_trnid[0, 0]]
    return cls(rotor_xy=np.stack(xy), yaw_coef=np.array(yc), thrust_max=float(np.min(tmax)),
               mass=float(mj_model.body_mass[body]))


@struct.dataclass
class MCControlState:
  """Integrators and previous measurements of the cascade. vel_int [3] (m/s^2), rate_int [3], prev_vel [3],
  prev_rate [3]."""
  vel_int: jnp.ndarray
  rate_int: jnp.ndarray
  prev_vel: jnp.ndarray
  prev_rate: jnp.ndarray

  @classmethod
  def zeros(cls):
    z = jnp.zeros(3)
    return cls(vel_int=z, rate_int=z, prev_vel=z, prev_rate=z)


def velocity_control(p: MulticopterParams, cs: MCControlState, vel_sp, vel, dt):
  """Velocity PID -> acceleration setpoint [3] (world, m/s^2, gravity excluded)."""
  kp = jnp.array([p.xy_vel_p, p.xy_vel_p, p.z_vel_p])
  ki = jnp.array([p.xy_vel_i, p.xy_vel_i, p.z_vel_i])
  kd = jnp.array([p.xy_vel_d, p.xy_vel_d, p.z_vel_d])
  err = vel_sp - vel
  vel_dot = (vel - cs.prev_vel) / dt
  acc_sp = kp * err + cs.vel_int - kd * vel_dot
  # Horizontal acceleration limit (PX4: the tilt limit; see the module docstring).
  h = math3d.norm(acc_sp[:2]) + 1e-9
  saturated = h > p.acc_hor_max
  acc_sp = math3d.scale_head(acc_sp, 2, jnp.minimum(1.0, p.acc_hor_max / h))
  # Anti-windup (as PX4): the horizontal integrator only integrates while the horizontal output is not saturated.
  grow = jnp.where((jnp.arange(3) < 2) & saturated, 0.0, 1.0)
  lim = jnp.array([p.vel_int_lim, p.vel_int_lim, p.vel_int_lim_z])
  vel_int = jnp.clip(cs.vel_int + grow * ki * err * dt, -lim, lim)
  return acc_sp, cs.replace(vel_int=vel_int, prev_vel=vel)


def thrust_attitude(p: MulticopterParams, hover_thrust, acc_sp, yaw_sp):
  """Acceleration setpoint -> (desired rotation [3,3] as its columns body_x, body_y, body_z (each a tuple of 3
  components), normalised collective thrust []). PX4 _accelerationControl."""
  ax, ay, az = acc_sp[0], acc_sp[1], acc_sp[2]
  lift = jnp.maximum(G + az, 0.1 * G)
  n = math3d.hypot(ax, ay, lift)
  zx, zy, zz = ax / n, ay / n, lift / n
  # Tilt limit: keep the direction, cap the angle from vertical.
  tilt = jnp.arccos(jnp.clip(zz, -1.0, 1.0))
  h = math3d.hypot(zx, zy) + 1e-9
  tilt_c = jnp.minimum(tilt, p.tilt_max)
  over = tilt > p.tilt_max
  s_c = jnp.sin(tilt_c)
  zx, zy, zz = (jnp.where(over, zx / h * s_c, zx), jnp.where(over, zy / h * s_c, zy),
                jnp.where(over, jnp.cos(tilt_c), zz))
  thrust = lift / G * hover_thrust / jnp.maximum(zz, 0.3)
  thrust = jnp.clip(thrust, p.thr_min, p.thr_max)
  cx, cy = jnp.cos(yaw_sp), jnp.sin(yaw_sp)
  # body_y = body_z x (cos yaw, sin yaw, 0), normalised; body_x = body_y x body_z
  yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
  ny = math3d.hypot(yx, yy, yz) + 1e-9
  yx, yy, yz = yx / ny, yy / ny, yz / ny
  xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
  return ((xx, xy, xz), (yx, yy, yz), (zx, zy, zz)), thrust


def attitude_control(p: MulticopterParams, r_des, quat):
  """Geometric attitude P controller -> body-rate setpoint [3] (rad/s), rate-limited per axis. r_des: the desired
  rotation's columns (`thrust_attitude`)."""
  r = math3d.quat_to_rot(quat)
  rc = [[r[k, j] for k in range(3)] for j in range(3)]    # rc[j][k] = R[k, j]: the columns of R

  def m(i, j):   # (R_des' R - R' R_des)[i, j]
    return sum(r_des[i][k] * rc[j][k] for k in range(3)) - sum(rc[i][k] * r_des[j][k] for k in range(3))

  e_r = 0.5 * jnp.stack([m(2, 1), m(0, 2), m(1, 0)])
  k = jnp.array([p.roll_p, p.pitch_p, p.yaw_p])
  lim = jnp.array([p.rollrate_max, p.pitchrate_max, p.yawrate_max])
  return jnp.clip(-k * e_r, -lim, lim)


def rate_control(p: MulticopterParams, cs: MCControlState, rate_sp, rate, dt, integrate):
  """Rate PID -> normalised torques [3] in [-1, 1]."""
  gains = np.array([p.rollrate_pid, p.pitchrate_pid, p.yawrate_pid], np.float32)  # [3, 3]: axis x (P, I, D)
  err = rate_sp - rate
  rate_dot = (rate - cs.prev_rate) / dt
  torque = gains[:, 0] * err + cs.rate_int - gains[:, 2] * rate_dot
  rate_int = jnp.where(integrate, jnp.clip(cs.rate_int + gains[:, 1] * err * dt, -p.rate_int_lim, p.rate_int_lim),
                       jnp.zeros(3))
  return jnp.clip(torque, -1.0, 1.0), cs.replace(rate_int=rate_int, prev_rate=rate)


def mix(airframe: Airframe, torque_norm, thrust_norm):
  """Normalised torques [3] and collective thrust [] -> rotor thrusts [n] (N), PX4-style desaturation."""
  alloc = np.asarray(airframe.alloc, np.float32)            # [n, 4]
  scale = np.asarray(airframe.torque_scale, np.float32)
  tmax = airframe.thrust_max
  n = airframe.n_rotors
  t0, t1, t2 = (torque_norm[k] * scale[k] for k in range(3))
  u_rp = [(alloc[i, 0] * t0 + alloc[i, 1] * t1) / tmax for i in range(n)]   # normalised rotor commands, roll/pitch
  u_y = [alloc[i, 2] * t2 / tmax for i in range(n)]
  u_t = [alloc[i, 3] * (thrust_norm * n * tmax) / tmax for i in range(n)]
  vmax = lambda xs: functools.reduce(jnp.maximum, xs)   # noqa: E731
  vmin = lambda xs: functools.reduce(jnp.minimum, xs)   # noqa: E731
  # 1) roll/pitch must fit in [0, 1]: scale them down if their spread alone exceeds the range.
  spread = vmax(u_rp) - vmin(u_rp)
  f = jnp.minimum(1.0, 1.0 / jnp.maximum(spread, 1e-9))
  u_rp = [x * f for x in u_rp]
  # 2) shift the collective thrust so that thrust + roll/pitch fits.
  base = [a + b for a, b in zip(u_t, u_rp)]
  lo, hi = jnp.maximum(0.0, -vmin(base)), jnp.maximum(0.0, vmax(base) - 1.0)
  base = [x + lo - hi for x in base]
  # 3) yaw gives way: largest fraction of the yaw command that keeps every rotor in range.
  room = [jnp.where(uy > 0, (1.0 - b) / jnp.maximum(uy, 1e-9), b / jnp.maximum(-uy, 1e-9)) for b, uy in zip(base, u_y)]
  s_y = jnp.clip(vmin([jnp.where(jnp.abs(uy) > 1e-9, r, 1.0) for r, uy in zip(room, u_y)]), 0.0, 1.0)
  u = jnp.clip(jnp.stack([b + s_y * uy for b, uy in zip(base, u_y)]), 0.0, 1.0)
  return u * tmax


def mc_control(p: MulticopterParams, airframe: Airframe, cs: MCControlState, vel_sp, yaw_sp, vel, quat, rate, dt,
               armed):
  """One tick of the whole cascade. Returns (new state, rotor thrusts [n] in N, debug dict).

  vel_sp, vel: [3] world m/s.  yaw_sp: [] rad.  quat: [4] estimated attitude.  rate: [3] body rad/s (gyro - bias).
  armed: [] bool; when False (landed / mission done) rotors are off and integrators reset.
  """
  acc_sp, cs = velocity_control(p, cs, vel_sp, vel, dt)
  return attitude_cascade(p, airframe, cs, acc_sp, yaw_sp, quat, rate, dt, armed)


def attitude_cascade(p: MulticopterParams, airframe: Airframe, cs: MCControlState, acc_sp, yaw_sp, quat, rate, dt,
                     armed):
  """The cascade below the velocity PID, from its output: acceleration setpoint [3] (world m/s^2, gravity excluded)
  -> attitude + collective thrust -> body rates -> torques -> rotor thrusts. The entry of controllers that act at
  the attitude loop (the prior-work baselines' `Estimator.acc_setpoint`). Returns what `mc_control` returns."""
  r_des, thrust = thrust_attitude(p, airframe.hover_thrust, acc_sp, yaw_sp)
  rate_sp = attitude_control(p, r_des, quat)
  torque, cs = rate_control(p, cs, rate_sp, rate, dt, integrate=armed)
  rotors = mix(airframe, torque, thrust)
  rotors = jnp.where(armed, rotors, 0.0)
  cs = jax_tree_where(armed, cs, cs.replace(vel_int=jnp.zeros(3), rate_int=jnp.zeros(3)))
  return cs, rotors, {"acc_sp": acc_sp, "rate_sp": rate_sp, "thrust": thrust, "torque": torque}


def jax_tree_where(cond, a, b):
  """Elementwise select between two pytrees of the same structure."""
  return jax.tree.map(lambda x, y: jnp.where(cond, x, y), a, b)
