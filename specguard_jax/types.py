"""Pytrees shared between the simulator, sensors, EKF, attacks and policies.

Frames and units (everywhere in the project):
  * world frame ENU: x east, y north, z up (metres); ground plane at z = 0.
  * body frame FLU: x forward, y left, z up.
  * quaternions are MuJoCo's (w, x, y, z), rotating body -> world.
  * Euler angles are (roll, pitch, yaw), intrinsic Z-Y-X; yaw is measured from +x (east) counter-clockwise, radians.
  * time in seconds, speeds in m/s, angular rates in rad/s, accelerations in m/s^2.
All arrays below are per vehicle; a batch of vehicles adds leading axes (vmap).
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class TrueState:
  """Ground-truth kinematic state of one vehicle, from the physics.

  pos: [3] world position (m).  vel: [3] world velocity (m/s).  quat: [4] attitude (w, x, y, z).
  ang_vel: [3] body-frame angular velocity (rad/s).  acc: [3] world-frame linear acceleration (m/s^2),
  *without* gravity (so a hovering vehicle has acc = 0; the accelerometer measures R^T (acc - g)).
  """

  pos: jnp.ndarray
  vel: jnp.ndarray
  quat: jnp.ndarray
  ang_vel: jnp.ndarray
  acc: jnp.ndarray


@struct.dataclass
class SensorReadings:
  """What the sensors deliver to the autopilot at one control tick (before the EKF).

  A sensor that updates slower than the tick holds its last sample; its `*_fresh` flag is 1.0 only on the tick a new
  sample arrives, and the EKF fuses only fresh samples. Attacks (issue 4) add biases to these fields.

  gps_pos: [3] world position (m).  gps_vel: [3] world velocity (m/s).  gps_fresh: [] 0/1.
  gyro: [3] body angular rate (rad/s).  accel: [3] body specific force (m/s^2), = R^T (acc - g), g = (0, 0, -9.81).
  mag_yaw: [] magnetic heading as yaw (rad, same convention as Euler yaw).  mag_fresh: [] 0/1.
  baro_alt: [] barometric altitude above the ground plane (m).  baro_fresh: [] 0/1.
  flow: [2] optical-flow rate about body x/y (rad/s) = horizontal body velocity / height above ground (drone only;
    zeros and flow_fresh = 0 on vehicles without the sensor).  flow_fresh: [] 0/1.
  odom_speed: [] wheel-odometry forward speed (m/s) (rover only; zero otherwise).  odom_fresh: [] 0/1.
  """

  gps_pos: jnp.ndarray
  gps_vel: jnp.ndarray
  gps_fresh: jnp.ndarray
  gyro: jnp.ndarray
  accel: jnp.ndarray
  mag_yaw: jnp.ndarray
  mag_fresh: jnp.ndarray
  baro_alt: jnp.ndarray
  baro_fresh: jnp.ndarray
  flow: jnp.ndarray
  flow_fresh: jnp.ndarray
  odom_speed: jnp.ndarray
  odom_fresh: jnp.ndarray


# Names of the physical sensors (attack targets, diagnosis labels). Order is part of the API (integer sensor ids).
SENSOR_NAMES = ("gps", "gyro", "accel", "mag", "baro", "flow")

# Names the envs, the trainer and the CLIs share (defined here, a module without heavy imports, so that the CLIs'
# argparse choices need not import the simulator): envs.VEHICLES, envs.base.CONTROL_MODES / DETECTORS / REWARDS
# re-export them.
VEHICLES = ("drone", "rover")
EKF_KERNELS = ("auto", "xla", "lanes")                  # EnvConfig.ekf_kernel (ekf_lanes.resolve_ekf_kernel)
CONTROL_MODES = ("autopilot", "override", "reactive")   # envs.base.EnvConfig.control_mode
DETECTORS = ("none", "residual", "oracle", "mixed")     # envs.base.EnvConfig.detector
RESIDUAL_DETECTORS = ("residual", "mixed")               # detectors that run the residual detector every tick
RECON_MODES = ("fused", "paper", "oracle")               # EnvConfig.recon_mode (estimation.recon.ReconConfig.mode)
REWARDS = ("compliance", "capped", "binary", "survival")   # rewards.reward; survival: the FTC baseline's (baselines.ftc)
VARIANTS = ("rc", "pc")                                  # ppo.config.TrainConfig.variant (RC / PC SpecGuard)
TRAIN_DETECTORS = tuple(d for d in DETECTORS if d != "none")   # a training run's phase-2 and held-out detectors
