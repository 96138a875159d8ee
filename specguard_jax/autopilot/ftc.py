"""A fault-tolerant control (FTC) stand-in at the multicopter's attitude loop (the prior-work baseline 'ftc',
specguard_jax.baselines.ftc_attitude; EnvConfig.recovery_estimator = "ftc").

What it keeps of the paper's FTC (recovery-rl, SpecGuard Sec. 2 and 5): a recovery controller switched in when an
attack is detected whose only objective is not to crash, acting on the (attacked) estimate, with no state
reconstruction and no notion of the mission's specifications. What it is here (no learning): a passive fault-tolerant
flight envelope. While the residual detector's alarm is up, in cruise and loiter, the acceleration setpoint that the
velocity PID hands the attitude loop (px4.attitude_cascade) is
  capped         horizontal |a_xy| <= acc_xy_max (4 m/s^2: ~22 deg of tilt, against the PID's 7 m/s^2 / 35 deg) and
                 vertical a_z in [-acc_z_max, acc_z_max] (thrust within ~30 % of hover),
  smoothed       a first-order low-pass with time constant tau (0.4 s),
so a corrupted estimate cannot command the large, fast tilts and thrust changes that end in a flip or a ground
strike, at the price of slower corrections (the position may drift: specs such as the geofence are not its concern).
Outside the alarm the filter state follows the PID's setpoint, so the switch is bumpless and attack-free missions fly
exactly like the autopilot.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from specguard_jax import math3d
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.estimation.estimator import Estimator


@dataclasses.dataclass(frozen=True)
class FTCConfig:
  """acc_xy_max: m/s^2 horizontal cap; acc_z_max: m/s^2 vertical cap; tau: s low-pass time constant; dt: s tick."""
  acc_xy_max: float = 4.0
  acc_z_max: float = 3.0
  tau: float = 0.4
  dt: float = 0.02


def envelope(cfg: FTCConfig, acc_prev, acc_pid):
  """The FTC's acceleration setpoint [3] (m/s^2) from its previous one and the PID's (module doc)."""
  h = math3d.norm(acc_pid[:2]) + 1e-9
  capped = jnp.concatenate([acc_pid[:2] * jnp.minimum(1.0, cfg.acc_xy_max / h),
                            jnp.clip(acc_pid[2:3], -cfg.acc_z_max, cfg.acc_z_max)])
  a = cfg.dt / (cfg.tau + cfg.dt)
  return acc_prev + a * (capped - acc_prev)


@dataclasses.dataclass(eq=False)
class FTCHook(Estimator):
  """In-tick FTC: sim['baseline'] = {'acc' [3] the envelope's last setpoint, 'active' [] bool}."""
  cfg: FTCConfig

  @classmethod
  def create(cls, env, model_path: str = ""):
    del model_path
    if env.vehicle != "drone":
      raise ValueError("recovery_estimator='ftc' acts at the multicopter's attitude loop: drone only")
    return cls(FTCConfig(dt=float(env.config.tick_dt)))

  def init(self, ekf, readings):
    del ekf, readings
    return {"acc": jnp.zeros(3), "active": jnp.zeros((), bool)}

  def acc_setpoint(self, sim, acc_sp, vel_sp, leg_vel):
    del vel_sp, leg_vel
    nav = sim["nav"]
    in_scope = (nav.phase == nav_lib.CRUISE) | (nav.phase == nav_lib.LOITER)
    active = (jnp.asarray(sim["det"].alarm) > 0) & in_scope
    acc = jnp.where(active, envelope(self.cfg, sim["baseline"]["acc"], acc_sp), acc_sp)
    return dict(sim, baseline={"acc": acc, "active": active}), acc
