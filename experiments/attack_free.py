"""Attack-free missions flown by the autopilot alone, drawn exactly as the held-out evaluation draws them
(specguard_jax.evaluation: seed 10,000, mission j from fold_in(key, j), world uniform over --worlds): per-spec
violations (the attack-free SVR the issue asks to be 0 %), completion, RSR, crashes, collisions.

  python experiments/attack_free.py --missions 1000 [--vehicle drone] [--worlds train|all|a,b] [--detector residual]
                              [--json OUT]

--worlds train (default) = the trainer's default worlds (the held-out evaluation's); all = the 10 presets.
--detector residual: the deployment env of SpecGuard-RC (residual detector, reconstruction, reactive switch) with a
zero policy, to count false alarms and what they cost; default: the autopilot alone.
"""

import argparse
import json
import sys
import time


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--missions", type=int, default=1000)
  p.add_argument("--worlds", default="train")
  p.add_argument("--seed", type=int, default=10_000)
  p.add_argument("--detector", default="none", choices=("none", "residual"))
  p.add_argument("--json", default=None)
  a = p.parse_args(argv)
  if a.missions < 1:
    p.error("--missions must be >= 1")
  import jax
  import jax.numpy as jnp
  import numpy as np

  from envs import worlds as worlds_lib
  from specguard_jax import evaluation as E
  from specguard_jax.ppo.config import TrainConfig
  worlds = {"train": tuple(TrainConfig().env.worlds), "all": worlds_lib.PRESET_NAMES}.get(a.worlds)
  worlds = worlds or tuple(w.strip() for w in a.worlds.split(","))
  bad = [w for w in worlds if w not in worlds_lib.PRESETS]
  if bad:
    p.error(f"unknown world(s) {', '.join(bad)}; choose from {', '.join(worlds_lib.PRESETS)}")
  ov = {"worlds": worlds}
  if a.detector != "none":
    ov.update(control_mode="reactive", detector=a.detector, reconstruction=True, override_frame="body",
              override_residual=True)
  env = E.make_env(a.vehicle, **ov)
  zero = lambda params, obs: jnp.zeros(obs.shape[:-1] + (3,))   # noqa: E731
  timing = {}
  rec, _, steps = E.rollout(env, zero, {}, (E.setting(None),), missions=a.missions, seed=a.seed, timing=timing,
                            cache=False)
  from specguard_jax import metrics
  v = rec["violated"]
  rec_ok = metrics.recovered(rec)
  fail = v.any(-1) | rec["crash"] | rec["collision"] | rec["nan"]
  out = {"vehicle": a.vehicle, "missions": a.missions, "seed": a.seed, "worlds": list(worlds), "detector": a.detector,
         "violating": int(v.any(-1).sum()), "failed": int(fail.sum()), "svr": float(fail.mean()),
         "violations_per_spec": {n: int(x) for n, x in zip(env.spec_names, v.sum(0))},
         "complete": int(rec["complete"].sum()), "recovered": int(rec_ok.sum()), "rsr": float(rec_ok.mean()),
         "crash": int(rec["crash"].sum()),
         "collision": int(rec["collision"].sum()), "stall": int(rec["stall"].sum()),
         "unfinished": int(rec["unfinished"].sum()), "false_alarms": int(rec["detected"].sum()),
         "per_world": {}, "mean_mission_s": float(np.mean(rec["t_end"])), "steps": steps,
         "compile_s": timing["compile_s"], "run_s": timing["run_s"], "device": str(jax.devices()[0])}
  for i, w in enumerate(worlds):
    m = rec["world"] == worlds_lib.PRESET_NAMES.index(w)
    out["per_world"][w] = {"missions": int(m.sum()), "failed": int(fail[m].sum()),
                           "violations_per_spec": {n: int(x) for n, x in zip(env.spec_names, v[m].sum(0)) if x}}
  print(f"{a.vehicle} attack-free, {a.missions} missions (seed {a.seed}, worlds {a.worlds}, detector {a.detector}) "
        f"on {out['device']}: failed {out['failed']} ({100 * out['svr']:.2f} %), per spec "
        f"{ {k: x for k, x in out['violations_per_spec'].items() if x} }, complete {out['complete']}, "
        f"RSR {100 * out['rsr']:.1f} % (within {metrics.RSR_RADIUS_M:g} m of the last waypoint), "
        f"crash {out['crash']}, collision {out['collision']}, stall {out['stall']}, false alarms "
        f"{out['false_alarms']}; compile {out['compile_s']:.1f} s, flight {out['run_s']:.1f} s")
  for w, r in out["per_world"].items():
    print(f"  {w:<22} {r['missions']:5d} missions, failed {r['failed']}  {r['violations_per_spec']}")
  if a.json:
    with open(a.json, "w") as fh:
      json.dump(out, fh, indent=1)
  return 0


if __name__ == "__main__":
  sys.exit(main())
