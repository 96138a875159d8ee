"""The EKF tick's covariance work with one vehicle per GPU lane: a Pallas Mosaic GPU kernel (NVIDIA Hopper).

What it computes is `ekf._cov_tick` (the XLA form, the reference and the CPU path): the prediction of P, the tick's
symmetrisation and clamps, the grouped innovation gates, the sequential scalar fusion of the accepted rows in
low-rank form, the timeout resets and the closing clean-up. It returns what `_cov_tick` returns (P [B, 15, 15], dx
[B, 15], test ratio [B, 13], accept [B, 13] bool), equal to float32 rounding (`tests/test_ekf_lanes.py`).

Layout: vehicle-minor. One program owns 128 vehicles, one per thread of a warpgroup; every per-vehicle quantity is a
row of a [rows, 128] block in shared memory, so in the kernel each is a [128] vector and the tick is straight-line
per-lane code with P's symmetry and F's / H's sparsity resolved statically: no shuffles, no masked reductions, no
[B, 15, 15] intermediates in global memory (what the XLA form's ~60 kernels per tick and the Triton tile kernel
`ekf_kernel.py` pay for). P lives in registers during the tick. XLA transposes the inputs into that layout ([225, B]
for P, row 15 i + j) and the outputs back (plain transposes, no gathers); shared memory holds P's upper triangle
(120 rows, copied in and out as 15 row ranges, XLA mirroring it on the way out) and the outputs overwrite the inputs'
block: 104 KB per program, two programs per SM (all 225 rows and a separate output block: 180 KB, one; 15-18 % slower).

Lowering: `plgpu.kernel` with Lane semantics. With jax 0.10 / 0.11 `pallas_call` lowers only to Triton on GPUs,
and Triton did not compile this straight-line form in 9 minutes (session 11); jax 0.11's default Warpgroup semantics
did not in 285 s (its layout inference grows faster than linearly with the kernel's length, session 34), where Lane
semantics compiles the whole tick in 3-8 s. Measured (BENCHMARKS.md session 35, H200, 65,536 vehicles, us per tick,
every row fresh / GPS rows stale): drone 216.5 / 131.9 against XLA's 677.9 / 488.1 and the Triton kernel's 453.7 /
344.7. A form that loops over P in shared memory (to keep the kernel short) compiled as fast but ran slower than XLA
(latency-bound on shared memory), so the tick stays straight-line code with P in registers (~170 per thread).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

N_ERR = 15
N_ROWS = 13
LANES = 128     # vehicles per program: one per thread of a warpgroup
TRI = tuple((i, j) for i in range(N_ERR) for j in range(i, N_ERR))       # P's upper triangle, 120 entries
TRI_INDEX = {ij: k for k, ij in enumerate(TRI)}


def _finite(x):
  """Elementwise isfinite (Mosaic GPU lowers abs and compare, not is_finite)."""
  return jnp.abs(x) < jnp.inf


class Layout:
  """Row offsets of the kernel's aux (input) and out (output) blocks, each [rows, lanes] float32.

  aux: A [9], B [9] (F's blocks, row-major), H's entries on `spec.h_entries()` [n_h], innov [13], enable [13]
  (1.0 / 0.0), due [3] (1.0 / 0.0, order ekf._RESETS). out: dx [15], test ratio [13], accept [13] (1.0 / 0.0).
  """

  def __init__(self, spec):
    self.A, self.B, self.H = 0, 9, 18
    self.innov = self.H + len(spec.h_entries())
    self.en = self.innov + N_ROWS
    self.due = self.en + N_ROWS
    self.n_aux = self.due + 3
    self.dx, self.ratio, self.acc = 0, N_ERR, N_ERR + N_ROWS
    self.n_out = N_ERR + 2 * N_ROWS


def tick_body(spec, resets, p_load, p_store, load, store, stage: str = "full"):
  """The per-lane covariance tick as straight-line code on [lanes] vectors (one vehicle per lane).

  p_load(i, j) -> P[i, j]; p_store(i, j, v) sets P[i, j] and P[j, i]; load(k) -> row k of aux, store(k, v) row k
  of out (both as `Layout` places them). Every load comes before the first store, so P and out may overwrite their
  inputs in place (the kernel's shared memory does).
  resets: ((cols, rows, how, var), ...) ekf._RESETS with their variances (`resets_of`).
  stage: "full" (the tick), or a probe for compile and run time (bench/ekf_lanes.py): "predict" (the prediction and
  its clamps alone, the other outputs zero) or "copy" (P and out copied from P and the first rows of aux)."""
  n = N_ERR
  o = Layout(spec)
  tri = [p_load(i, j) for (i, j) in TRI]
  if stage == "copy":      # memory floor: every output row from an input row
    for k, (i, j) in enumerate(TRI):
      p_store(i, j, tri[k] * 1.0)
    for k in range(o.n_out):
      store(k, load(k) * 1.0)
    return
  P = [[tri[TRI_INDEX[(min(i, j), max(i, j))]] for j in range(n)] for i in range(n)]
  A = [[load(o.A + 3 * i + m) for m in range(3)] for i in range(3)]
  B = [[load(o.B + 3 * i + m) for m in range(3)] for i in range(3)]
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
    for (i, j) in TRI:
      p_store(i, j, P[i][j])
    zero = load(o.innov) * 0.0
    for r in range(o.n_out):
      store(r, zero)
    return

  # ---- gates (ekf._gate) and low-rank sequential fusion (ekf._rows_unrolled)
  hd = {}
  for e, (i, c) in enumerate(spec.h_entries()):
    hd.setdefault(i, {})[c] = load(o.H + e)
  used = [i for i in range(N_ROWS) if spec.used[i]]

  def hdot(i, v):   # h_i . v, v indexable by error-state column
    t = None
    for c, h in hd[i].items():
      t = h * v[c] if t is None else t + h * v[c]
    return t

  PHt = {i: [hdot(i, [P[c][r] for c in range(n)]) for r in range(n)] for i in used}
  innov = [load(o.innov + i) for i in range(N_ROWS)]
  enable = [load(o.en + i) > 0.5 for i in range(N_ROWS)]
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
    do = (load(o.due + b) > 0.5) & ~fused
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

  for (i, j) in TRI:
    p_store(i, j, P[i][j])
  zero = 0.0 * innov[0]
  for r in range(n):
    store(o.dx + r, zero if dx[r] is None else dx[r])
  for i in range(N_ROWS):
    store(o.ratio + i, ratio[i])
    store(o.acc + i, jnp.where(accept[i], 1.0, 0.0))


def pack(spec, P, A, B, H, innov, enable, due):
  """Batch-major inputs -> (P [225, B], aux [n_aux, B]): the kernel's vehicle-minor layout."""
  nb = P.shape[0]
  f32 = jnp.float32
  hd = jnp.stack([H[:, i, c] for i, c in spec.h_entries()], axis=1)
  aux = jnp.concatenate([A.reshape(nb, 9), B.reshape(nb, 9), hd, innov, enable.astype(f32), due.astype(f32)], axis=1)
  return P.reshape(nb, N_ERR * N_ERR).astype(f32).T, aux.astype(f32).T


def unpack(Pt, out, nb, upper_only: bool = False):
  """The kernel's outputs (P [225, >= B], out [41, >= B]) -> (P [B, 15, 15], dx [B, 15], ratio [B, 13],
  accept [B, 13] bool). upper_only: only P's rows i <= j were written (the rest is read from the transpose)."""
  o = out[:, :nb].T
  P = Pt[:, :nb].T.reshape(nb, N_ERR, N_ERR)
  if upper_only:
    P = jnp.where(np.triu(np.ones((N_ERR, N_ERR), bool)), P, jnp.swapaxes(P, 1, 2))
  return P, o[:, :N_ERR], o[:, N_ERR:N_ERR + N_ROWS], o[:, N_ERR + N_ROWS:] > 0.5


def cov_tick_xla(spec, resets, P, A, B, H, innov, enable, due, stage: str = "full"):
  """`tick_body` in plain JAX over [B] vectors: the kernel's arithmetic on any backend (tests; eager on the CPU is
  quicker than compiling its ~10^4 operations)."""
  nb = P.shape[0]
  Pt, aux = pack(spec, P, A, B, H, innov, enable, due)
  p_out, out = {}, {}

  def p_store(i, j, v):
    p_out[(i, j)] = p_out[(j, i)] = v

  tick_body(spec, resets, lambda i, j: Pt[N_ERR * i + j], p_store, lambda k: aux[k], out.__setitem__, stage)
  Po = jnp.stack([p_out[(i, j)] for i in range(N_ERR) for j in range(N_ERR)])
  return unpack(Po, jnp.stack([out[k] for k in range(len(out))]), nb)


@functools.partial(jax.jit, static_argnames=("spec", "resets", "stage", "interpret", "triangle"))
def cov_tick(spec, resets, P, A, B, H, innov, enable, due, stage: str = "full", interpret=None,
             triangle: bool = True):
  """The tick's covariance work for a batch of B vehicles as one Mosaic GPU kernel (NVIDIA Hopper or newer).

  P: [B, 15, 15] symmetric covariance before the prediction. A, B: [B, 3, 3] F's blocks (`ekf._predict_nominal`).
  H: [B, 13, 15] observation Jacobian (its entries on `spec.h_entries()` are read). innov: [B, 13]. enable: [B, 13]
  bool. due: [B, 3] bool, the timeout resets due (order ekf._RESETS). spec: `ekf._cov_spec`; resets: `resets_of`.
  Returns (P [B, 15, 15], dx [B, 15], ratio [B, 13], accept [B, 13] bool). stage: see `tick_body`.
  triangle: shared memory holds P's upper triangle only (120 rows, copied in and out as 15 row ranges; XLA mirrors
  it on the way out) and the outputs overwrite aux in place: 104 KB per program instead of 180, two programs per SM.
  interpret: Mosaic GPU's interpreter parameters (`InterpretGPUParams()`: runs on the CPU, for tests)."""
  from jax.experimental import pallas as pl
  import jax.experimental.pallas.mosaic_gpu as plgpu
  nb = P.shape[0]
  bp = -(-nb // LANES) * LANES
  lay = Layout(spec)
  Pt, aux = (jnp.pad(x, ((0, 0), (0, bp - nb))) for x in pack(spec, P, A, B, H, innov, enable, due))
  f32 = jnp.float32
  # P's rows in shared memory: all 225, or the upper triangle's 120 (row i's entries j >= i as one range)
  ranges = [(N_ERR * i + i, TRI_INDEX[(i, i)], N_ERR - i) for i in range(N_ERR)] if triangle else [(0, 0, 225)]
  p_row = (lambda i, j: TRI_INDEX[(min(i, j), max(i, j))]) if triangle else (lambda i, j: N_ERR * i + j)

  def kernel(p_gmem, aux_gmem, po_gmem, out_gmem, p_smem, aux_smem, *scratch):
    *out_smem, p_bar, aux_bar = scratch
    out_smem = out_smem[0] if out_smem else aux_smem
    blk = pl.ds(jax.lax.axis_index("b") * LANES, LANES)
    for g, s_, n in ranges:
      plgpu.copy_gmem_to_smem(p_gmem.at[pl.ds(g, n), blk], p_smem.at[pl.ds(s_, n)], p_bar)
    plgpu.copy_gmem_to_smem(aux_gmem.at[:, blk], aux_smem, aux_bar)
    plgpu.barrier_wait(p_bar)
    plgpu.barrier_wait(aux_bar)

    def p_store(i, j, v):
      p_smem[p_row(i, j)] = v
      if i != j and not triangle:
        p_smem[p_row(j, i)] = v

    def store(k, v):
      out_smem[k] = v

    tick_body(spec, resets, lambda i, j: p_smem[p_row(i, j)], p_store, lambda k: aux_smem[k], store, stage)
    plgpu.commit_smem()
    for g, s_, n in ranges:
      plgpu.copy_smem_to_gmem(p_smem.at[pl.ds(s_, n)], po_gmem.at[pl.ds(g, n), blk])
    plgpu.copy_smem_to_gmem(out_smem.at[pl.ds(0, lay.n_out)], out_gmem.at[:, blk])
    plgpu.wait_smem_to_gmem(0)

  # triangle: the outputs overwrite aux in place (every load of tick_body precedes its first store)
  out_scratch = [] if triangle else [plgpu.SMEM((lay.n_out, LANES), f32)]
  Po, out = plgpu.kernel(
    kernel, out_type=(jax.ShapeDtypeStruct((N_ERR * N_ERR, bp), f32), jax.ShapeDtypeStruct((lay.n_out, bp), f32)),
    grid=(bp // LANES,), grid_names=("b",),
    scratch_types=[plgpu.SMEM((120 if triangle else 225, LANES), f32), plgpu.SMEM((lay.n_aux, LANES), f32)]
    + out_scratch + [plgpu.Barrier(num_arrivals=len(ranges)), plgpu.Barrier(num_arrivals=1)],
    compiler_params=None if interpret else plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Lane),
    interpret=interpret)(Pt, aux)
  return unpack(Po, out, nb, upper_only=triangle)


def resets_of(cfg):
  """ekf._RESETS with their variances, as the static tuple the kernel is traced for."""
  from specguard_jax import ekf as ekf_lib
  return tuple((tuple(cols), tuple(rows), how, float(v))
               for (cols, rows, how), v in zip(ekf_lib._RESETS, ekf_lib._reset_variances(cfg)))
