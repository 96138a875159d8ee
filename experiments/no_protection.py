"""The "No protection" column: the autopilot alone under overt / stealthy attacks on each sensor.

  python experiments/no_protection.py --vehicle drone --missions 1000 [--seed 0] [--json OUT]

For each attacked sensor (Table 3) and profile, `--missions` generated missions spread over the 10 worlds fly with
one random attack each (paper Table 3 bias ranges, onset 15-50 % into the mission, 15-40 s long). Reports the share
of missions that violate any spec (whole-episode STL verdict over the flown part), a critical spec (S1, S2, S12),
collisions, crashes (ground impact or flip: the episode ends, often before a spec is violated), completion, and
`failed` = any spec violated or crash or collision. The env is compiled once per vehicle: missions, worlds and attacks are data.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--missions", type=int, default=1000)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--json", default=None)
  p.add_argument("--sensors", default=None, help="comma-separated subset of sensors (default: all)")
  p.add_argument("--profiles", default="overt,stealthy")
  a = p.parse_args()
  import envs
  from envs import missions as missions_lib
  from envs import rollout
  from envs import worlds
  from specguard_jax import attacks
  env = envs.make(a.vehicle)
  sensors = [s for s in attacks.SENSOR_NAMES if not (a.vehicle == "rover" and s == "flow")]
  if a.sensors:
    sensors = [s for s in sensors if s in a.sensors.split(",")]
  crit = np.asarray(env.spec_table.critical)
  n = a.missions
  max_steps = int(env.config.max_episode_s / env.dt) + 1
  rows = []
  print(f"{a.vehicle}, {n} missions per setting over {len(worlds.PRESET_NAMES)} worlds, "
        f"{jax.devices()[0].device_kind}")
  print(f"{'sensor':6s} {'type':9s} {'violating':>9s} {'critical':>9s} {'collision':>9s} {'crash':>6s} "
        f"{'complete':>9s} {'failed':>7s} {'wall s':>7s}")
  for profile in a.profiles.split(","):
    for sensor in sensors:
      setting = attacks.SENSOR_NAMES.index(sensor) * 2 + attacks.PROFILES.index(profile)
      key = jax.random.fold_in(jax.random.PRNGKey(a.seed), setting)
      k_m, k_a, k_r = jax.random.split(key, 3)
      ms = jax.vmap(lambda k: missions_lib.generate_mission(env.mission_cfg, k))(jax.random.split(k_m, n))
      cfg = attacks.AttackConfig(sensors=(sensor,), profiles=(profile,))
      att = jax.vmap(lambda k, d: attacks.sample_attack(cfg, k, d))(jax.random.split(k_a, n), ms.nominal_duration)
      wid = jnp.arange(n, dtype=jnp.int32) % len(worlds.PRESET_NAMES)
      t0 = time.time()
      state, _, _ = rollout.fly_batch(env, jax.random.split(k_r, n), max_steps, missions=ms, world_ids=wid,
                                      attacks=att)
      rob = np.asarray(state.info["spec_robustness"])
      ep = jax.tree.map(np.asarray, state.info["episode"])
      r = {"sensor": sensor, "profile": profile, "missions": n,
           "violating": float(np.mean(np.any(rob < 0, -1))), "critical": float(np.mean(np.any(rob[:, crit] < 0, -1))),
           "collision": float(np.mean(ep["collision"] > 0)), "crash": float(np.mean(ep["crash"] > 0)),
           "complete": float(np.mean(ep["complete"] > 0)),
           "failed": float(np.mean(np.any(rob < 0, -1) | (ep["crash"] > 0) | (ep["collision"] > 0))),
           "per_spec": dict(zip(env.spec_names, np.mean(rob < 0, 0).round(4).tolist())),
           "wall_s": time.time() - t0}
      rows.append(r)
      print(f"{sensor:6s} {profile:9s} {100 * r['violating']:8.1f}% {100 * r['critical']:8.1f}% "
            f"{100 * r['collision']:8.1f}% {100 * r['crash']:5.1f}% {100 * r['complete']:8.1f}% "
            f"{100 * r['failed']:6.1f}% {r['wall_s']:7.1f}",
            flush=True)
  if a.json:
    with open(a.json, "w") as f:
      json.dump({"vehicle": a.vehicle, "device": jax.devices()[0].device_kind, "rows": rows}, f, indent=1)


if __name__ == "__main__":
  main()
