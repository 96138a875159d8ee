"""Time the EKF's per-lane covariance kernel (specguard_jax/ekf_lanes.py) against the XLA form and the Triton kernel.

  python bench/ekf_lanes.py --envs 65536 [--vehicle drone|rover] [--stage copy|predict|full] [--ticks full stale]
                            [--no-xla] [--triton]
  MOSAIC_GPU_DUMP_PTXAS=1 python bench/ekf_lanes.py --prep [--vehicle rover]   # the env's kernel; ptxas: registers

Prints us per tick (best of 3 x 20 chained ticks, compile excluded) and the compile time; for the full stage the
kernel's output is compared with `ekf._cov_tick` (the largest relative deviation of P and dx, and whether the gate
records are identical). The kernel is timed on P packed ([B, 121], as the env keeps it with the kernel), the XLA
reference and the Triton kernel on P [B, 15, 15]. Stages: "full" the tick; "predict" the prediction and its clamps
alone; "copy" a kernel that copies its blocks (the memory floor of the layout). --prep times `prep_tick` instead, the
kernel the env runs (the tick's inputs prepared per lane), against `ekf._tick_prep_xla` under vmap; with
MOSAIC_GPU_DUMP_PTXAS=1 in the environment ptxas prints each kernel's registers and spills. Needs an NVIDIA Hopper
GPU. Measured: BENCHMARKS.md, sessions 34-36 and 41.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys

import jax
import numpy as np

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes


def deviation(ref, out):
  """(max relative deviation of P per vehicle, of dx, whether ratio / accept agree to rounding / exactly)."""
  P_r, dx_r, ratio_r, acc_r = [np.asarray(x) for x in ref]
  P, dx, ratio, acc = [np.asarray(x) for x in out]
  dP = np.max(np.abs(P - P_r) / np.max(np.abs(P_r), axis=(1, 2), keepdims=True))
  ddx = np.max(np.abs(dx - dx_r) / (np.max(np.abs(dx_r), axis=1, keepdims=True) + 1e-12))
  return dP, ddx, bool(np.allclose(ratio, ratio_r, rtol=2e-5, atol=1e-7)), bool(np.array_equal(acc, acc_r))


def prep_rows(cfg, stale, xla: bool = True):
  """[(name, fn)] for --prep: `prep_tick` (P packed) and, with xla, `ekf._tick_prep_xla` under vmap (P square); each
  fn(P, *inputs) -> (P, ...) as `tests.test_ekf_lanes._raw_batch`'s inputs."""
  from tests.test_ekf_kernel import DT as dt
  spec = ekf_lib._cov_spec(cfg, dt, stale)
  ref = jax.vmap(functools.partial(ekf_lib._tick_prep_xla, cfg, dt, stale))
  rows = [("XLA (ekf._tick_prep_xla)", ref)] if xla else []
  return rows + [("lanes, prep_tick", functools.partial(ekf_lanes.prep_tick, spec, ekf_lanes.resets_of(cfg),
                                                        flow_min_height=float(cfg.flow_min_height)))]


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--envs", type=int, nargs="+", default=[65536])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--stage", default="full", choices=("copy", "predict", "full"))
  p.add_argument("--ticks", nargs="+", default=["full", "stale"], choices=("full", "stale"),
                 help="full: every row fresh (the GPS tick); stale: GPS rows left out (the other four ticks)")
  p.add_argument("--no-xla", action="store_true", help="skip the XLA reference's timing")
  p.add_argument("--triton", action="store_true", help="time the Triton kernel (ekf_kernel.py, --fused-ekf triton)")
  p.add_argument("--prep", action="store_true",
                 help="time prep_tick (the env's kernel: inputs prepared per lane) against ekf._tick_prep_xla")
  a = p.parse_args()
  if jax.default_backend() != "gpu":
    sys.exit(f"bench/ekf_lanes.py: the Mosaic GPU kernel needs an NVIDIA Hopper GPU (backend: {jax.default_backend()})")
  sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  from bench.ekf_kernel import timed
  from tests.test_ekf_kernel import DT as dt, _batch, _fused, _xla
  cfg = ekf_lib.EKFConfig.drone() if a.vehicle == "drone" else ekf_lib.EKFConfig.rover()
  resets = ekf_lanes.resets_of(cfg)
  print(f"{jax.devices()[0].device_kind}, {a.vehicle}: us per tick (compile s)", flush=True)
  if a.prep:
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
    from test_ekf_lanes import _raw_batch    # (it imports its sibling test_ekf_kernel by that name)
    for n in a.envs:
      args = _raw_batch(cfg, n, seed=0)
      packed_args = [ekf_lib.pack_p(args[0])] + args[1:]
      for stale in [() if t == "full" else ("gps",) for t in a.ticks]:
        for name, fn in prep_rows(cfg, stale, not a.no_xla):
          t, c = timed(fn, packed_args if name.startswith("lanes") else args)
          print(f"  {n:7d} stale={stale!s:9s} {name:24s} {t:9.1f} us  ({c:.1f} s)", flush=True)
    return
  for n in a.envs:
    args = _batch(cfg, n, seed=0)
    for stale in [() if t == "full" else ("gps",) for t in a.ticks]:
      spec = ekf_lib._cov_spec(cfg, dt, stale)
      xla = _xla(cfg, stale)   # jit(vmap(ekf._cov_tick)), the reference
      rows = [("XLA (ekf._cov_tick)", xla)] if not a.no_xla else []
      if a.triton:
        rows.append(("Triton (ekf_kernel)", _fused(cfg, stale, False)))
      rows.append((f"lanes, {a.stage}", functools.partial(ekf_lanes.cov_tick, spec, resets, stage=a.stage)))
      packed_args = (ekf_lib.pack_p(args[0]),) + tuple(args[1:])   # P as the env keeps it with the lanes kernel
      for name, fn in rows:
        lanes = name.startswith("lanes")
        t, c = timed(fn, packed_args if lanes else args)
        print(f"  {n:7d} stale={stale!s:9s} {name:24s} {t:9.1f} us  ({c:.1f} s)", flush=True)
        if a.stage == "full" and lanes:
          out = jax.jit(fn)(*packed_args)
          out = (ekf_lib.as_square(out[0]),) + tuple(out[1:])
          dP, ddx, ratio_ok, acc_ok = deviation(xla(*args), out)
          print(f"    vs ekf._cov_tick: P {dP:.1e}, dx {ddx:.1e} (relative, worst vehicle); ratio within 2e-5: "
                f"{ratio_ok}; accept identical: {acc_ok}", flush=True)


if __name__ == "__main__":
  main()
