"""In-tick estimators of the prior-work baselines, called by the env's autopilot tick (envs/base.py `_tick`).

EnvConfig.recovery_estimator picks one ('software_sensors': SSR, 'dae': the state-level denoising autoencoder,
'imu_denoise': UnRocker, 'ffc': PID-Piper, 'ftc': FTC); the env builds it once with
`make(env, name, model_path)` and calls, every tick (pure JAX, jittable, vmappable):
  state = est.init(ekf, readings)                      at reset (kept in sim['baseline'])
  sim, readings_for_ekf = est.pre_ekf(sim, readings)   before the autopilot's EKF fuses this tick's readings
  sim, estimate = est.post_ekf(sim, ekf, readings)     the estimate the navigator and autopilot fly on
  sim, acc_sp = est.acc_setpoint(sim, acc_sp, vel_sp, leg_vel)
                                                       the acceleration setpoint of the multicopter's attitude loop
All see sim['det'] (the detector's alarm and diagnosis mask of the PREVIOUS tick: the detector runs after the EKF).
"""

from __future__ import annotations

from specguard_jax.autopilot import ftc
from specguard_jax.estimation import dae
from specguard_jax.estimation import ffc
from specguard_jax.estimation import imu_denoise
from specguard_jax.estimation import software_sensors
from specguard_jax.estimation.estimator import Estimator


def make(env, name: str, model_path: str = "") -> Estimator:
  """The estimator `name` for `env` (an envs.base.RAVEnv being constructed); one-line ValueError on a bad model file."""
  if name == "software_sensors":
    return software_sensors.SoftwareSensors.create(env, model_path)
  if name == "dae":
    return dae.DAEEstimator.create(env, model_path)
  if name == "imu_denoise":
    return imu_denoise.IMUDenoiser.create(env, model_path)
  if name == "ffc":
    return ffc.FFCHook.create(env, model_path)
  if name == "ftc":
    return ftc.FTCHook.create(env, model_path)
  raise ValueError(f"unknown recovery estimator {name!r}; choose software_sensors, dae, imu_denoise, ffc or ftc")
