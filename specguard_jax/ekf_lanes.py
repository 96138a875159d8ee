"""The EKF tick's covariance work with one vehicle per GPU lane: a Pallas Mosaic GPU kernel (Hopper) with loops.

What it computes is `ekf._cov_tick` (the XLA form, the reference and the CPU path): the prediction of P and the tick's
symmetrisation and clamps, the grouped innovation gates, the sequential scalar fusion of the accepted rows, the
timeout resets and the closing clean-up. Returns what `_cov_tick` returns (P [B, 15, 15], dx [B, 15], test ratio
[B, 13], accept [B, 13] bool), equal to float32 rounding (`tests/test_ekf_lanes.py`).

Layout: vehicle-minor. One program owns 128 vehicles (one per thread of a warpgroup); every per-vehicle quantity is
one row of a [rows, 128] block in shared memory (P as its 225 entries, row 15 i + j), so each is a [128] vector in
the kernel and the tick is per-lane arithmetic: no shuffles, no masked reductions, no [B, 15, 15] intermediates in
global memory. XLA transposes the inputs into that layout and the outputs back (plain transposes, no gathers).

Why loops: the same tick written as straight-line per-lane code (bench/ekf_lanes.py, session 34) ran its prediction
in ~30 us at 65,536 vehicles but took > 285 s to compile whole (Mosaic GPU's compile grows faster than linearly with
the kernel's length). Here every pass over P is a `fori_loop` over its rows or columns with a short body, and the
fusion is one loop over the 13 observation rows with H's row read from shared memory (dense over the 9 columns H can
be non-zero in, _H_COLS; entries off the row's support are exact zeros, so the sums round as the sparse ones do), so
the kernel is a few hundred operations long whatever the configuration.

Fusion form: the rolled one (`ekf._rows_rolled`: P_i = P_{i-1} - c_i u_i u_i', u_i = P_{i-1} h_i), equal to the
accelerators' low-rank form up to rounding; every update is c * (u_r * u_j), so P stays exactly symmetric.

Why `plgpu.kernel`: with jax 0.10 / 0.11 `pallas_call` lowers only to Triton on GPUs (no Mosaic GPU lowering rule is
registered), and Triton has no addressable shared memory in Pallas; `plgpu.kernel` gives the TMA copies and the
shared-memory scratch this layout needs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

N_ERR = 15
N_ROWS = 13
N_HCOLS = 9           # H can be non-zero in error-state columns 0..8 only (ekf._H_COLS)
LANES = 128           # vehicles per program: one per thread of a warpgroup


def _finite(x):
  """Elementwise isfinite (Mosaic GPU lowers abs and compare, not is_finite)."""
  return jnp.abs(x) < jnp.inf


def _where(pred, a, b):
  """jnp.where whose predicate may be a traced scalar (a loop index test): broadcast to the vectors' shape first
  (Mosaic GPU's warpgroup lowering of select does no implicit broadcast)."""
  shape = jnp.broadcast_shapes(jnp.shape(a), jnp.shape(b))
  if jnp.shape(pred) == shape:
    return jnp.where(pred, a, b)
  # as a float: Mosaic GPU cannot broadcast (convert) a scalar bool to a vector of them
  return jnp.where(jnp.broadcast_to(jnp.where(pred, 1.0, 0.0), shape) > 0.5, a, b)


def _not(b):
  """Logical not of a bool vector (Mosaic GPU's warpgroup lowering of lax.not_p on bools fails: i1 registers)."""
  return jnp.where(b, 0.0, 1.0) > 0.5


def _select(i, values, dtype):
  """values[i] for a traced scalar index i and a static table (a chain of scalar selects)."""
  out = jnp.asarray(values[0], dtype)
  for k in range(1, len(values)):
    out = jnp.where(i == k, jnp.asarray(values[k], dtype), out)
  return out


class Layout:
  """Row offsets of the kernel's shared-memory blocks (each [rows, 128] float32).

  aux (input): A [9], B [9] (F's blocks, row-major), H's entries on the support of each used row [n_h] (order
  `spec.h_entries()`), innov [13], enable [13] (1.0 / 0.0), due [3] (1.0 / 0.0, order ekf._RESETS).
  out: dx [15], ratio [13], accept [13] (1.0 / 0.0).
  work (scratch): u [15] (the current row's P h), s [15] and lift [15] (the clamps), cleared [15] and new_var [15]
  (the resets).
  """

  def __init__(self, spec):
    self.h_entries = spec.h_entries()
    self.A, self.B, self.H = 0, 9, 18
    self.innov = self.H + len(self.h_entries)
    self.en = self.innov + N_ROWS
    self.due = self.en + N_ROWS
    self.n_aux = self.due + 3
    self.dx, self.ratio, self.acc = 0, N_ERR, N_ERR + N_ROWS
    self.n_out = N_ERR + 2 * N_ROWS
    self.u, self.s, self.lift, self.clr, self.nv = (k * N_ERR for k in range(5))
    self.n_work = 5 * N_ERR
    # per observation row: where its H entries start in aux, and its support [lo, hi) (contiguous, checked)
    self.h_off, self.h_lo, self.h_hi = [], [], []
    for i in range(N_ROWS):
      cols = [c for (r, c) in self.h_entries if r == i]
      if cols:
        if cols != list(range(cols[0], cols[-1] + 1)) or cols[-1] >= N_HCOLS:
          raise ValueError(f"ekf_lanes: row {i}'s H support {cols} is not a contiguous range within columns 0..8")
        self.h_off.append(self.H + [r for r, _ in self.h_entries].index(i))
        self.h_lo.append(cols[0])
        self.h_hi.append(cols[-1] + 1)
      else:                                    # a row never fused here: an empty support (its h is all zeros)
        self.h_off.append(self.H)
        self.h_lo.append(0)
        self.h_hi.append(0)


def tick_body(spec, resets, p, aux, out, work, fori=jax.lax.fori_loop):
  """The per-lane covariance tick on refs indexed by row: p [225] (P, updated in place), aux / out / work as
  `Layout` places them (out written). resets: ((cols, rows, how, var), ...) ekf._RESETS with their variances.
  Works on any refs whose rows are [lanes] vectors: Mosaic GPU shared memory, or `_Rows` (plain JAX arrays; then
  `fori` is a loop that carries their arrays). Loop bodies write through the refs and carry nothing."""
  n = N_ERR
  lay = Layout(spec)
  dt = spec.dt
  zero = aux[lay.innov] * 0.0    # a vector of zeros in the loaded vectors' layout (loop carries must match it)
  A = [[aux[lay.A + 3 * i + m] for m in range(3)] for i in range(3)]
  B = [[aux[lay.B + 3 * i + m] for m in range(3)] for i in range(3)]

  def s3(t):
    return (t[0] + t[1]) + t[2]

  def transition(v):
    """(F v)[0:9] for v [15] indexable (a column of P: F P; or a row: P F', F's blocks applied the same way)."""
    new = [v[m] + dt * v[3 + m] for m in range(3)]
    new += [v[3 + i] + (s3([A[i][m] * v[6 + m] for m in range(3)]) + s3([B[i][m] * v[12 + m] for m in range(3)]))
            for i in range(3)]
    new += [v[6 + i] + s3([B[i][m] * v[9 + m] for m in range(3)]) for i in range(3)]
    return new

  # ---- prediction (ekf._predict_cov): F P column by column, then (F P) F' row by row, in place
  def fp_col(c, _):
    new = transition([p[n * m + c] for m in range(n)])
    for r in range(9):
      p[n * r + c] = new[r]
    return None

  def fpf_row(r, _):
    new = transition([p[n * r + m] for m in range(n)])
    for m in range(9):
      p[n * r + m] = new[m]
    return None

  fori(0, n, fp_col, None)
  fori(0, n, fpf_row, None)

  def clamps(i, d):
    """ekf._condition's diagonal clamps of entry i given its (finite) variance d: stores s_i and lift_i."""
    # = sqrt(min(1, var_max / max(d, 1e-30))) as in the reference (Mosaic GPU lowers rsqrt, not sqrt)
    s = jax.lax.rsqrt(jnp.maximum(1.0, jnp.maximum(d, 1e-30) * (1.0 / spec.var_max[i])))
    work[lay.s + i] = s
    work[lay.lift + i] = jnp.maximum(spec.var_min[i] - d * (s * s), 0.0)

  # + Q on the diagonal; the symmetrisation leaves the diagonal as it is (0.5 (d + d) = d)
  for i in range(n):
    d = p[(n + 1) * i] + spec.q[i]
    p[(n + 1) * i] = d
    clamps(i, jnp.where(_finite(d), d, 0.0))
  s_all = [work[lay.s + j] for j in range(n)]

  def symmetrise_row(i, _):
    """ekf._condition with symmetrisation, on the pairs (i, j >= i); pairs (i, j < i) were done on row j."""
    s_i, lift_i = work[lay.s + i], work[lay.lift + i]
    for j in range(n):
      a, b = p[n * i + j], p[n * j + i]
      v = 0.5 * (a + b)
      v = jnp.where(_finite(v), v, 0.0) * (s_i * s_all[j])
      v = _where(i == j, v + lift_i, v)
      p[n * i + j] = _where(j >= i, v, a)
      p[n * j + i] = _where(j >= i, v, b)
    return None

  fori(0, n, symmetrise_row, None)

  # ---- gates on the predicted variances (ekf._gate): S_i = h_i' P h_i + R_i
  def h_row(i):
    """Row i of H over columns 0..8 ([9] vectors; exact zeros off its support)."""
    off, lo, hi = (_select(i, t, jnp.int32) for t in (lay.h_off, lay.h_lo, lay.h_hi))
    return [_where((c >= lo) & (c < hi), aux[off + c - lo], 0.0) for c in range(N_HCOLS)]

  def hdot(h, v):
    """h . v over columns 0..8, ascending (the order of the reference's sparse sums)."""
    t = h[0] * v[0]
    for c in range(1, N_HCOLS):
      t = t + h[c] * v[c]
    return t

  def p_times_h(h, rows):
    """u_r = (P h)_r = sum_c h_c P[r, c] into work's u rows, for r < rows (a loop over rows)."""
    def row(r, _):
      work[lay.u + r] = hdot(h, [p[n * r + c] for c in range(N_HCOLS)])
      return None
    fori(0, rows, row, None)

  def gate_row(i, _):
    h = h_row(i)
    p_times_h(h, N_HCOLS)
    S = hdot(h, [work[lay.u + c] for c in range(N_HCOLS)]) + _select(i, spec.R, jnp.float32)
    g = _select(i, spec.gate, jnp.float32)
    innov = aux[lay.innov + i]
    r = innov * innov / ((g * g) * S)
    out[lay.ratio + i] = jnp.where(_finite(r), r, 1e6)
    return None

  fori(0, N_ROWS, gate_row, None)
  enable = [aux[lay.en + i] > 0.5 for i in range(N_ROWS)]
  bad = [enable[i] & _not(out[lay.ratio + i] <= 1.0) for i in range(N_ROWS)]
  group_bad = {}
  for i, g in enumerate(spec.group_of_row):
    group_bad[g] = bad[i] if g not in group_bad else group_bad[g] | bad[i]
  accept = [enable[i] & _not(group_bad[spec.group_of_row[i]]) for i in range(N_ROWS)]
  for i in range(N_ROWS):
    out[lay.acc + i] = jnp.where(accept[i], 1.0, 0.0)
  for r in range(n):
    out[lay.dx + r] = zero

  # ---- sequential fusion of the accepted rows (the rolled form of ekf._fuse)
  def fuse_row(i, _):
    h = h_row(i)
    p_times_h(h, n)
    u = [work[lay.u + r] for r in range(n)]
    take = (out[lay.acc + i] > 0.5) & (_select(i, spec.used, jnp.int32) > 0)
    innov = jnp.where(take, aux[lay.innov + i], 0.0)
    c = jnp.where(take, 1.0 / (hdot(h, u) + _select(i, spec.R, jnp.float32)), 0.0)
    g = c * (innov - hdot(h, [out[lay.dx + k] for k in range(N_HCOLS)]))

    def update(r, _):
      ur = work[lay.u + r]
      for j in range(n):
        p[n * r + j] = p[n * r + j] - c * (ur * u[j])
      out[lay.dx + r] = out[lay.dx + r] + g * ur
      return None

    fori(0, n, update, None)
    return None

  fori(0, N_ROWS, fuse_row, None)

  # ---- timeout resets and the closing clean-up (ekf._reset_and_condition: _condition without symmetrisation)
  resettable = set()
  for k in range(n):
    work[lay.clr + k] = zero
    work[lay.nv + k] = zero
  for b, (cols, rows, how, var) in enumerate(resets):
    fused = accept[rows[0]]
    for r in rows[1:]:
      fused = (fused & accept[r]) if how == "all" else (fused | accept[r])
    do = (aux[lay.due + b] > 0.5) & _not(fused)
    for c in cols:
      work[lay.clr + c] = jnp.where(do, 1.0, 0.0)
      work[lay.nv + c] = jnp.where(do, var, 0.0)
      resettable.add(c)
  clr = [work[lay.clr + j] > 0.5 if j in resettable else None for j in range(n)]
  for i in range(n):
    d = p[(n + 1) * i]
    if clr[i] is not None:
      d = jnp.where(clr[i], work[lay.nv + i], d)
    clamps(i, jnp.where(_finite(d), d, 0.0))
  s_all = [work[lay.s + j] for j in range(n)]

  def clean_row(i, _):
    cl_i = work[lay.clr + i] > 0.5
    nv_i, s_i, lift_i = work[lay.nv + i], work[lay.s + i], work[lay.lift + i]
    for j in range(n):
      v = p[n * i + j]
      m = cl_i if clr[j] is None else cl_i | clr[j]
      v = jnp.where(m, 0.0, v)
      v = _where(i == j, v + nv_i, v)
      v = jnp.where(_finite(v), v, 0.0) * (s_i * s_all[j])
      p[n * i + j] = _where(i == j, v + lift_i, v)
    return None

  fori(0, n, clean_row, None)


def pack(spec, P, A, B, H, innov, enable, due):
  """Batch-major inputs -> (P [225, B], aux [n_aux, B]) in the kernel's vehicle-minor layout."""
  nb = P.shape[0]
  f32 = jnp.float32
  hd = jnp.stack([H[:, i, c] for i, c in spec.h_entries()], axis=1)
  aux = jnp.concatenate([A.reshape(nb, 9), B.reshape(nb, 9), hd, innov, enable.astype(f32), due.astype(f32)], axis=1)
  return P.reshape(nb, N_ERR * N_ERR).astype(f32).T, aux.astype(f32).T


def unpack(Pt, out, nb):
  """The kernel's outputs -> (P [B, 15, 15], dx [B, 15], ratio [B, 13], accept [B, 13] bool)."""
  o = out[:, :nb].T
  return (Pt[:, :nb].T.reshape(nb, N_ERR, N_ERR), o[:, :N_ERR], o[:, N_ERR:N_ERR + N_ROWS],
          o[:, N_ERR + N_ROWS:] > 0.5)


class _Rows:
  """A [rows, lanes] jnp array as a mutable ref indexed by row (static or traced): `tick_body` in plain JAX."""

  def __init__(self, x):
    self.x = x

  def __getitem__(self, k):
    return jax.lax.dynamic_index_in_dim(self.x, k, keepdims=False)

  def __setitem__(self, k, v):
    self.x = jax.lax.dynamic_update_index_in_dim(self.x, jnp.broadcast_to(v, self.x.shape[1:]), k, 0)


def cov_tick_xla(spec, resets, P, A, B, H, innov, enable, due):
  """`tick_body` in plain JAX over [B] vectors (a reference for the kernel's arithmetic; runs on any backend).

  The loops carry the refs' arrays through `fori_loop`, so this is traced as the kernel is."""
  nb = P.shape[0]
  Pt, aux = pack(spec, P, A, B, H, innov, enable, due)
  lay = Layout(spec)
  refs = [_Rows(Pt), _Rows(aux), _Rows(jnp.zeros((lay.n_out, nb), jnp.float32)),
          _Rows(jnp.zeros((lay.n_work, nb), jnp.float32))]
  tick_body(spec, resets, *refs, fori=_carrying(refs))
  return unpack(refs[0].x, refs[2].x, nb)


def _carrying(refs):
  """A fori_loop for `tick_body` on _Rows refs: the refs' arrays are the loop's carry (bodies write through refs)."""
  def fori(lo, hi, body, init):
    def step(k, xs):
      for r, x in zip(refs, xs):
        r.x = x
      body(k, init)
      return tuple(r.x for r in refs)
    for r, x in zip(refs, jax.lax.fori_loop(lo, hi, step, tuple(r.x for r in refs))):
      r.x = x
    return init
  return fori


@functools.partial(jax.jit, static_argnames=("spec", "resets", "interpret"))
def cov_tick(spec, resets, P, A, B, H, innov, enable, due, interpret=None):
  """The tick's covariance work for a batch of B vehicles as one Mosaic GPU kernel (an NVIDIA Hopper GPU).

  P: [B, 15, 15] symmetric covariance before the prediction. A, B: [B, 3, 3] F's blocks (`ekf._predict_nominal`).
  H: [B, 13, 15] observation Jacobian (entries on `spec.h_entries()` read). innov: [B, 13]. enable: [B, 13] bool.
  due: [B, 3] bool, the timeout resets due (order ekf._RESETS). resets: `resets_of(cfg)`.
  Returns (P [B, 15, 15], dx [B, 15], ratio [B, 13], accept [B, 13] bool).
  interpret: Mosaic GPU's interpreter parameters (`InterpretGPUParams()`: runs on the CPU, for tests)."""
  from jax.experimental import pallas as pl
  import jax.experimental.pallas.mosaic_gpu as plgpu
  nb = P.shape[0]
  bp = -(-nb // LANES) * LANES
  lay = Layout(spec)
  Pt, aux = pack(spec, P, A, B, H, innov, enable, due)
  Pt, aux = (jnp.pad(x, ((0, 0), (0, bp - nb))) for x in (Pt, aux))
  f32 = jnp.float32

  def kernel(p_gmem, aux_gmem, po_gmem, out_gmem, p_smem, aux_smem, out_smem, work_smem, bars):
    blk = pl.ds(jax.lax.axis_index("b") * LANES, LANES)
    plgpu.copy_gmem_to_smem(p_gmem.at[:, blk], p_smem, bars.at[0])
    plgpu.copy_gmem_to_smem(aux_gmem.at[:, blk], aux_smem, bars.at[1])
    plgpu.barrier_wait(bars.at[0])
    plgpu.barrier_wait(bars.at[1])
    tick_body(spec, resets, p_smem, aux_smem, out_smem, work_smem)
    plgpu.commit_smem()
    plgpu.copy_smem_to_gmem(p_smem, po_gmem.at[:, blk])
    plgpu.copy_smem_to_gmem(out_smem, out_gmem.at[:, blk])
    plgpu.wait_smem_to_gmem(0)

  Po, out = plgpu.kernel(
    kernel, out_type=(jax.ShapeDtypeStruct((N_ERR * N_ERR, bp), f32), jax.ShapeDtypeStruct((lay.n_out, bp), f32)),
    grid=(bp // LANES,), grid_names=("b",),
    scratch_types=[plgpu.SMEM((N_ERR * N_ERR, LANES), f32), plgpu.SMEM((lay.n_aux, LANES), f32),
                   plgpu.SMEM((lay.n_out, LANES), f32), plgpu.SMEM((lay.n_work, LANES), f32),
                   plgpu.Barrier(num_arrivals=1, num_barriers=2)],
    # Lane semantics (jax 0.10's default; 0.11 defaults to Warpgroup, whose layout inference took > 10 min on this
    # kernel on the host CPU, where Lane lowers it in about a second)
    compiler_params=None if interpret else plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Lane),
    interpret=interpret)(Pt, aux)
  return unpack(Po, out, nb)


def resets_of(cfg):
  """ekf._RESETS with their variances, as the static tuple the kernel is traced for."""
  from specguard_jax import ekf as ekf_lib
  return tuple((tuple(cols), tuple(rows), how, float(v))
               for (cols, rows, how), v in zip(ekf_lib._RESETS, ekf_lib._reset_variances(cfg)))
