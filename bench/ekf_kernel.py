"""The EKF tick's covariance work: XLA form vs the fused Pallas/Triton kernel (specguard_jax/ekf_kernel.py), per tick.

  python bench/ekf_kernel.py --envs 65536 [--blocks 2 4 8] [--warps 1 2 4]

Prints us per tick (best of 3 runs of a jitted 20-tick loop) and the compile time of each variant; drone, every row
fresh (the GPS tick) and GPS rows stale (the other four ticks of an env step). Both forms include the timeout resets
and clean-up of P (in the kernel's case the XLA pass after it, as in the env).
"""

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def timed(fn, args, reps=20):
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


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--envs", type=int, default=65536)
  p.add_argument("--blocks", type=int, nargs="+", default=[2], help="vehicles per program (the shipped kernel: 2)")
  p.add_argument("--warps", type=int, nargs="+", default=[1], help="warps per program (the shipped kernel: 1)")
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  a = p.parse_args()
  from specguard_jax import ekf as ekf_lib
  from specguard_jax import ekf_kernel
  sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  from tests.test_ekf_kernel import _batch
  cfg = ekf_lib.EKFConfig.drone() if a.vehicle == "drone" else ekf_lib.EKFConfig.rover()
  noise, gate = ekf_lib._noise_and_gates(cfg)
  args = _batch(cfg, a.envs, seed=0)
  dt = 0.02
  print(f"{jax.devices()[0].device_kind}, {a.vehicle}, {a.envs} envs: us per tick (compile s)")
  for stale in [(), ("gps",)]:
    xla = jax.vmap(lambda P, A, B, H, innov, en, due: ekf_lib._cov_tick(
        cfg, P, A, B, dt, H, innov, jnp.asarray(noise) ** 2, jnp.asarray(gate), en, due, stale, unrolled=True))
    t, c = timed(xla, args)
    print(f"  stale={stale!s:10s} XLA                      {t:9.1f} us  ({c:.1f} s)", flush=True)
    spec = ekf_lib._cov_spec(cfg, dt, stale)
    for blk in a.blocks:
      for w in a.warps:
        def fused(P, A, B, H, innov, en, due):   # the kernel, then the resets + clean-up pass the XLA tick includes
          ab = jnp.concatenate([A.reshape(-1, 9), B.reshape(-1, 9)], axis=1)
          P, dx, ratio, acc, diag = ekf_kernel.cov_tick(spec, P, ab, H, innov, en, num_warps=w, block=blk)
          return jax.vmap(lambda *x: ekf_lib._reset_and_condition(cfg, *x))(P, acc, due, diag), dx, ratio, acc
        try:
          t, c = timed(fused, args)
          print(f"  stale={stale!s:10s} kernel block {blk:3d} warps {w}  {t:9.1f} us  ({c:.1f} s)", flush=True)
        except Exception as e:  # noqa: BLE001  (a configuration Triton cannot compile: report and go on)
          print(f"  stale={stale!s:10s} kernel block {blk:3d} warps {w}  failed: {str(e).splitlines()[0][:200]}")


if __name__ == "__main__":
  main()
