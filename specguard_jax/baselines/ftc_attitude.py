"""FTC baseline 'ftc': a fault-tolerant flight envelope at the multicopter's attitude loop, switched in by the
residual detector (specguard_jax.autopilot.ftc; EnvConfig.recovery_estimator='ftc'). No training; drone only. The
RL policy that acted through the velocity setpoint is 'ftc_rl' (baselines/ftc.py).
"""

from __future__ import annotations

from specguard_jax import controllers

ENV_OVERRIDES = (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
                 ("reconstruction", False), ("recovery_estimator", "ftc"))


def build(ctx):
  """Controller 'ftc' (nothing to train)."""
  if ctx.vehicle != "drone":
    raise controllers.NotAvailable("FTC acts at the multicopter's attitude loop: drone only")
  return controllers.Controller("ftc", ENV_OVERRIDES, controllers.zero_policy, None,
                                "FTC: while the alarm is up, the attitude loop flies a capped, smoothed acceleration "
                                "setpoint (bounded tilt and thrust); no reconstruction, no specs")
