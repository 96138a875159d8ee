"""Attack-free traces (recorded by `envs.record(env, keys, n_ticks, RECORD_FIELDS, ...)`) and the offline replay of
attacked sensor streams through a fresh EKF.

A trace holds, per autopilot tick k (leading axes [B, T] for a batch):
  truth: TrueState the readings of tick k measure (before that tick's physics).
  readings: SensorReadings of tick k (clean).  ekf: EKFState after fusing them (clean, what the autopilot used).
  controls: [n_u] controls applied during the PREVIOUS tick (the ones that moved truth k-1 -> k): rotor thrusts (N)
    for the drone, (throttle, steer) for the rover.  time: [] s.  phase: [] int32 navigator phase.
The vehicle is flown by its autopilot on the clean estimate; attacks are then applied offline to `readings` and
replayed (`replay_ekf`), so every estimator is scored on the same true trajectory ("open-loop" evaluation).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from specguard_jax import attacks as attacks_lib
from specguard_jax import ekf as ekf_lib


# The envs.record fields of a trace (module doc).
RECORD_FIELDS = ("truth", "readings", "ekf", "controls", "time", "phase")


def vehicle_controls(vehicle: str, sim) -> jax.Array:
  """[n_u] controls of the last applied tick from the env's sim dict: drone rotor thrusts [4] (N), rover
  (throttle, steer) [2]."""
  veh = sim["vehicle"]
  if vehicle == "drone":
    return veh["rotors"]
  return jnp.stack([veh["throttle"], veh["steer"]])


def attacked_readings(readings, schedule, times):
  """Apply an AttackSchedule to a [T] sequence of readings at times [T] (vmap over the leading axis)."""
  return jax.vmap(lambda r, t: attacks_lib.apply_attack(r, schedule, t))(readings, times)


def replay_ekf(ekf_cfg, ekf0, readings, dt):
  """Run a fresh EKF over readings [T] starting from ekf0 (the state BEFORE the first reading). Returns EKFState
  [T]."""
  def body(s, r):
    s = ekf_lib.ekf_step(ekf_cfg, s, r, dt)
    return s, s
  return jax.lax.scan(body, ekf0, readings)[1]
