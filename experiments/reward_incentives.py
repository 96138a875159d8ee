"""What each spec's reward term pays for compliant flight: attack-free missions flown by the autopilot alone, the
per-step reward of every spec averaged per mission phase, for each reward (`EnvConfig.reward`).

  python experiments/reward_incentives.py [--vehicle drone] [--missions 16] [--rewards compliance,capped,binary]
                                          [--json OUT]

Every mission here is compliant or nearly so, so any term below 1 pays for something other than compliance: the
policy can earn it by flying differently while staying compliant (more clearance, hurrying to a waypoint). The
trainer's completion bonus is worth 1 per step (ppo.config.TrainConfig.completion_bonus), so a phase whose mean total
is r < 1 makes each step saved there worth about 1 - r: an incentive to hurry that a spec violation must outweigh
(at most 1/n per step for one of the n weighted specs, normalised). docs/DESIGN.md "Reward incentives" reads it.
"""

import argparse
import json


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--missions", type=int, default=16)
  p.add_argument("--rewards", default="compliance,capped,binary")
  p.add_argument("--mission-s", type=float, default=100.0, help="longest generated mission (s, nominal)")
  p.add_argument("--max-s", type=float, default=200.0, help="flight time recorded per mission (s)")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--json", default=None)
  a = p.parse_args(argv)
  from specguard_jax.types import REWARDS
  rewards = [r.strip() for r in a.rewards.split(",") if r.strip()]
  bad = [r for r in rewards if r not in REWARDS or r == "survival"]
  if bad or not rewards:
    p.error(f"--rewards: unknown or spec-free reward(s) {', '.join(bad)}; choose from compliance, capped, binary")
  if a.missions < 1 or a.max_s <= 0 or a.mission_s <= 0:
    p.error("--missions must be >= 1, --mission-s and --max-s > 0")
  import jax
  import jax.numpy as jnp
  import numpy as np

  import dataclasses

  import envs
  from envs import missions as missions_lib
  from specguard_jax.autopilot.navigator import PHASE_NAMES

  base = missions_lib.MissionConfig.drone() if a.vehicle == "drone" else missions_lib.MissionConfig.rover()
  mission = dataclasses.replace(base, max_duration_s=a.mission_s, min_duration_s=min(base.min_duration_s,
                                                                                     a.mission_s / 2))
  env = envs.make(a.vehicle, reward=rewards[0], max_episode_s=a.max_s, mission=mission)
  steps = int(round(a.max_s / env.dt))
  keys = jax.random.split(jax.random.PRNGKey(a.seed), a.missions)
  weights = np.asarray(env.reward_fn.weights(env.config.critical_weight)) > 0

  @jax.jit
  def fly(keys):
    """Per step: signals and phase of every mission, and whether it still flies ([T, B] each)."""
    s = jax.vmap(env.reset)(keys)

    def body(s, _):
      n = jax.vmap(env.step)(s, jnp.zeros((a.missions, env.action_size)))
      keep = lambda x, y: jnp.where(s.done.reshape((-1,) + (1,) * (x.ndim - 1)) > 0, x, y)   # noqa: E731
      return jax.tree.map(keep, s, n), (n.info["signals"], s.info["sim"]["nav"].phase, s.done == 0)

    return jax.lax.scan(body, s, None, steps)[1]

  signals, phase, live = fly(keys)
  phase, live = np.asarray(phase), np.asarray(live)
  out = {"vehicle": a.vehicle, "missions": a.missions, "seed": a.seed, "specs": list(env.spec_names),
         "weighted": [n for n, w in zip(env.spec_names, weights) if w], "rewards": {}}
  for r in rewards:
    per = np.asarray(jax.jit(jax.vmap(jax.vmap(lambda sig: env.reward_fn.per_spec(
        sig, binary=r == "binary", capped=r == "capped"))))(signals))   # [T, B, n]
    rows = {}
    for k, name in enumerate(PHASE_NAMES[:-1]):
      m = live & (phase == k)
      if m.any():
        spec = per[m].mean(0)
        rows[name] = {"steps": int(m.sum()), "total": float(spec[weights].mean()),
                      "per_spec": {n: round(float(v), 4) for n, v, w in zip(env.spec_names, spec, weights) if w}}
    out["rewards"][r] = rows
  print(f"{a.vehicle}, {a.missions} attack-free autopilot missions: mean per-step reward per phase (1 = the maximum)")
  for r, rows in out["rewards"].items():
    print(f"\nreward {r}")
    names = out["weighted"]
    print("| phase | steps | total | " + " | ".join(names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for ph, v in rows.items():
      print(f"| {ph} | {v['steps']} | {v['total']:.3f} | " + " | ".join(f"{v['per_spec'][n]:.2f}" for n in names)
            + " |")
  if a.json:
    with open(a.json, "w") as f:
      json.dump(out, f, indent=1)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
