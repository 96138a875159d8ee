"""Quadrotor env: Iris-class MJX free body flown by the PX4-style cascade (assets/drone.xml).

Physics per tick: rotor thrusts (actuators on sites, with yaw reaction torque) x per-episode thrust gain; linear +
quadratic aerodynamic drag on the air-relative velocity (steady wind + Ornstein-Uhlenbeck gusts) and rotational
damping as qfrc_applied; mass and inertia scaled per episode. Ground contact is analytic (landing legs): the body
cannot sink below its standing height, sits level while thrust < weight, and a touchdown faster than 2.5 m/s
vertically or 2 m/s horizontally, or any ground contact in cruise/loiter, is a crash.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco import mjx

from envs import missions as missions_lib
from envs.base import PhysicsState, RAVEnv
from specguard_jax import ekf as ekf_lib
from specguard_jax import math3d
from specguard_jax import sensors as sensors_lib
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.autopilot import px4
from specguard_jax.types import TrueState

DRAG_LIN = 0.10    # N per m/s
DRAG_QUAD = 0.025  # N per (m/s)^2 (0.5 rho Cd A, A ~ 0.04 m^2)
DRAG_ROT = 0.005   # N m per rad/s
GROUND_Z = 0.12    # body origin height when standing on the legs (m)
TILT_CRASH = 1.3   # rad (~75 deg): flipped


class DroneEnv(RAVEnv):
  vehicle = "drone"
  asset = "drone.xml"
  radius = 0.35
  attitude_loop = True

  def __init__(self, config=None, mc_params: px4.MulticopterParams | None = None, **overrides):
    super().__init__(config, **overrides)
    self.mc_params = mc_params or px4.MulticopterParams()
    self.airframe = px4.Airframe.from_mjcf(self.mj_model)

  def _default_mission_config(self):
    return missions_lib.MissionConfig.drone()

  def _default_estimation_configs(self):
    return sensors_lib.SensorConfig.drone(), ekf_lib.EKFConfig.drone()

  def _nav_params(self):
    return nav_lib.NavParams(planar=False)

  def _ground_offset(self):
    return GROUND_Z

  def _vehicle_init(self, mission, dr, key):
    wp0 = mission.waypoints[0]
    yaw0 = jnp.arctan2(wp0[1] - mission.home[1], wp0[0] - mission.home[0])
    yaw0 = yaw0 + 0.05 * jax.random.normal(key)
    pos = mission.home.at[2].set(GROUND_Z)
    quat = math3d.euler_to_quat(jnp.stack([0.0, 0.0, yaw0]))
    data = mjx.make_data(self.mjx_model)
    data = data.replace(qpos=jnp.concatenate([pos, quat]))
    truth = TrueState(pos=pos, vel=jnp.zeros(3), quat=quat, ang_vel=jnp.zeros(3), acc=jnp.zeros(3))
    return data, truth

  def _vehicle_control_init(self):
    return px4.MCControlState.zeros()

  def _vehicle_extra_init(self):
    return {"yaw_hold": jnp.zeros(()), "on_ground": jnp.ones((), bool), "hit": jnp.zeros((), bool),
            "rotors": jnp.zeros(self.airframe.n_rotors)}

  def _actuation(self, sim):
    return sim["vehicle"]["rotors"]

  def _vehicle_landed(self, sim):
    return sim["vehicle"]["on_ground"]

  def _vehicle_crashed(self, sim, signals):
    truth = sim["truth"]
    up = math3d.quat_to_rot(truth.quat)[2, 2]
    flipped = up < jnp.cos(TILT_CRASH)
    return sim["vehicle"]["hit"] | flipped

  def _vehicle_tick(self, phys, sim, mission, vel_sp, leg_dir, acc_residual=None):
    dt = self.config.tick_dt
    ekf, readings, nav, veh, dr = sim["ekf"], sim["readings"], sim["nav"], sim["vehicle"], sim["dr"]
    # ---- autopilot ----
    yaw_est = ekf_lib.ekf_euler(ekf)[2]
    cruising = (nav.phase == nav_lib.CRUISE) & (math3d.norm(leg_dir[:2]) > 0.3)
    yaw_hold = jnp.where(nav.phase == nav_lib.TAKEOFF, jnp.where(nav.time <= dt, yaw_est, veh["yaw_hold"]),
                         veh["yaw_hold"])
    yaw_sp = jnp.where(cruising, jnp.arctan2(leg_dir[1], leg_dir[0]), yaw_hold)
    armed = ~((nav.phase == nav_lib.DONE) & veh["on_ground"])
    rate_est = readings.gyro - ekf.gyro_bias
    acc_sp, ctrl = px4.velocity_control(self.mc_params, sim["ctrl"], vel_sp, ekf.vel, dt)
    if acc_residual is not None:   # SpecGuard's attitude + thrust residual (EnvConfig.override_attitude)
      acc_sp = acc_sp + acc_residual
    if self.recovery is not None:   # baseline hook (PID-Piper, FTC): the acceleration (attitude + thrust) setpoint
      sim, acc_sp = self.recovery.acc_setpoint(sim, acc_sp, vel_sp, leg_dir * mission.cruise_speed)
    ctrl, rotors, _ = px4.attitude_cascade(self.mc_params, self.airframe, ctrl, acc_sp, yaw_sp, ekf.quat, rate_est, dt,
                                           armed)
    # ---- physics ----
    thrusts = rotors * dr["thrust_gain"]
    v = phys.qvel[:3]
    v_rel = v - (dr["wind"] + sim["gust"])
    drag = -(DRAG_LIN * v_rel + DRAG_QUAD * math3d.norm(v_rel) * v_rel) * dr["drag_scale"]
    rot_drag = -DRAG_ROT * phys.qvel[3:6]
    with jax.named_scope("physics"):
      data = mjx.step(self._model(dr), self.physics_data(phys, ctrl=thrusts,
                                                         qfrc_applied=jnp.concatenate([drag, rot_drag])))
    # ---- analytic ground (landing legs) ----
    z, vz = data.qpos[2], data.qvel[2]
    below = z <= GROUND_Z
    weight = self.airframe.mass * dr["mass_scale"] * 9.81
    resting = below & (sum(thrusts[i] for i in range(thrusts.shape[0])) < weight)
    impact = below & ~veh["on_ground"] & ((vz < -2.5) | (math3d.norm(data.qvel[:2]) > 2.0))
    unplanned = below & ((nav.phase == nav_lib.CRUISE) | (nav.phase == nav_lib.LOITER))
    yaw = math3d.quat_to_euler(data.qpos[3:7])[2]
    level = math3d.euler_to_quat(jnp.stack([0.0, 0.0, yaw]))
    qpos = math3d.with_component(data.qpos, 2, jnp.maximum(z, GROUND_Z))
    qpos = jnp.where(resting, jnp.concatenate([qpos[:3], level]), qpos)
    qvel = math3d.with_component(data.qvel, 2, jnp.where(below, jnp.maximum(vz, 0.0), vz))
    qvel = jnp.where(resting, jnp.zeros(6), qvel)
    acc = jnp.where(resting, jnp.zeros(3), data.qacc[:3])
    quat = qpos[3:7]
    truth = TrueState(pos=qpos[:3], vel=qvel[:3], quat=quat, ang_vel=qvel[3:6], acc=acc)
    veh = {"yaw_hold": yaw_hold, "on_ground": below, "hit": veh["hit"] | impact | unplanned, "rotors": thrusts}
    return PhysicsState.of(data.replace(qpos=qpos, qvel=qvel)), dict(sim, truth=truth, ctrl=ctrl, vehicle=veh)
