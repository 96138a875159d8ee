"""Recovery without a learned policy: the autopilot flying on reconstructed states (DeLorean-style RC with a zero
residual) under every attack setting, per detector; the baseline a SpecGuard policy must beat.

  python experiments/recovery_modes.py --vehicle drone --missions 500 --detectors residual oracle [--json OUT]
Prints one table row per (detector, setting): SVR (any spec violated), critical, RSR (completed), crash, collision,
detected; 'none' = the autopilot alone (no detector, no reconstruction).
"""

from __future__ import annotations

import argparse
import json
import time

import jax.numpy as jnp

import envs
from specguard_jax import evaluation

WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")


def zero_policy(params, obs):
  return jnp.zeros((obs.shape[0], 3), jnp.float32)


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  ap.add_argument("--missions", type=int, default=500)
  ap.add_argument("--detectors", nargs="+", default=["none", "residual", "oracle"],
                  choices=("none", "residual", "oracle"))
  ap.add_argument("--seed", type=int, default=10_000)
  ap.add_argument("--json", default="")
  a = ap.parse_args(argv)
  out = {}
  print("| detector | setting | SVR | critical | RSR | crash | collision | detected |\n|---|---|---|---|---|---|---|---|")
  for det in a.detectors:
    kw = dict(worlds=WORLDS, override_frame="body", override_residual=True)
    if det == "none":
      env = envs.make(a.vehicle, control_mode="autopilot", **kw)
    else:
      env = envs.make(a.vehicle, control_mode="reactive", detector=det, detector_delay=0.5, reconstruction=True, **kw)
    t0 = time.time()
    res = evaluation.evaluate(env, zero_policy, None, missions=a.missions, seed=a.seed)
    wall = time.time() - t0
    for name, r in res.items():
      if name.startswith("_"):
        continue
      print(f"| {det} | {name} | {100 * r['svr']:.1f} | {100 * r['critical']:.1f} | {100 * r['rsr']:.1f} | "
            f"{100 * r['crash']:.1f} | {100 * r['collision']:.1f} | {100 * r.get('detected', float('nan')):.1f} |",
            flush=True)
    out[det] = dict(res, wall_s=wall)
  if a.json:
    with open(a.json, "w") as f:
      json.dump(out, f, indent=1)


if __name__ == "__main__":
  main()
