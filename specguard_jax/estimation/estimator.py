"""The interface of an in-tick recovery hook (the prior-work baselines' SSR, UnRocker, PID-Piper and FTC hooks,
estimation.hooks).

Subclasses override what they change; the defaults pass readings and estimate through.
"""

from __future__ import annotations


class Estimator:
  """Identity hooks; subclasses override what they change."""

  def init(self, ekf, readings):
    raise NotImplementedError

  def pre_ekf(self, sim, readings):
    return sim, readings

  def post_ekf(self, sim, est, readings):
    del readings
    return sim, est

  def acc_setpoint(self, sim, acc_sp, vel_sp, leg_vel):
    """The acceleration setpoint [3] (world m/s^2, gravity excluded) the multicopter's attitude loop flies, given the
    velocity PID's acc_sp, the velocity setpoint vel_sp [3] m/s it tracked (the navigator's, from the estimate) and
    the plan's leg velocity leg_vel [3] m/s (the active leg's direction x the mission's cruise speed: waypoints only,
    no estimate) (envs/drone.py; rovers never call it)."""
    del vel_sp, leg_vel
    return sim, acc_sp
