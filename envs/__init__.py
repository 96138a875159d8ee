"""Vehicles, worlds and missions as MJX envs.

`envs.make(vehicle, world=..., **EnvConfig fields)` returns a brax Env; `envs.record(env, keys, n_ticks, fields)`
flies a batch through the env's autopilot ticks and records chosen fields; `envs.fly_batch` flies a batch of
episodes under a policy (envs/rollout.py).
"""

from __future__ import annotations

import dataclasses

# First: mujoco.mjx without its notices about the absent optional Warp backend (stdout stays clean for the CLIs'
# --json output).
from specguard_jax import third_party  # noqa: F401,I001

from envs.base import EnvConfig  # noqa: E402
from envs.drone import DroneEnv  # noqa: E402
from envs.rollout import fly_batch, record  # noqa: E402,F401
from envs.rover import RoverEnv  # noqa: E402

from specguard_jax.types import VEHICLES  # noqa: E402
_ENVS = {"drone": DroneEnv, "rover": RoverEnv}


def make(vehicle: str, world: str = "suburban_residential", **overrides):
  """Build the env of `vehicle` ('drone' | 'rover') in world preset `world`.

  `overrides` are fields of envs.base.EnvConfig (e.g. control_mode='override', ticks_per_step=5, mission=...).
  Raises ValueError with one line naming the problem for an unknown vehicle, world or field.
  """
  if vehicle not in VEHICLES:
    raise ValueError(f"unknown vehicle {vehicle!r}; choose one of {', '.join(VEHICLES)}")
  fields = {f.name for f in dataclasses.fields(EnvConfig)}
  bad = sorted(set(overrides) - fields)
  if bad:
    raise ValueError(f"unknown env option(s) {', '.join(bad)}; valid: {', '.join(sorted(fields))}")
  return _ENVS[vehicle](EnvConfig(world=world, **overrides))
