"""Ground rover env: Ackermann rover on planar MJX joints (assets/rover.xml), driven by the ArduRover-style controller.

Tyre model per tick (dynamic bicycle model): rear-wheel traction = throttle x drive force x per-episode gain, bounded
by friction; lateral axle forces = cornering stiffness x slip angle, saturated at mu x axle load (mu randomised per
episode); rolling resistance and aerodynamic drag. Slip angles use max(|u|, 2 m/s) in the denominator so the explicit
50 Hz integration stays stable at low speed (tyres are softer than real there; the rover never skids at those speeds).
Forces are applied as generalised forces on the slide/slide/hinge joints; the steering servo is rate-limited.
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
from specguard_jax.autopilot import ardurover
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.types import TrueState

BODY_Z = 0.2          # body origin height (m)
CG_FRONT = 0.275      # CoG to front axle (m)
CG_REAR = 0.275       # CoG to rear axle (m)
CORNERING = 150.0     # N/rad per axle
MU = 0.9              # tyre-road friction (nominal)
STEER_RATE = 3.0      # rad/s servo slew


class RoverEnv(RAVEnv):
  vehicle = "rover"
  asset = "rover.xml"
  radius = 0.45

  def __init__(self, config=None, rover_params: ardurover.RoverParams | None = None, **overrides):
    super().__init__(config, **overrides)
    self.rover_params = rover_params or ardurover.RoverParams()
    self.mass = float(self.mj_model.body_mass[1])

  def _default_mission_config(self):
    return missions_lib.MissionConfig.rover()

  def _default_estimation_configs(self):
    return sensors_lib.SensorConfig.rover(), ekf_lib.EKFConfig.rover()

  def _nav_params(self):
    return nav_lib.NavParams(planar=True, acc_brake=2.0, acc_turn=3.0)

  def _query_pos(self, pos):
    return math3d.with_component(pos, 2, 0.0)

  def _ground_offset(self):
    return BODY_Z

  def _vehicle_init(self, mission, dr, key):
    wp0 = mission.waypoints[0]
    yaw0 = jnp.arctan2(wp0[1] - mission.home[1], wp0[0] - mission.home[0])
    data = mjx.make_data(self.mjx_model)
    data = data.replace(qpos=jnp.stack([mission.home[0], mission.home[1], yaw0]))
    truth = self._truth(data.qpos, jnp.zeros(3), jnp.zeros(3))
    return data, truth

  def _truth(self, qpos, qvel, qacc):
    pos = jnp.stack([qpos[0], qpos[1], BODY_Z])
    quat = math3d.euler_to_quat(jnp.stack([0.0, 0.0, qpos[2]]))
    return TrueState(pos=pos, vel=jnp.stack([qvel[0], qvel[1], 0.0]), quat=quat,
                     ang_vel=jnp.stack([0.0, 0.0, qvel[2]]), acc=jnp.stack([qacc[0], qacc[1], 0.0]))

  def _actuation(self, sim):
    return jnp.stack([sim["vehicle"]["steer"], sim["vehicle"]["throttle"]])

  def _vehicle_control_init(self):
    return ardurover.RoverControlState.zeros()

  def _vehicle_extra_init(self):
    return {"steer": jnp.zeros(()), "throttle": jnp.zeros(())}

  def _vehicle_tick(self, phys, sim, mission, vel_sp, leg_dir, acc_residual=None):
    del acc_residual   # no attitude loop (RAVEnv.attitude_loop False: override_attitude is refused)
    dt = self.config.tick_dt
    p = self.rover_params
    ekf, veh, dr = sim["ekf"], sim["vehicle"], sim["dr"]
    yaw_est = ekf_lib.ekf_euler(ekf)[2]
    speed_est = ekf_lib.ekf_body_velocity(ekf)[0]
    ctrl, throttle, steer_cmd = ardurover.rover_control(p, sim["ctrl"], vel_sp, yaw_est, speed_est, dt,
                                                        armed=jnp.ones((), bool))
    steer = veh["steer"] + jnp.clip(steer_cmd - veh["steer"], -STEER_RATE * dt, STEER_RATE * dt)
    # ---- tyre forces (body frame) ----
    yaw = phys.qpos[2]
    vx, vy, r = phys.qvel[0], phys.qvel[1], phys.qvel[2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    u = c * vx + s * vy
    v = -s * vx + c * vy
    mass = self.mass * dr["mass_scale"]
    mu = MU * dr["friction"]
    n_axle = 0.5 * mass * 9.81
    u_den = jnp.maximum(jnp.abs(u), 2.0)
    sgn = jnp.where(u >= 0, 1.0, -1.0)
    alpha_f = steer * sgn - jnp.arctan2(v + CG_FRONT * r, u_den)
    alpha_r = -jnp.arctan2(v - CG_REAR * r, u_den)
    fy_f = jnp.clip(CORNERING * alpha_f, -mu * n_axle, mu * n_axle)
    fy_r = jnp.clip(CORNERING * alpha_r, -mu * n_axle, mu * n_axle)
    fx = jnp.clip(throttle * p.drive_force * dr["thrust_gain"], -mu * n_axle, mu * n_axle)
    resist = -(p.rolling * u + p.drag * dr["drag_scale"] * u * jnp.abs(u))
    fxb = fx - fy_f * jnp.sin(steer) + resist
    fyb = fy_f * jnp.cos(steer) + fy_r
    mz = CG_FRONT * fy_f * jnp.cos(steer) - CG_REAR * fy_r
    qfrc = jnp.stack([c * fxb - s * fyb, s * fxb + c * fyb, mz])
    with jax.named_scope("physics"):
      data = mjx.step(self._model(dr), self.physics_data(phys, qfrc_applied=qfrc))
    truth = self._truth(data.qpos, data.qvel, data.qacc)
    veh = {"steer": steer, "throttle": throttle}
    return PhysicsState.of(data), dict(sim, truth=truth, ctrl=ctrl, vehicle=veh)
