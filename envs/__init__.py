"""Vehicles, worlds and missions. `envs.make(vehicle, world=..., **overrides)` returns a brax Env."""

from __future__ import annotations

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
  # MJX prints "Failed to import warp" on stdout when its optional Warp backend is absent; keep stdout clean for
  # the CLIs' --json output.
  from mujoco import mjx as _mjx  # noqa: F401

from specguard_jax.types import VEHICLES  # noqa: E402


def make(vehicle: str, world: str = "suburban_residential", **overrides):
  """Build the env of `vehicle` ('drone' | 'rover') in world preset `world`.

  `overrides` are fields of envs.base.EnvConfig (e.g. control_mode='override', ticks_per_step=5, mission=...).
  Raises ValueError with one line naming the problem for an unknown vehicle, world or field.
  """
  import dataclasses

  from envs.base import EnvConfig
  if vehicle not in VEHICLES:
    raise ValueError(f"unknown vehicle {vehicle!r}; choose one of {', '.join(VEHICLES)}")
  fields = {f.name for f in dataclasses.fields(EnvConfig)}
  bad = sorted(set(overrides) - fields)
  if bad:
    raise ValueError(f"unknown env option(s) {', '.join(bad)}; valid: {', '.join(sorted(fields))}")
  config = EnvConfig(world=world, **overrides)
  if vehicle == "drone":
    from envs.drone import DroneEnv
    return DroneEnv(config)
  from envs.rover import RoverEnv
  return RoverEnv(config)
