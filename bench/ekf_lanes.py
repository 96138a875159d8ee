"""The EKF tick's covariance work with one vehicle per GPU thread, as a Pallas Mosaic GPU kernel: an experiment.

  python bench/ekf_lanes.py --envs 65536 --stage copy|predict|full [--vehicle drone|rover] [--no-xla]

What it computes is `ekf._cov_tick` (the XLA form, the reference): prediction of P, the tick's symmetrisation and
clamps, the gates, the low-rank sequential fusion, the timeout resets and the closing clean-up. The layout is
vehicle-minor: every per-vehicle quantity is one row of a [rows, B] array (P as its 120-entry upper triangle), so in
the kernel each is a [128] vector, one vehicle per CUDA lane, and the whole tick is straight-line per-lane code with
P's symmetry and F's / H's sparsity resolved statically: no shuffles, no masked reductions, no [B, 15, 15] buffers
between kernels (what the XLA form and the Triton tile kernel `specguard_jax/ekf_kernel.py` pay for).

Why Mosaic GPU and `plgpu.kernel`: Triton did not compile this straight-line form in 9 minutes (session 11); with
jax 0.11 `pallas_call` lowers only to Triton on GPUs (its Mosaic GPU lowering rule is not registered), so the kernel
is a `plgpu.kernel` with one TMA copy of its input block into shared memory and one of its output block back.

Measured (BENCHMARKS.md "Session 34", H200, drone, 65,536 envs, GPS rows stale): `--stage copy` (pack, a kernel that
copies its block, unpack) 153 us per tick, compile 8 s; `--stage predict` (the prediction and its clamps, 168
registers, no spills) 161 us, compile 73 s: the per-lane arithmetic costs ~7 us over the copy, the layout change
(pack + unpack in XLA, ~130 us) is most of it; `--stage full` did not finish compiling in 285 s. Not used by the env:
it needs a form that compiles in seconds (loops over P's rows in shared memory instead of straight-line code) and P
kept in the kernel's layout between ticks. `tests/test_ekf_lanes.py` checks the per-lane body against `ekf._cov_tick`
on the CPU (plain XLA over lanes), that the kernel lowers for CUDA, and its blocks and offsets in Mosaic GPU's CPU
interpreter (`interpret=InterpretGPUParams()`; the whole kernel interpreted equals `ekf._cov_tick` too, ~1 min).
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax import ekf as ekf_lib

N_ERR = 15
N_ROWS = 13
LANES = 128     # vehicles per program: one per CUDA lane of a warpgroup
TRI = tuple((i, j) for i in range(N_ERR) for j in range(i, N_ERR))       # P's packed upper triangle, 120 entries
TRI_INDEX = {ij: k for k, ij in enumerate(TRI)}
FULL_FROM_TRI = np.array([TRI_INDEX[(min(i, j), max(i, j))] for i in range(N_ERR) for j in range(N_ERR)])


def _finite(x):
  """Elementwise isfinite (Mosaic GPU lowers abs and compare, not is_finite)."""
  return jnp.abs(x) < jnp.inf


def layout(spec):
  """Row offsets of the kernel's input and output arrays: (in_rows, out_rows, offsets dict)."""
  h = spec.h_entries()
  o = {"P": 0, "A": 120, "B": 129, "H": 138}
  o["innov"] = o["H"] + len(h)
  o["en"] = o["innov"] + N_ROWS
  o["due"] = o["en"] + N_ROWS
  n_in = o["due"] + 3
  return n_in, 120 + N_ERR + 2 * N_ROWS, o


def body(load, store, spec, resets, stage: str = "full"):
  """Per-lane covariance tick. load(k) -> [L] row k of the input (rows as `layout` places them); store(k, v) row k of
  the output: P's triangle (120, order TRI), dx (15), test ratios (13), accepted (13, 1.0 / 0.0).
  resets: ((cols, rows, how, var), ...) the timeout-reset blocks (ekf._RESETS with their variances).
  stage: "full" (the tick), or a probe for compile and run time: "predict" (the prediction and its clamps alone,
  the other outputs zero) or "copy" (output row k = input row k)."""
  n = N_ERR
  _, _, o = layout(spec)
  tri = [load(o["P"] + k) for k in range(120)]
  if stage == "copy":      # memory floor: every output row from an input row
    _, n_out, _ = layout(spec)
    for k in range(n_out):
      store(k, load(k) * 1.0)
    return
  P = [[tri[TRI_INDEX[(min(i, j), max(i, j))]] for j in range(n)] for i in range(n)]
  A = [[load(o["A"] + 3 * i + m) for m in range(3)] for i in range(3)]
  B = [[load(o["B"] + 3 * i + m) for m in range(3)] for i in range(3)]
  dt = spec.dt

  # ---- prediction (ekf._predict_cov): FP = P + E P, X = FP + FP E', + Q, then _condition with symmetrisation
  def s3(t):
    return (t[0] + t[1]) + t[2]
  FP = [[None] * n for _ in range(n)]
  for c in range(n):
    for m in range(3):
      FP[m][c] = P[m][c] + dt * P[3 + m][c]
    for i in range(3):
      FP[3 + i][c] = P[3 + i][c] + (s3([A[i][m] * P[6 + m][c] for m in range(3)])
                                    + s3([B[i][m] * P[12 + m][c] for m in range(3)]))
      FP[6 + i][c] = P[6 + i][c] + s3([B[i][m] * P[9 + m][c] for m in range(3)])
    for r in range(9, n):
      FP[r][c] = P[r][c]
  X = [[None] * n for _ in range(n)]
  for r in range(n):
    for m in range(3):
      X[r][m] = FP[r][m] + dt * FP[r][3 + m]
    for i in range(3):
      X[r][3 + i] = FP[r][3 + i] + (s3([FP[r][6 + m] * A[i][m] for m in range(3)])
                                    + s3([FP[r][12 + m] * B[i][m] for m in range(3)]))
      X[r][6 + i] = FP[r][6 + i] + s3([FP[r][9 + m] * B[i][m] for m in range(3)])
    for c in range(9, n):
      X[r][c] = FP[r][c]
  for i in range(n):
    X[i][i] = X[i][i] + spec.q[i]

  def condition(S, sym):
    """ekf._condition on the triangle: S[i][j] for i <= j."""
    T = {}
    for (i, j) in TRI:
      v = 0.5 * (S[i][j] + S[j][i]) if sym else S[i][j]
      T[(i, j)] = jnp.where(_finite(v), v, 0.0)
    s, lift = [], []
    for i in range(n):
      d = T[(i, i)]
      si = jax.lax.rsqrt(jnp.maximum(1.0, jnp.maximum(d, 1e-30) * (1.0 / spec.var_max[i])))
      s.append(si)
      lift.append(jnp.maximum(spec.var_min[i] - d * (si * si), 0.0))
    out = [[None] * n for _ in range(n)]
    for (i, j) in TRI:
      v = T[(i, j)] * (s[i] * s[j])
      out[i][j] = out[j][i] = v + lift[i] if i == j else v
    return out

  P = condition(X, True)
  if stage == "predict":   # compile-size probe: the prediction alone
    for k, (i, j) in enumerate(TRI):
      store(k, P[i][j])
    for r in range(N_ERR + 2 * N_ROWS):
      store(120 + r, load(o["innov"]) * 0.0)
    return

  # ---- gates (ekf._gate) and low-rank sequential fusion (ekf._rows_unrolled)
  hd = {}
  for e, (i, c) in enumerate(spec.h_entries()):
    hd.setdefault(i, {})[c] = load(o["H"] + e)
  used = [i for i in range(N_ROWS) if spec.used[i]]

  def hdot(i, v):   # h_i . v, v indexable by error-state column
    t = None
    for c, h in hd[i].items():
      t = h * v[c] if t is None else t + h * v[c]
    return t

  PHt = {i: [hdot(i, [P[c][r] for c in range(n)]) for r in range(n)] for i in used}
  innov = [load(o["innov"] + i) for i in range(N_ROWS)]
  enable = [load(o["en"] + i) > 0.5 for i in range(N_ROWS)]
  ratio, bad = [], []
  for i in range(N_ROWS):
    S = hdot(i, PHt[i]) + spec.R[i] if i in PHt else spec.R[i] + 0.0 * innov[i]
    r = innov[i] * innov[i] / ((spec.gate[i] * spec.gate[i]) * S)
    r = jnp.where(_finite(r), r, 1e6)
    ratio.append(r)
    bad.append(enable[i] & ~(r <= 1.0))
  gbad = {}
  for i in range(N_ROWS):
    g = spec.group_of_row[i]
    gbad[g] = bad[i] if g not in gbad else gbad[g] | bad[i]
  accept = [enable[i] & ~gbad[spec.group_of_row[i]] for i in range(N_ROWS)]
  innov = [jnp.where(accept[i], innov[i], 0.0) for i in range(N_ROWS)]

  us, cs = [], []
  dx = [None] * n
  for i in used:
    pht = PHt[i]
    for u, c in zip(us, cs):
      k = c * hdot(i, u)
      pht = [pht[r] - k * u[r] for r in range(n)]
    c = jnp.where(accept[i], 1.0 / (hdot(i, pht) + spec.R[i]), 0.0)
    g = c * (innov[i] - (hdot(i, dx) if dx[0] is not None else 0.0))
    dx = [(g * pht[r]) if dx[r] is None else dx[r] + g * pht[r] for r in range(n)]
    us.append(pht)
    cs.append(c)
  Pn = [[None] * n for _ in range(n)]
  for (i, j) in TRI:
    v = P[i][j]
    for u, c in zip(us, cs):
      v = v - c * (u[i] * u[j])
    Pn[i][j] = Pn[j][i] = v

  # ---- timeout resets, closing clean-up (ekf._reset_and_condition)
  cleared = [None] * n
  new_var = [0.0] * n
  for b, (cols, rows, how, var) in enumerate(resets):
    fl = [accept[r] for r in rows]
    fused = fl[0]
    for f in fl[1:]:
      fused = (fused & f) if how == "all" else (fused | f)
    do = (load(o["due"] + b) > 0.5) & ~fused
    for c in cols:
      cleared[c] = do
      new_var[c] = jnp.where(do, var, 0.0)
  for (i, j) in TRI:
    ci, cj = cleared[i], cleared[j]
    if ci is not None or cj is not None:
      m = ci if cj is None else (cj if ci is None else ci | cj)
      v = jnp.where(m, 0.0, Pn[i][j])
      if i == j:
        v = v + new_var[i]
      Pn[i][j] = Pn[j][i] = v
  P = condition(Pn, False)

  for k, (i, j) in enumerate(TRI):
    store(k, P[i][j])
  zero = 0.0 * innov[0]
  for r in range(n):
    store(120 + r, zero if dx[r] is None else dx[r])
  for i in range(N_ROWS):
    store(120 + n + i, ratio[i])
    store(120 + n + N_ROWS + i, jnp.where(accept[i], 1.0, 0.0))


def pack(spec, P, A, B, H, innov, enable, due):
  """Batch-major inputs -> the kernel's [rows, B] input (P [B, 15, 15] symmetric)."""
  nb = P.shape[0]
  Pf = P.reshape(nb, N_ERR * N_ERR)
  tri = Pf[:, [i * N_ERR + j for i, j in TRI]]
  hd = jnp.stack([H[:, i, c] for i, c in spec.h_entries()], axis=1)
  f32 = jnp.float32
  return jnp.concatenate([tri, A.reshape(nb, 9), B.reshape(nb, 9), hd, innov, enable.astype(f32),
                          due.astype(f32)], axis=1).astype(f32).T


def unpack(Y, nb):
  """The kernel's [161, >= B] output -> (P [B, 15, 15], dx [B, 15], ratio [B, 13], accept [B, 13] bool)."""
  P = Y[FULL_FROM_TRI, :nb].T.reshape(nb, N_ERR, N_ERR)
  o = 120
  return (P, Y[o:o + N_ERR, :nb].T, Y[o + N_ERR:o + N_ERR + N_ROWS, :nb].T,
          Y[o + N_ERR + N_ROWS:o + N_ERR + 2 * N_ROWS, :nb].T > 0.5)


def cov_tick_lanes_xla(spec, resets, P, A, B, H, innov, enable, due):
  """The per-lane body as plain XLA over [B] vectors (reference / CPU path)."""
  X = pack(spec, P, A, B, H, innov, enable, due)
  out = {}
  body(lambda k: X[k], out.__setitem__, spec, resets)
  Y = jnp.stack([out[k] for k in range(len(out))])
  return unpack(Y, P.shape[0])


def cov_tick_lanes_mgpu(spec, resets, P, A, B, H, innov, enable, due, lanes: int = LANES, stage: str = "full",
                        interpret=None):
  """The per-lane body as one Pallas Mosaic GPU kernel (Hopper): one program per `lanes` vehicles, its input block
  copied GMEM -> SMEM by TMA, the per-lane body on [lanes] vectors, the output block SMEM -> GMEM.
  interpret: Mosaic GPU's interpreter parameters (`InterpretGPUParams()`: runs on the CPU, for tests)."""
  from jax.experimental import pallas as pl
  import jax.experimental.pallas.mosaic_gpu as plgpu
  nb = P.shape[0]
  bp = -(-nb // lanes) * lanes
  X = pack(spec, P, A, B, H, innov, enable, due)
  X = jnp.pad(X, ((0, 0), (0, bp - nb)))
  n_in, n_out, _ = layout(spec)
  f32 = jnp.float32

  def kernel(x_gmem, y_gmem, x_smem, y_smem, bar):
    blk = pl.ds(jax.lax.axis_index("b") * lanes, lanes)
    plgpu.copy_gmem_to_smem(x_gmem.at[:, blk], x_smem, bar)
    plgpu.barrier_wait(bar)

    def store(k, v):
      y_smem[k] = v
    body(lambda k: x_smem[k], store, spec, resets, stage)
    plgpu.commit_smem()
    plgpu.copy_smem_to_gmem(y_smem, y_gmem.at[:, blk])
    plgpu.wait_smem_to_gmem(0)

  Y = plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct((n_out, bp), f32), grid=(bp // lanes,), grid_names=("b",),
                   scratch_types=[plgpu.SMEM((n_in, lanes), f32), plgpu.SMEM((n_out, lanes), f32),
                                  plgpu.Barrier(num_arrivals=1)], interpret=interpret)(X)
  return unpack(Y, nb)


def resets_of(cfg):
  """ekf._RESETS with their variances, as the static tuple `body` takes."""
  return tuple((tuple(cols), tuple(rows), how, float(v))
               for (cols, rows, how), v in zip(ekf_lib._RESETS, ekf_lib._reset_variances(cfg)))


def main():
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--envs", type=int, nargs="+", default=[65536])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--stage", default="full", choices=("copy", "predict", "full", "loop", "loop-layout"),
                 help="straight-line kernel: copy: pack + a kernel copying its block + unpack (the layout's floor); "
                      "predict: the prediction alone; full: the whole tick (checked against ekf._cov_tick). "
                      "loop: the library's looped kernel specguard_jax/ekf_lanes.py (checked too); loop-layout: its "
                      "XLA transposes in and out alone, no kernel")
  p.add_argument("--ticks", nargs="+", default=["stale"], choices=("full", "stale"),
                 help="full: every row fresh (the GPS tick); stale: GPS rows left out (the other four ticks)")
  p.add_argument("--no-xla", action="store_true", help="skip the XLA reference's timing")
  a = p.parse_args()
  if jax.default_backend() != "gpu":
    sys.exit(f"bench/ekf_lanes.py: the Mosaic GPU kernel needs an NVIDIA Hopper GPU (backend: {jax.default_backend()})")
  sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  from bench.ekf_kernel import timed
  from tests.test_ekf_kernel import DT as dt, _batch, _check, _xla
  from specguard_jax import ekf_lanes
  cfg = ekf_lib.EKFConfig.drone() if a.vehicle == "drone" else ekf_lib.EKFConfig.rover()
  resets = resets_of(cfg)
  print(f"{jax.devices()[0].device_kind}, {a.vehicle}: us per tick (compile s)", flush=True)
  for n in a.envs:
    args = _batch(cfg, n, seed=0)
    for stale in [() if t == "full" else ("gps",) for t in a.ticks]:
      spec = ekf_lib._cov_spec(cfg, dt, stale)
      xla = _xla(cfg, stale)   # jit(vmap(ekf._cov_tick)), the reference
      if not a.no_xla:
        t, c = timed(xla, args)
        print(f"  {n:7d} stale={stale!s:9s} XLA (ekf._cov_tick)   {t:9.1f} us  ({c:.1f} s)", flush=True)
      if a.stage == "loop":
        lanes = lambda *x: ekf_lanes.cov_tick(spec, resets, *x)
      elif a.stage == "loop-layout":
        lanes = lambda *x: ekf_lanes.unpack(*(lambda Pt, aux: (Pt, aux[:ekf_lanes.Layout(spec).n_out]))(
          *ekf_lanes.pack(spec, *x)), x[0].shape[0])
      else:
        lanes = lambda *x: cov_tick_lanes_mgpu(spec, resets, *x, stage=a.stage)
      t, c = timed(lanes, args)
      print(f"  {n:7d} stale={stale!s:9s} lanes, stage {a.stage:11s} {t:9.1f} us  ({c:.1f} s)", flush=True)
      if a.stage in ("full", "loop"):
        _check(xla(*args), jax.jit(lanes)(*args))
        print("    equal to ekf._cov_tick (tests/test_ekf_kernel.py's tolerances)", flush=True)


if __name__ == "__main__":
  main()
