"""Time the lanes EKF kernel (specguard_jax/ekf_lanes.py, `prep_tick`) against the XLA filter's tick.

  python bench/ekf_lanes.py --envs 65536 [--vehicle drone|rover] [--ticks full stale] [--no-xla]
  MOSAIC_GPU_DUMP_PTXAS=1 python bench/ekf_lanes.py [--vehicle rover]     # ptxas: each kernel's registers and spills

Prints us per tick (best of 3 x 20 chained ticks, compile excluded) and the compile time, then the kernel's deviation
from the XLA reference (`ekf_lanes.reference_tick` under vmap): the largest relative deviation of P and dx, and
whether the gate records agree. The kernel is timed on P packed ([B, 121], as the env keeps it with the kernel), the
XLA reference on P [B, 15, 15]. Needs an NVIDIA Hopper GPU. Figures: BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import jax
import numpy as np

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes

DT = 0.02   # s, the env's tick


def timed(fn, args, reps=20):
  """(best us per call of fn over reps chained calls (P fed back), compile s)."""
  @jax.jit
  def run(P, *rest):
    return jax.lax.fori_loop(0, reps, lambda _, P: fn(P, *rest)[0], P)
  t0 = time.perf_counter()
  jax.block_until_ready(run(*args))
  compile_s = time.perf_counter() - t0
  best = float("inf")
  for _ in range(3):
    t = time.perf_counter()
    jax.block_until_ready(run(*args))
    best = min(best, (time.perf_counter() - t) / reps)
  return best * 1e6, compile_s


def deviation(ref, out):
  """(max relative deviation of P per vehicle, of dx, whether ratio / accept agree to rounding / exactly)."""
  P_r, dx_r, ratio_r, acc_r = [np.asarray(x) for x in ref]
  P, dx, ratio, acc = [np.asarray(x) for x in out]
  dP = np.max(np.abs(P - P_r) / np.max(np.abs(P_r), axis=(1, 2), keepdims=True))
  ddx = np.max(np.abs(dx - dx_r) / (np.max(np.abs(dx_r), axis=1, keepdims=True) + 1e-12))
  return dP, ddx, bool(np.allclose(ratio, ratio_r, rtol=2e-5, atol=1e-7)), bool(np.array_equal(acc, acc_r))


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--envs", type=int, nargs="+", default=[65536])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--ticks", nargs="+", default=["full", "stale"], choices=("full", "stale"),
                 help="full: every row fresh (the GPS tick); stale: GPS rows left out (the other four ticks)")
  p.add_argument("--no-xla", action="store_true", help="skip the XLA reference's timing")
  a = p.parse_args()
  if jax.default_backend() != "gpu":
    sys.exit(f"bench/ekf_lanes.py: the Mosaic GPU kernel needs an NVIDIA Hopper GPU (backend: {jax.default_backend()})")
  sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
  from test_ekf_lanes import _raw_batch
  cfg = ekf_lib.EKFConfig.drone() if a.vehicle == "drone" else ekf_lib.EKFConfig.rover()
  print(f"{jax.devices()[0].device_kind}, {a.vehicle}: us per tick (compile s)", flush=True)
  for n in a.envs:
    args = _raw_batch(cfg, n, seed=0)
    packed_args = [ekf_lib.pack_p(args[0])] + args[1:]
    for stale in [() if t == "full" else ("gps",) for t in a.ticks]:
      ref = jax.jit(jax.vmap(functools.partial(ekf_lanes.reference_tick, cfg, DT, stale)))
      lanes = functools.partial(ekf_lanes.prep_tick, ekf_lanes.cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg),
                                flow_min_height=float(cfg.flow_min_height))
      rows = ([] if a.no_xla else [("XLA (reference_tick)", ref, args)]) + [("lanes, prep_tick", lanes, packed_args)]
      for name, fn, fn_args in rows:
        t, c = timed(fn, fn_args)
        print(f"  {n:7d} stale={stale!s:9s} {name:24s} {t:9.1f} us  ({c:.1f} s)", flush=True)
      out = jax.jit(lanes)(*packed_args)
      dP, ddx, ratio_ok, acc_ok = deviation(ref(*args)[:4], (ekf_lib.as_square(out[0]),) + tuple(out[1:4]))
      print(f"    vs reference_tick: P {dP:.1e}, dx {ddx:.1e} (relative, worst vehicle); ratio within 2e-5: "
            f"{ratio_ok}; accept identical: {acc_ok}", flush=True)


if __name__ == "__main__":
  main()
