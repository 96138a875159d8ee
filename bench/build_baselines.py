import sys, time
from specguard_jax import controllers as c
out = sys.argv[1]
ctx = c.BuildContext(vehicle="drone", run_dir=None, cache_dir=out, seed=0,
                     worlds=("suburban_residential", "urban_city_streets", "urban_park", "open_mountain"), train_budget="full")
for n in ("ssr", "unrocker", "pid_piper", "ftc"):
  t0 = time.time()
  try:
    ctl = c.build(n, ctx)
    print(n, "built in", round(time.time() - t0, 1), "s:", ctl.description, flush=True)
  except Exception as e:
    print(n, "FAILED", type(e).__name__, e, flush=True)
