"""Fly missions with the autopilot alone (no attack, no recovery policy) and report outcomes.

  python -m envs.fly --vehicle drone --world urban_park --missions 256 [--seed 0] [--plot out.png] [--json]
  python -m envs.fly --vehicle drone --mission envs/data/drone_survey.plan --plot survey.png
  python -m envs.fly --vehicle rover --mission my.plan --params rover.parm --plot my.png   # your plan and parameters
  python -m envs.fly --vehicle rover --world all --missions 1000 --json     # every world preset

Missions run in parallel (vmapped, in batches of --batch) until each completes, crashes, collides, stalls or hits
its time limit. Prints completion rate, collisions, geofence entries, crashes, stalls and NaN resets (--json: one
JSON object with those keys, per world under "worlds" when several are flown).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings

import envs
from envs import mission_files
from envs import missions as missions_lib
from envs import rollout
from envs import worlds as worlds_lib
from envs.plotting import plot_mission
from specguard_jax import attacks
from specguard_jax.types import VEHICLES


def _parser():
  p = argparse.ArgumentParser(prog="python -m envs.fly", description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicle", choices=VEHICLES, default="drone")
  p.add_argument("--world", default="suburban_residential", help="world preset name, or 'all'")
  p.add_argument("--missions", type=int, default=16, help="number of missions per world (>= 1)")
  p.add_argument("--batch", type=int, default=0, help="missions per jitted batch (0: all on GPU, 64 on CPU)")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--mission", default=None,
                 help="QGroundControl mission file (.plan or QGC WPL 110) to fly, with its geoFence and rally points")
  p.add_argument("--params", default=None,
                 help="autopilot parameter file (PX4 .params or ArduPilot .parm): spec parameters, mission speed and "
                      "acceptance radius, home-centred fence (specguard_jax.specs.vehicle_params)")
  p.add_argument("--max-waypoints", type=int, default=1000,
                 help="most waypoints a --mission file may have (more is an error, never a truncation)")
  p.add_argument("--max-s", type=float, default=None,
                 help="episode cap (s; default EnvConfig.max_episode_s, 400): a long or slow plan needs more")
  p.add_argument("--max-duration", type=float, default=None,
                 help="cap on generated mission duration (s); shorter missions run faster on CPU")
  p.add_argument("--attack", default=None,
                 help="attack these sensors (comma-separated, from gps,gyro,accel,mag,baro,flow), one random attack "
                      "per mission with the paper's Table 3 biases; several names = a multi-sensor attack")
  p.add_argument("--attack-type", choices=("overt", "stealthy", "both"), default="overt")
  p.add_argument("--plot", default=None, help="write a top-down + altitude plot of the first mission to this PNG")
  p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
  return p


def make_env(vehicle: str, max_duration=None, attack=None, attack_type="overt", mission_file=None, params_file=None,
             max_waypoints: int = 1000, max_s=None):
  """The autopilot-only env used by `fly` (one per vehicle: the world is chosen per call, as data); mission_file /
  params_file: EnvConfig.mission_file / params_file (the user's plan, with its fences, and parameters)."""
  overrides = {"mission_file": mission_file or "", "params_file": params_file or "",
               "mission_max_waypoints": int(max_waypoints)}
  if max_s is not None:
    overrides["max_episode_s"] = float(max_s)
  if attack:
    names = tuple(a.strip() for a in attack.split(",") if a.strip())
    profiles = attacks.PROFILES if attack_type == "both" else (attack_type,)
    overrides["attack"] = attacks.AttackConfig(sensors=names, profiles=profiles, n_sensors=len(names))
  if max_duration is not None:
    base = missions_lib.MissionConfig.drone() if vehicle == "drone" else missions_lib.MissionConfig.rover()
    overrides["mission"] = dataclasses.replace(base, max_duration_s=float(max_duration),
                                               min_duration_s=min(base.min_duration_s, float(max_duration) / 2))
  return envs.make(vehicle, **overrides)


def fly(vehicle: str, world: str, missions: int, seed: int = 0, batch: int = 0, mission_file=None,
        max_duration=None, plot=None, env=None, params_file=None) -> dict:
  """Fly `missions` missions in `world`; returns the outcome dict printed by the CLI. Pass `env` (from make_env) to
  reuse one compiled rollout across worlds; otherwise mission_file / params_file build it (make_env)."""
  import jax
  import jax.numpy as jnp
  import numpy as np

  env = env or make_env(vehicle, max_duration, mission_file=mission_file, params_file=params_file)
  world_id = worlds_lib.PRESET_NAMES.index(world)
  if mission_file is not None and env.plan is None:
    raise ValueError("fly(mission_file=...) with an env built without it: pass make_env(..., mission_file=...)")
  if batch <= 0:
    batch = missions if jax.default_backend() != "cpu" else min(missions, 64)
  max_steps = int(env.config.max_episode_s / env.dt) + 1
  totals = {k: 0 for k in rollout.EPISODE_FLAGS + ("truncated", "unfinished", "attacked", "missions_violating")}
  totals["violations_per_spec"] = [0] * len(env.spec_names)
  times, steps_run, t0, traj0 = [], 0, time.time(), None
  first = None
  for start in range(0, missions, batch):
    n = min(batch, missions - start)
    # Distinct missions per world and per batch, reproducible from --seed.
    keys = jax.random.split(jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), world_id), start), batch)
    state, traj, t = rollout.fly_batch(env, keys, max_steps,   # the env flies its plan (EnvConfig.mission_file)
                                       world_ids=jnp.full((batch,), world_id, jnp.int32))
    jax.block_until_ready(state.done)
    state = jax.tree.map(lambda x: x[:n], state)
    s = rollout.summarize(state)
    for k in totals:
      totals[k] = [a + b for a, b in zip(totals[k], s[k])] if k == "violations_per_spec" else totals[k] + s[k]
    times += s["mission_time_s"]
    steps_run += int(t) * batch
    if first is None:
      first, traj0 = state, traj
  wall = time.time() - t0
  out = {
      "vehicle": vehicle, "world": world, "missions": missions, "seed": seed,
      "completion_rate": totals["complete"] / missions,
      "collisions": totals["collision"], "geofence_entries": totals["fence_breach"], "crashes": totals["crash"],
      "stalls": totals["stall"], "nan_resets": totals["nan"], "truncated": totals["truncated"],
      "attacked": totals["attacked"], "missions_violating": totals["missions_violating"],
      "violation_rate": totals["missions_violating"] / missions,
      "violations_per_spec": dict(zip(env.spec_names, totals["violations_per_spec"])),
      "mean_mission_time_s": float(np.mean(times)), "env_steps": steps_run,
      "waypoints": int(np.max(np.asarray(first.info["mission"].n_waypoints))),
      "control_ticks": steps_run * env.config.ticks_per_step, "wall_s": wall,
      "env_steps_per_s": steps_run / max(wall, 1e-9), "backend": jax.default_backend(),
  }
  if plot:
    one = jax.tree.map(lambda x: np.asarray(x[0]), first.info)
    tr = {k: np.asarray(v) for k, v in traj0.items()}
    tr["dt"] = env.dt
    plot_mission(plot, one["world"], one["mission"], tr,
                 title=f"{vehicle} in {world}: {'complete' if one['episode']['complete'] else 'not complete'}")
    out["plot"] = plot
  return out


def main(argv=None):
  args = _parser().parse_args(argv)
  if args.missions < 1:
    _parser().error("--missions must be >= 1")
  if args.world != "all" and args.world not in worlds_lib.PRESETS:
    _parser().error(f"unknown world {args.world!r}; choose 'all' or one of: {', '.join(worlds_lib.PRESETS)}")
  import os
  for what, path in (("mission file", args.mission), ("parameter file", args.params)):
    if path is not None and not os.path.isfile(path):
      _parser().error(f"{what} not found: {path}")
  if args.max_waypoints < 1:
    _parser().error("--max-waypoints must be >= 1")
  if args.max_s is not None and not 0 < args.max_s < float("inf"):
    _parser().error("--max-s must be a finite number of seconds > 0")
  names = list(worlds_lib.PRESETS) if args.world == "all" else [args.world]
  results = []
  try:
    with warnings.catch_warnings():   # a mission file's warning: one line on stderr
      warnings.showwarning = lambda message, *_, **__: print(f"warning: {message}", file=sys.stderr)
      if args.mission is not None:   # a bad file fails before the env is built
        mission_files.load_plan(args.mission, args.vehicle, max_waypoints=args.max_waypoints,
                                **({} if args.max_s is None else {"max_episode_s": args.max_s}))
      with warnings.catch_warnings():   # the file's notices were printed by the check above
        warnings.simplefilter("ignore", mission_files.MissionFileWarning)
        env = make_env(args.vehicle, args.max_duration, args.attack, args.attack_type, args.mission, args.params,
                       args.max_waypoints, args.max_s)
      for i, name in enumerate(names):
        results.append(fly(args.vehicle, name, args.missions, args.seed, args.batch, args.mission, args.max_duration,
                           args.plot if i == 0 else None, env=env))
  except ValueError as e:  # bad mission file, attack or config: one line, no traceback
    print(f"error: {e}", file=sys.stderr)
    return 2
  if args.json:
    print(json.dumps(results[0] if len(results) == 1 else {"worlds": results}))
    return 0
  cols = ("world", "completion_rate", "collisions", "geofence_entries", "crashes", "stalls", "nan_resets",
          "truncated", "violation_rate", "mean_mission_time_s", "env_steps", "wall_s")
  print(f"{args.vehicle}: {args.missions} missions per world, seed {args.seed}, backend {results[0]['backend']}")
  print("  ".join(f"{c:>16}" for c in cols))
  for r in results:
    print("  ".join(f"{r[c]:>16.3f}" if isinstance(r[c], float) else f"{r[c]:>16}" for c in cols))
  if args.plot:
    print(f"plot written to {args.plot}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
