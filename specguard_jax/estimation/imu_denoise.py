"""UnRocker-style temporal denoising of the IMU readings before the estimator (the prior-work baseline 'unrocker',
specguard_jax.baselines.unrocker; EnvConfig.recovery_estimator = "imu_denoise").

UnRocker corrects inertial-sensor readings corrupted by injection (acoustic resonance of MEMS gyroscopes and
accelerometers: large, fast, oscillating or impulsive errors) over a time window and leaves the original estimator
and controller in charge. Here: a Hampel filter per axis of the gyroscope [3] (rad/s) and the accelerometer [3]
(m/s^2) over the last `window` ticks (the current one included): a sample farther than k MADs (median absolute
deviation, scaled by 1.4826 to a Gaussian sigma, with a floor) from the window's median is replaced by the median;
other samples pass unchanged (no lag on clean data). Active while the residual detector's alarm is up (the window is
kept filled always, so it is ready at the switch); otherwise the EKF fuses the raw readings, so attack-free missions
fly exactly like the autopilot. What it cannot do: remove a constant bias (after about half a window the median
itself carries it); it only delays a step by ~window/2 ticks, and it does not touch the other sensors.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from specguard_jax.estimation.estimator import Estimator


@dataclasses.dataclass(frozen=True)
class DenoiseConfig:
  """window: ticks (0.18 s at 50 Hz); k: outlier threshold in scaled MADs; floor: [gyro rad/s, accel m/s^2] least
  scale (the sensors' white noise is ~0.005 rad/s and ~0.05 m/s^2: a quiet window must not flag ordinary noise)."""
  window: int = 9
  k: float = 3.0
  floor: tuple = (0.02, 0.2)


def hampel(cfg: DenoiseConfig, window):
  """window [W, 6] (gyro xyz, accel xyz; oldest first, current last) -> denoised current sample [6]."""
  med = jnp.median(window, 0)
  mad = 1.4826 * jnp.median(jnp.abs(window - med), 0)
  floor = jnp.repeat(jnp.asarray(cfg.floor, jnp.float32), 3)
  x = window[-1]
  return jnp.where(jnp.abs(x - med) > cfg.k * jnp.maximum(mad, floor), med, x)


@dataclasses.dataclass(eq=False)
class IMUDenoiser(Estimator):
  """In-tick UnRocker: sim['baseline'] = {'window' [W, 6] raw IMU samples, 'filled' [] bool}."""
  cfg: DenoiseConfig

  @classmethod
  def create(cls, env, model_path: str = ""):
    del env, model_path
    return cls(DenoiseConfig())

  def init(self, ekf, readings):
    del ekf, readings
    return {"window": jnp.zeros((self.cfg.window, 6)), "filled": jnp.zeros((), bool)}

  def pre_ekf(self, sim, readings):
    st = sim["baseline"]
    x = jnp.concatenate([readings.gyro, readings.accel])
    window = jnp.where(st["filled"], jnp.concatenate([st["window"][1:], x[None]]),
                       jnp.broadcast_to(x, st["window"].shape))
    y = hampel(self.cfg, jnp.nan_to_num(window))
    alarm = jnp.asarray(sim["det"].alarm) > 0
    rd = readings.replace(gyro=jnp.where(alarm, y[:3], readings.gyro), accel=jnp.where(alarm, y[3:], readings.accel))
    return dict(sim, baseline={"window": window, "filled": jnp.ones((), bool)}), rd
