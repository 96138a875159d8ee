"""Build (train/fit) the prior-work baselines at a budget into a cache dir and time each step; prints one JSON object.

  python experiments/build_baselines.py --budget full --out runs/default/eval/baselines    # GPU, before evaluate.py
  JAX_PLATFORMS=cpu python experiments/build_baselines.py --budget ci --out /tmp/bl --only ssr,unrocker_dae,pid_piper

The cache names are <name>_<vehicle>_<budget>_s<seed>_w<worlds tag> (specguard_jax.baselines.common.cache_path):
evaluate.py reuses them when --out here is <evaluate --out>/baselines, --seed is evaluate.py's --seed (default 10000
for both) and --worlds its worlds (a --run's training worlds; with other worlds it builds its own).
Walls (and this process's CPU seconds, the fairer figure on a shared CPU): 'flights' = the attack-free recording SSR, UnRocker and PID-Piper share (timed alone first, compile
included), then each builder (compiles included; a cached baseline only loads). Per baseline the cache's meta
(fit losses, held-out errors, pairs) and, for FTC, the run's summary and return curve are reported.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from specguard_jax.baselines import TRAINED as NAMES  # noqa: E402  (the baselines that train; unrocker, ftc: rules)


def _fail(msg: str):
  print(f"build_baselines.py: error: {msg}", file=sys.stderr)
  sys.exit(2)


def main(argv=None) -> dict:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--budget", default="full", choices=("ci", "full"))
  p.add_argument("--out", required=True, help="baseline cache dir (evaluate.py uses <its --out>/baselines)")
  p.add_argument("--only", default=",".join(NAMES), help=f"comma-separated subset of {','.join(NAMES)}")
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--seed", type=int, default=10_000, help="build seed (evaluate.py passes its --seed, default 10000)")
  p.add_argument("--worlds", default="", help="comma-separated training worlds (default: controllers.DEFAULT_WORLDS)")
  p.add_argument("--json", default="", help="also write the result here")
  args = p.parse_args(argv)
  names = tuple(n.strip() for n in args.only.split(",") if n.strip())
  if not names or any(n not in NAMES for n in names):
    _fail(f"--only takes a comma-separated subset of {','.join(NAMES)}, got {args.only!r}")

  import jax
  from specguard_jax import controllers as C
  from specguard_jax.baselines import common
  worlds = tuple(w for w in args.worlds.split(",") if w) or C.DEFAULT_WORLDS
  ctx = C.BuildContext(vehicle=args.vehicle, cache_dir=args.out, seed=args.seed, worlds=worlds,
                       train_budget=args.budget)
  res = {"device": str(jax.devices()[0].device_kind), "backend": jax.default_backend(), "jax": jax.__version__,
         "budget": args.budget, "budget_sizes": common.budget_summary(args.budget), "vehicle": args.vehicle,
         "seed": args.seed, "out": os.path.abspath(args.out), "wall_s": {}, "cpu_s": {}, "meta": {}}
  if "ftc_rl" in names:
    from specguard_jax.baselines import ftc
    fc = ftc.train_config(ctx)
    res["ftc_sizes"] = {"num_envs": fc.num_envs, "unroll_length": fc.unroll_length,
                        "phase1_steps": fc.phase1_steps, "phase2_steps": fc.phase2_steps}
  t_all, c_all = time.time(), time.process_time()
  need_flights = any(n != "ftc_rl" and not os.path.exists(common.cache_path(ctx, n, "msgpack")) for n in names)
  if need_flights:
    t0, c0 = time.time(), time.process_time()
    common.flights(args.vehicle, worlds, args.budget, args.seed)
    res["wall_s"]["flights"] = round(time.time() - t0, 2)
    res["cpu_s"]["flights"] = round(time.process_time() - c0, 2)
    print(f"flights recorded in {res['wall_s']['flights']} s", file=sys.stderr, flush=True)
  for n in names:
    if n == "ftc_rl":   # the recording is not needed any more: free its device memory before PPO
      common.flights.cache_clear()
    t0, c0 = time.time(), time.process_time()
    try:
      ctl = C.build(n, ctx)
      res["wall_s"][n] = round(time.time() - t0, 2)
      res["cpu_s"][n] = round(time.process_time() - c0, 2)
      res["meta"][n] = common.build_meta(ctx, n)
      print(f"{n} built in {res['wall_s'][n]} s: {ctl.description}", file=sys.stderr, flush=True)
    except Exception as e:  # noqa: BLE001 - report and go on with the next baseline
      res["wall_s"][n] = round(time.time() - t0, 2)
      res["meta"][n] = {"error": f"{type(e).__name__}: {' '.join(str(e).split())[:300]}"}
      print(f"{n} FAILED after {res['wall_s'][n]} s: {res['meta'][n]['error']}", file=sys.stderr, flush=True)
  res["wall_s"]["total"] = round(time.time() - t_all, 2)
  res["cpu_s"]["total"] = round(time.process_time() - c_all, 2)
  text = json.dumps(res, indent=1)
  print(text, flush=True)
  if args.json:
    with open(args.json, "w") as f:
      f.write(text)
  return res


if __name__ == "__main__":
  main()
