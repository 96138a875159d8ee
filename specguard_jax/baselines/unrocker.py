"""UnRocker baseline: temporal denoising of the IMU readings before the original estimator and controller.

specguard_jax.estimation.imu_denoise (EnvConfig.recovery_estimator='imu_denoise'): while the residual detector's alarm
is up, a Hampel filter over the last ticks of gyroscope and accelerometer samples replaces outlying samples by the
window's median before the autopilot's EKF fuses them; everything else is the autopilot's. No training (a filter),
so nothing is cached.
"""

from __future__ import annotations

from specguard_jax import controllers

ENV_OVERRIDES = (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
                 ("reconstruction", False), ("recovery_estimator", "imu_denoise"))


def build(ctx):
  """Controller 'unrocker' (nothing to train)."""
  del ctx
  return controllers.Controller("unrocker", ENV_OVERRIDES, controllers.zero_policy, None,
                                "UnRocker: while the alarm is up the EKF fuses IMU readings denoised over a time "
                                "window (Hampel filter); original estimator and controller")
