"""The EKF tick's covariance work with one vehicle per GPU lane: a Pallas Mosaic GPU kernel (NVIDIA Hopper).

What it computes is `ekf._cov_tick` (the XLA form, the reference and the CPU path): the prediction of P, the tick's
symmetrisation and clamps, the grouped innovation gates, the sequential scalar fusion of the accepted rows (P
updated row by row, `ekf._rows_rolled`'s form; `_cov_tick`'s low-rank form is the same filter), the timeout resets and
the closing clean-up. It returns what `_cov_tick` returns (P, dx [B, 15], test
ratio [B, 13], accept [B, 13] bool), equal to float32 rounding (`tests/test_ekf_lanes.py`).

One program owns 128 vehicles, one per thread of a warpgroup, so in the kernel every per-vehicle quantity is a [128]
vector and the tick is straight-line per-lane code with P's symmetry and F's / H's sparsity resolved statically: no
shuffles, no masked reductions, no [B, 15, 15] intermediates in global memory (what the XLA form's ~60 kernels per
tick and the Triton tile kernel `ekf_kernel.py` pay for). P lives in registers during the tick.
Memory layout: P batch-major as the env holds it, no transposes: packed ([B, 121]: its upper triangle and a zero,
`ekf.pack_p`; the env keeps P so with this kernel, `ekf_init(p_layout="packed")`); each program copies its 128
vehicles' contiguous rows into shared memory with one TMA copy and each lane reads its own vehicle's entries at an
odd stride (conflict-free); P written back in place. The other inputs vehicle-minor ([n_aux, B], `pack_aux`, one
fusion of XLA's), the outputs over them: 98 KB per program, two per SM. (Session 35's layout, XLA transposing the inputs to
vehicle-minor [rows, B] and back, moved ~3x the bytes: 207 / 129 us per drone tick against 140 / 105.)

`prep_tick` (what `ekf.ekf_step` runs with fused="lanes"): the same kernel with the tick's inputs prepared per lane
too: the nominal state's prediction, F's blocks, H and the innovations from the state and the readings
(`prep_inputs`, the arithmetic of ekf._predict_nominal / ekf._innovations), so XLA hands the kernel 51 rows of
state and reading components instead of deriving `pack_aux`'s 69-75 rows (each row of that concatenate fusion
re-derived its value from ~10 operands: 24 us per rover tick at 65,536 vehicles, session 39's profile). The
trainer's env step at 65,536 envs on one H200 (session 40): rover 1.986 ms against 2.067 with `cov_tick`, drone 2.773
against 2.798.

Lowering: `plgpu.kernel` with Lane semantics. With jax 0.10 / 0.11 `pallas_call` lowers only to Triton on GPUs,
and Triton did not compile this straight-line form in 9 minutes (session 11); jax 0.11's default Warpgroup semantics
did not in 285 s (its layout inference grows faster than linearly with the kernel's length, session 34), where Lane
semantics compiles the whole tick in 3-8 s. Measured (BENCHMARKS.md sessions 35-36, H200, 65,536 vehicles, us per
tick, every row fresh / GPS rows stale): drone 139.9 / 104.6 against XLA's 677.9 / 488.1 and the Triton kernel's
453.7 / 344.7. A form that loops over P in shared memory (to keep the kernel short) compiled as fast but ran slower
than XLA (latency-bound on shared memory), so the tick stays straight-line code with P in registers.
Registers (ptxas, `MOSAIC_GPU_DUMP_PTXAS=1 python bench/ekf_lanes.py --prep`): 255 per thread, 4 B of spills since
the rows are fused with P updated row by row (session 41); the low-rank form held every row's P h_i and u_i to the
end and spilled ~1.1 KB per thread on the GPS tick (136 B on the rover's other ticks): `prep_tick` at 65,536 rovers on
an H200, GPS-free / GPS tick, 63.2 / 69.4 us per tick against 67.5 / 162.9 (drone 62.0 / 70.7 against 66.0 / 137.6),
the trainer's env step rover 2.005 -> 1.894 ms, drone 2.779 -> 2.696.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax.ekf import N_ERR, N_PACKED, TRI, TRI_INDEX, as_square, layout_like, pack_p, p_layout, tri_index

N_ROWS = 13
LANES = 128     # vehicles per program: one per thread of a warpgroup


def _finite(x):
  """Elementwise isfinite (Mosaic GPU lowers abs and compare, not is_finite)."""
  return jnp.abs(x) < jnp.inf


class Layout:
  """Offsets of a vehicle's inputs in aux and of its outputs in out (the outputs overwrite the inputs in place).

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


def _layout_inputs(spec, load):
  """The tick's inputs besides P from aux rows placed as `Layout` places them: dict(A, B [3][3], hd {row: {col: h}},
  innov [13], enable [13] bool, due [3] bool), every value a [lanes] vector."""
  o = Layout(spec)
  hd = {}
  for e, (i, c) in enumerate(spec.h_entries()):
    hd.setdefault(i, {})[c] = load(o.H + e)
  return dict(A=[[load(o.A + 3 * i + m) for m in range(3)] for i in range(3)],
              B=[[load(o.B + 3 * i + m) for m in range(3)] for i in range(3)], hd=hd,
              innov=[load(o.innov + i) for i in range(N_ROWS)], enable=[load(o.en + i) > 0.5 for i in range(N_ROWS)],
              due=[load(o.due + b) > 0.5 for b in range(3)])


def tick_body(spec, resets, p_load, p_store, load, store, stage: str = "full", inputs=None, o=None):
  """The per-lane covariance tick as straight-line code on [lanes] vectors (one vehicle per lane).

  p_load(i, j) -> P[i, j] and p_store(i, j, v) sets P[i, j] and P[j, i], both for i <= j; load(k) -> entry k of aux,
  store(k, v) sets entry k of out (both as `Layout` places them); every value a [lanes] vector. Every load comes
  before the first store, so P and out may overwrite their inputs in place (the kernel's shared memory does).
  resets: ((cols, rows, how, var), ...) ekf._RESETS with their variances (`resets_of`).
  stage: "full" (the tick), or a probe for compile and run time (bench/ekf_lanes.py): "predict" (the prediction and
  its clamps alone, the other outputs zero) or "copy" (P and out copied from P and the first rows of aux).
  inputs: the inputs besides P as `_layout_inputs` returns them (default: loaded from `Layout`'s rows); o: where the
  outputs go (attributes dx, ratio, acc, n_out; default `Layout(spec)`)."""
  n = N_ERR
  o = Layout(spec) if o is None else o
  tri = [p_load(i, j) for (i, j) in TRI]
  if stage == "copy":      # memory floor: every output row from an input row
    for k, (i, j) in enumerate(TRI):
      p_store(i, j, tri[k] * 1.0)
    for k in range(o.n_out):
      store(k, load(k) * 1.0)
    return
  P = [[tri[tri_index(i, j)] for j in range(n)] for i in range(n)]
  inputs = _layout_inputs(spec, load) if inputs is None else inputs
  A, B = inputs["A"], inputs["B"]
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
    zero = inputs["innov"][0] * 0.0
    for r in range(o.n_out):
      store(r, zero)
    return

  # ---- gates (ekf._gate) and the sequential fusion of the accepted rows
  hd = inputs["hd"]
  used = [i for i in range(N_ROWS) if spec.used[i]]

  def hdot(i, v):   # h_i . v, v indexable by error-state column
    t = None
    for c, h in hd[i].items():
      t = h * v[c] if t is None else t + h * v[c]
    return t

  # Gates from the predicted P: S_i = h_i' P h_i + R_i as a quadratic form over h_i's few entries (no P h_i vector
  # is kept for later: a [15] vector per row held across the fusion spilled registers to local memory, session 41).
  innov, enable = inputs["innov"], inputs["enable"]
  ratio, bad = [], []
  for i in range(N_ROWS):
    if i in used:
      S = hdot(i, {c: hdot(i, [P[c][r] for r in range(n)]) for c in hd[i]}) + spec.R[i]
    else:
      S = spec.R[i] + 0.0 * innov[i]
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

  # Sequential scalar fusion with P updated after each row (ekf._rows_rolled's form; ekf._rows_unrolled's low-rank
  # form, the XLA reference, is the same filter): per row P h_i from the current P, then P -= c (P h_i)(P h_i)' on
  # the triangle. Live across rows: P's 120 entries, dx, one [15] vector; the low-rank form kept every row's P_0 h_i
  # and u_i until the end (~390 values: 255 registers and ~1.1 KB of spills per thread on the GPS tick).
  dx = [None] * n
  for i in used:
    pht = [hdot(i, [P[c][r] for c in range(n)]) for r in range(n)]
    c = jnp.where(accept[i], 1.0 / (hdot(i, pht) + spec.R[i]), 0.0)
    g = c * (innov[i] - (hdot(i, dx) if dx[0] is not None else 0.0))
    dx = [(g * pht[r]) if dx[r] is None else dx[r] + g * pht[r] for r in range(n)]
    cp = [c * pht[r] for r in range(n)]
    for (a, b) in TRI:
      P[a][b] = P[b][a] = P[a][b] - cp[a] * pht[b]
  Pn = P

  # ---- timeout resets, closing clean-up (ekf._reset_and_condition)
  cleared = [None] * n
  new_var = [0.0] * n
  for b, (cols, rows, how, var) in enumerate(resets):
    fl = [accept[r] for r in rows]
    fused = fl[0]
    for f in fl[1:]:
      fused = (fused & f) if how == "all" else (fused | f)
    do = inputs["due"][b] & ~fused
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


def pack_aux(spec, A, B, H, innov, enable, due):
  """The tick's per-vehicle inputs besides P, vehicle-minor: aux [n_aux, B] float32, rows as `Layout` places them
  (XLA writes it in one fusion, reading each input coalesced; batch-major [B, n_aux] it reads them ~32 arrays per
  warp: 70 us per drone tick at 65,536 vehicles, session 36)."""
  nb = A.shape[0]
  hd = jnp.stack([H[:, i, c] for i, c in spec.h_entries()], axis=1)
  aux = jnp.concatenate([A.reshape(nb, 9), B.reshape(nb, 9), hd, innov, enable.astype(jnp.float32),
                         due.astype(jnp.float32)], axis=1)
  return aux.astype(jnp.float32).T


def _unpack_out(out, nb, spec):
  """out [>= n_out, >= B] -> (dx [B, 15], ratio [B, 13], accept [B, 13] bool)."""
  lay = Layout(spec)
  o = out[:lay.n_out, :nb].T
  return o[:, lay.dx:lay.dx + N_ERR], o[:, lay.ratio:lay.ratio + N_ROWS], o[:, lay.acc:lay.acc + N_ROWS] > 0.5


def _packed_io(fn):
  """fn on P packed [B, 121] -> the same taking and returning P in any layout (ekf.P_LAYOUTS)."""
  @functools.wraps(fn)
  def wrapped(spec, resets, P, *args, **kw):
    if p_layout(P) == "packed":
      return fn(spec, resets, P, *args, **kw)
    Pk, *rest = fn(spec, resets, pack_p(as_square(P)), *args, **kw)
    return (layout_like(as_square(Pk), P), *rest)
  return wrapped


@_packed_io
def cov_tick_xla(spec, resets, P, A, B, H, innov, enable, due, stage: str = "full"):
  """`tick_body` in plain JAX over [B] vectors: the kernel's arithmetic on any backend (tests; eager on the CPU is
  quicker than compiling its ~10^4 operations). Arguments and results as `cov_tick`'s."""
  aux = pack_aux(spec, A, B, H, innov, enable, due)
  p_out, out = dict(enumerate(P.T)), {}

  def p_store(i, j, v):
    p_out[TRI_INDEX[(i, j)]] = v

  tick_body(spec, resets, lambda i, j: P[:, TRI_INDEX[(i, j)]], p_store, lambda k: aux[k], out.__setitem__, stage)
  return (jnp.stack([p_out[k] for k in range(N_PACKED)], axis=1),
          *_unpack_out(jnp.stack([out[k] for k in range(len(out))]), P.shape[0], spec))


JAX_VERSION = tuple(int(x) for x in jax.__version__.split(".")[:2])
# P written in place through a jax Ref (jax >= 0.11; jax 0.10's Pallas cannot discharge a Ref into a Mosaic GPU kernel)
IN_PLACE = JAX_VERSION >= (0, 11)


@functools.partial(jax.jit, static_argnames=("spec", "resets", "stage", "in_place"))
@_packed_io
def cov_tick(spec, resets, P, A, B, H, innov, enable, due, stage: str = "full", in_place: bool = IN_PLACE):
  """The tick's covariance work for a batch of B vehicles as one Mosaic GPU kernel (NVIDIA Hopper or newer).

  P: [B, 121] packed (`ekf.pack_p`, the env's layout with this kernel), returned packed; or P in another layout
  (ekf.P_LAYOUTS), returned in it (packed and unpacked around the kernel). The covariance before the prediction.
  A, B: [B, 3, 3] F's blocks (`ekf._predict_nominal`). H: [B, 13, 15] observation Jacobian (its entries on
  `spec.h_entries()` are read). innov: [B, 13]. enable: [B, 13] bool. due: [B, 3] bool, the timeout resets due
  (order ekf._RESETS). spec: `ekf._cov_spec`; resets: `resets_of`. Returns (P, dx [B, 15], ratio [B, 13],
  accept [B, 13] bool). stage: see `tick_body`.

  Layout: P batch-major as the env holds it, no transposes: [B, 121] row-major viewed as [B 121 / 128, 128], so
  program b's 128 vehicles are the rows 121 b + [0, 121), one TMA copy into shared memory, where lane v reads its
  vehicle's entry k at word 121 v + k (121 is odd: the 32 lanes of a warp hit 32 banks); written back in place and
  copied out the same way. The other inputs vehicle-minor (`pack_aux`, [n_aux, B]: program b's columns, row k a
  [128] vector), the outputs written over them and copied out to [n_out, B]. 98 KB per program, two per SM.
  in_place: P's output is its input's buffer (a jax Ref; default on jax >= 0.11), else a new array (XLA then copies
  it into the loop's carry: ~16 us per tick at 65,536 vehicles)."""
  @jax.custom_batching.custom_vmap
  def call(*args):
    return _kernel(spec, resets, *args, stage=stage, in_place=in_place)

  @call.def_vmap
  def _(axis_size, in_batched, *args):   # an outer vmap (a sweep's members): its axis joins the kernel's batch
    args = [x if b else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, b in zip(args, in_batched)]
    outs = call(*[x.reshape((-1,) + x.shape[2:]) for x in args])
    return tuple(o.reshape((axis_size, -1) + o.shape[1:]) for o in outs), (True,) * len(outs)

  return call(P, A, B, H, innov, enable, due)


def _kernel(spec, resets, P, A, B, H, innov, enable, due, stage, in_place):
  """cov_tick's kernel call on P packed [B, 121] (B unbatched: one flat batch)."""
  lay = Layout(spec)

  def body(p_load, p_store, load, store):
    tick_body(spec, resets, p_load, p_store, load, store, stage)

  Po, out = _lanes_call(P, pack_aux(spec, A, B, H, innov, enable, due), lay.n_aux, lay.n_out, body, in_place)
  return (Po, *_unpack_out(out, P.shape[0], spec))


def _lanes_call(P, aux, n_rows, n_out, body, in_place):
  """One Mosaic GPU kernel over P packed [B, 121] and aux [n_in, B] (vehicle-minor): each program copies its 128
  vehicles' P rows and aux columns into shared memory (aux into the first n_in of n_rows >= n_in rows), runs
  body(p_load, p_store, load, store) per lane, writes P back (in place with in_place) and the aux rows [0, n_out) out.
  Returns (P packed [B, 121], out [n_out, B_padded])."""
  from jax.experimental import pallas as pl
  import jax.experimental.pallas.mosaic_gpu as plgpu
  nb = P.shape[0]
  bp = -(-nb // LANES) * LANES
  f32 = jnp.float32
  Pg = jnp.pad(P.astype(f32), ((0, bp - nb), (0, 0))).reshape(bp * N_PACKED // LANES, LANES)
  n_in = aux.shape[0]
  aux = jnp.pad(aux, ((0, 0), (0, bp - nb)))

  def kernel(p_gmem, aux_gmem, *refs):
    *po_gmem, out_gmem, p_smem, aux_smem, p_bar, aux_bar = refs
    po_gmem = po_gmem[0] if po_gmem else p_gmem      # in place: P's ref is the output
    b = jax.lax.axis_index("b")
    blk = pl.ds(b * LANES, LANES)
    plgpu.copy_gmem_to_smem(p_gmem.at[pl.ds(b * N_PACKED, N_PACKED)], p_smem, p_bar)
    plgpu.copy_gmem_to_smem(aux_gmem.at[:, blk], aux_smem.at[pl.ds(0, n_in)], aux_bar)
    p_vm = p_smem.reshape(LANES * N_PACKED).reshape(LANES, N_PACKED)     # [vehicle, entry] view
    plgpu.barrier_wait(p_bar)
    plgpu.barrier_wait(aux_bar)

    def p_store(i, j, v):
      p_vm[:, TRI_INDEX[(i, j)]] = v

    def store(k, v):
      aux_smem[k] = v

    body(lambda i, j: p_vm[:, TRI_INDEX[(i, j)]], p_store, lambda k: aux_smem[k], store)
    plgpu.commit_smem()
    plgpu.copy_smem_to_gmem(p_smem, po_gmem.at[pl.ds(b * N_PACKED, N_PACKED)])
    plgpu.copy_smem_to_gmem(aux_smem.at[pl.ds(0, n_out)], out_gmem.at[:, blk])
    plgpu.wait_smem_to_gmem(0)

  out_type = jax.ShapeDtypeStruct((n_out, bp), f32)
  call = plgpu.kernel(
    kernel, out_type=out_type if in_place else (jax.ShapeDtypeStruct(Pg.shape, f32), out_type),
    grid=(bp // LANES,), grid_names=("b",),
    scratch_types=[plgpu.SMEM((N_PACKED, LANES), f32), plgpu.SMEM((n_rows, LANES), f32),
                   plgpu.Barrier(num_arrivals=1), plgpu.Barrier(num_arrivals=1)],
    compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Lane))
  if in_place:    # P's buffer written in place (the custom call aliases it: no copy of P after the kernel)
    p_ref = jax.new_ref(Pg)
    out = call(p_ref, aux)
    Po = jax.freeze(p_ref)
  else:
    Po, out = call(Pg, aux)
  return Po.reshape(bp, N_PACKED)[:nb], out


def resets_of(cfg):
  """ekf._RESETS with their variances, as the static tuple the kernel is traced for."""
  from specguard_jax import ekf as ekf_lib
  return tuple((tuple(cols), tuple(rows), how, float(v))
               for (cols, rows, how), v in zip(ekf_lib._RESETS, ekf_lib._reset_variances(cfg)))


# ----------------------------------------------------------------------------------------------------------------------
# The tick with its inputs prepared in the kernel: F's blocks, H and the innovations computed per lane from the
# nominal state and the readings (what ekf._predict_nominal and ekf._innovations do in XLA). The kernel's input block
# is then 51 rows, each a copy of one state or reading component, where `cov_tick`'s is 69-75 rows that XLA computes
# in one concatenate fusion, every row re-deriving its value from ~10 operands (rover profile, session 39: 24 us of
# that fusion per tick against the kernel's 47). The prepared inputs stay in registers (through shared memory, as
# `cov_tick`'s kernel reads its inputs, was slower: one H200, 65,536 envs, the trainer's env, session 40,
# bench/env_step_ab.py, ms per step: rover 1.986 in registers, 2.003 through shared memory, 2.066-2.068 with
# `cov_tick`; drone 2.773 / 2.798 / 2.797-2.799).
_PREP_IN = (("quat", 4), ("vel", 3), ("pos", 3), ("gb", 3), ("ab", 3), ("gyro", 3), ("accel", 3), ("z", N_ROWS),
            ("en", N_ROWS), ("due", 3))
_PREP_OUT = (("dx", N_ERR), ("ratio", N_ROWS), ("acc", N_ROWS), ("innov", N_ROWS), ("pos", 3), ("vel", 3),
             ("quat", 4))


def _offsets(fields):
  out, k = {}, 0
  for name, size in fields:
    out[name] = k
    k += size
  return out, k


class PrepLayout:
  """Rows of `prep_tick`'s inputs in aux and of its outputs over them (the kernel's out block: rows [0, n_out)).

  in (`_PREP_IN`): quat [4], vel [3], pos [3], gyro_bias [3], accel_bias [3] (the nominal state before the tick),
  gyro [3], accel [3] (the IMU sample, unclipped), z [13] (`ekf._measurement_rows`), enable [13] (1.0 / 0.0, the flow
  rows before the predicted-height check), due [3]. out (`_PREP_OUT`): dx [15], ratio [13], accept [13] (1.0 / 0.0),
  innov [13] (before the gates), the predicted pos [3], vel [3], quat [4]."""

  def __init__(self):
    self.inp, self.n_in = _offsets(_PREP_IN)
    self.out, self.n_out = _offsets(_PREP_OUT)
    self.dx, self.ratio, self.acc = self.out["dx"], self.out["ratio"], self.out["acc"]
    self.n_rows = max(self.n_in, self.n_out)


def _sqrt(x):
  """sqrt(x) for x > 0 as x rsqrt(x) (jax 0.10's Mosaic GPU lowers rsqrt, not sqrt); NaN at 0 and inf, where
  its callers fall back as they do for sqrt's 0 and inf."""
  return x * jax.lax.rsqrt(x)


def _q_mul(a, b):
  aw, ax, ay, az = a
  bw, bx, by, bz = b
  return [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
          aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw]


def _q_rotvec(v):
  """ekf._rotvec_to_quat on components."""
  a2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
  small = a2 < 1e-8
  a = _sqrt(jnp.where(small, 1.0, a2))
  s = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * a) / a)
  c = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * a))
  return [c, s * v[0], s * v[1], s * v[2]]


def _q_normalize(q):
  """ekf._normalize_quat on components."""
  n = _sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
  ok = _finite(n) & (n > 1e-6)
  d = jnp.where(ok, n, 1.0)
  return [jnp.where(ok, x / d, unit) for x, unit in zip(q, (1.0, 0.0, 0.0, 0.0))]


def _q_rot(q):
  """math3d.quat_to_rot on components: [3][3]."""
  w, x, y, z = q
  return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def prep_inputs(spec, flow_min_height: float, x: dict):
  """ekf._predict_nominal and ekf._innovations per lane. x: the `PrepLayout` inputs by name, lists of [lanes]
  vectors. Returns (the inputs of `tick_body` as `_layout_inputs` gives them, the innovations before the gates [13],
  the predicted pos [3], vel [3], quat [4])."""
  from specguard_jax.sensors import ACCEL_RANGE, GRAVITY, GYRO_RANGE
  dt = spec.dt
  w = [jnp.clip(g, -GYRO_RANGE, GYRO_RANGE) - b for g, b in zip(x["gyro"], x["gb"])]
  a = [jnp.clip(f, -ACCEL_RANGE, ACCEL_RANGE) - b for f, b in zip(x["accel"], x["ab"])]
  q0 = x["quat"]
  quat = _q_normalize(_q_mul(q0, _q_rotvec([c * dt for c in w])))
  rm = _q_rot(_q_mul(q0, _q_rotvec([0.5 * c * dt for c in w])))
  ra = [rm[i][0] * a[0] + rm[i][1] * a[1] + rm[i][2] * a[2] for i in range(3)]
  acc_w = [ra[0], ra[1], ra[2] - GRAVITY]
  pos = [p + v * dt + 0.5 * c * dt * dt for p, v, c in zip(x["pos"], x["vel"], acc_w)]
  vel = [v + c * dt for v, c in zip(x["vel"], acc_w)]
  zero = 0.0 * ra[0]
  A = [[zero, ra[2] * dt, -ra[1] * dt], [-ra[2] * dt, zero, ra[0] * dt], [ra[1] * dt, -ra[0] * dt, zero]]
  B = [[-rm[i][m] * dt for m in range(3)] for i in range(3)]

  # ekf._linearise at the predicted state
  r = _q_rot(quat)
  vb = [r[0][c] * vel[0] + r[1][c] * vel[1] + r[2][c] * vel[2] for c in range(3)]
  hgt = jnp.maximum(pos[2], flow_min_height)
  yaw = jnp.arctan2(r[1][0], r[0][0])
  pred = pos + vel + [pos[2], yaw, vb[0] / hgt, vb[1] / hgt, vb[0], vb[1], vb[2]]
  col = [[r[0][k], r[1][k], r[2][k]] for k in range(3)]                       # dvb / dvel, row k
  dth = [[c[1] * vel[2] - c[2] * vel[1], c[2] * vel[0] - c[0] * vel[2], c[0] * vel[1] - c[1] * vel[0]]
         for c in col]                                                           # dvb / dtheta, row k
  nrm = r[0][0] * r[0][0] + r[1][0] * r[1][0]
  dyaw = [-r[0][0] * r[2][0] / nrm, -r[1][0] * r[2][0] / nrm]
  dhgt = jnp.where(pos[2] > flow_min_height, 1.0, jnp.where(pos[2] == flow_min_height, 0.5, 0.0))
  H = {i: {i: 1.0} for i in range(6)}
  H[6] = {2: 1.0}
  H[7] = {6: dyaw[0], 7: dyaw[1], 8: 1.0 + zero}
  for k in range(2):
    H[8 + k] = {2: -vb[k] / (hgt * hgt) * dhgt, **{3 + m: col[k][m] / hgt for m in range(3)},
                **{6 + m: dth[k][m] / hgt for m in range(3)}}
  for k in range(3):
    H[10 + k] = {**{3 + m: col[k][m] for m in range(3)}, **{6 + m: dth[k][m] for m in range(3)}}
  hd = {}
  for i, c in spec.h_entries():
    h = H[i][c]
    hd.setdefault(i, {})[c] = h + zero if isinstance(h, float) else h
  innov = [zi - pi for zi, pi in zip(x["z"], pred)]
  innov[7] = jnp.arctan2(jnp.sin(innov[7]), jnp.cos(innov[7]))
  low_ok = pos[2] >= flow_min_height
  enable = [(e > 0.5) & low_ok if i in (8, 9) else e > 0.5 for i, e in enumerate(x["en"])]
  inputs = dict(A=A, B=B, hd=hd, innov=innov, enable=enable, due=[d > 0.5 for d in x["due"]])
  return inputs, innov, pos, vel, quat


def prep_body(spec, resets, flow_min_height, p_load, p_store, load, store):
  """The tick with its inputs prepared per lane (`prep_inputs`, held in registers), then `tick_body`; loads and
  stores as `tick_body`'s, rows as `PrepLayout` places them."""
  lay = PrepLayout()
  x = {name: [load(lay.inp[name] + k) for k in range(size)] for name, size in _PREP_IN}
  inputs, innov, pos, vel, quat = prep_inputs(spec, flow_min_height, x)
  # Stored before the tick (every input is loaded by now): the predicted state is not held in registers through it.
  for name, vals in (("innov", innov), ("pos", pos), ("vel", vel), ("quat", quat)):
    for k, v in enumerate(vals):
      store(lay.out[name] + k, v)
  tick_body(spec, resets, p_load, p_store, load, store, inputs=inputs, o=lay)


def pack_prep(quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due):
  """`prep_tick`'s inputs [B, ...] -> aux [51, B] float32 vehicle-minor (rows as `PrepLayout` places them)."""
  parts = (quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due)
  return jnp.concatenate([jnp.asarray(p).astype(jnp.float32) for p in parts], axis=1).T


def _unpack_prep(out, nb):
  """out [64, >= B] (rows `_PREP_OUT`) -> (dx, ratio, accept bool, innov, pos, vel, quat), each [B, ...]."""
  offsets, n_out = _offsets(_PREP_OUT)
  o = out[:n_out, :nb].T
  res = []
  for name, size in _PREP_OUT:
    v = o[:, offsets[name]:offsets[name] + size]
    res.append(v > 0.5 if name == "acc" else v)
  return tuple(res)


@_packed_io
def prep_tick_xla(spec, resets, P, *inputs, flow_min_height: float):
  """`prep_body` in plain JAX over [B] vectors (tests, the CPU), aux rows in a dict standing in for shared memory.
  Arguments and results as `prep_tick`'s."""
  mem = dict(enumerate(pack_prep(*inputs)))
  p_out = dict(enumerate(P.T))

  def p_store(i, j, v):
    p_out[TRI_INDEX[(i, j)]] = v

  prep_body(spec, resets, flow_min_height, lambda i, j: P[:, TRI_INDEX[(i, j)]], p_store, mem.__getitem__,
            mem.__setitem__)
  nb = P.shape[0]
  o = jnp.stack([jnp.broadcast_to(mem[k], (nb,)) for k in range(PrepLayout().n_out)])
  return (jnp.stack([p_out[k] for k in range(N_PACKED)], axis=1), *_unpack_prep(o, nb))


@functools.partial(jax.jit, static_argnames=("spec", "resets", "flow_min_height", "in_place"))
@_packed_io
def prep_tick(spec, resets, P, quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due, *,
              flow_min_height: float, in_place: bool = IN_PLACE):
  """The whole EKF tick but the injection and the records as one Mosaic GPU kernel: the nominal state's prediction,
  H, the innovations (`prep_inputs`) and `cov_tick`'s covariance work, per lane.

  P: [B, 121] packed (or any layout, returned in it). quat [B, 4], vel, pos, gyro_bias, accel_bias [B, 3]: the
  nominal state before the tick; gyro, accel [B, 3]: the IMU sample; z [B, 13]: `ekf._measurement_rows`; enable
  [B, 13] bool (the flow rows before the predicted-height check); due [B, 3] bool; flow_min_height: the EKF
  config's (m). Returns (P, dx [B, 15], ratio
  [B, 13], accept [B, 13] bool, innov [B, 13] before the gates, pos [B, 3], vel [B, 3], quat [B, 4] predicted)."""
  lay = PrepLayout()

  @jax.custom_batching.custom_vmap
  def call(P, *args):
    def body(p_load, p_store, load, store):
      prep_body(spec, resets, flow_min_height, p_load, p_store, load, store)
    Po, out = _lanes_call(P, pack_prep(*args), lay.n_rows, lay.n_out, body, in_place)
    return (Po, *_unpack_prep(out, P.shape[0]))

  @call.def_vmap
  def _(axis_size, in_batched, *args):   # an outer vmap (a sweep's members): its axis joins the kernel's batch
    args = [x if b else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, b in zip(args, in_batched)]
    outs = call(*[x.reshape((-1,) + x.shape[2:]) for x in args])
    return tuple(o.reshape((axis_size, -1) + o.shape[1:]) for o in outs), (True,) * len(outs)

  return call(P, quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due)
