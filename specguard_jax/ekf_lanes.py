"""The EKF tick as one Pallas Mosaic GPU kernel, one vehicle per GPU lane (NVIDIA Hopper or newer), and the choice
between it and the XLA filter (`resolve_ekf_kernel`, `ekf_step`).

`prep_tick` computes for a batch what `ekf.ekf_step` computes in XLA before the injection and the records: the
nominal state's prediction, H and the innovations (`prep_inputs`), then the covariance work (`tick_body`), equal to
float32 rounding (tests/test_ekf_lanes.py checks the kernel's body, run in plain JAX on the CPU, against the XLA tick).
Why: in XLA the vmapped tick is dozens of small kernels over [B, 15, 15] buffers; here each thread of a warpgroup owns
one vehicle, the tick is straight-line code with P's symmetry and F's / H's sparsity resolved statically, and P stays
in registers for the whole tick. P is packed ([B, 121], `ekf.pack_p`; the env keeps it so with this kernel), copied
into shared memory with one TMA copy per 128 vehicles and written back in place; the other inputs come vehicle-minor
([51, B], `pack_prep`). Lowered with Lane semantics (Triton and Warpgroup semantics do not compile code this long).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from specguard_jax import ekf as ekf_lib
from specguard_jax.ekf import N_ERR, N_PACKED, TRI, TRI_INDEX, as_square, layout_like, pack_p, p_layout, tri_index
from specguard_jax.types import EKF_KERNELS

N_ROWS = 13
LANES = 128     # vehicles per program: one per thread of a warpgroup
JAX_VERSION = tuple(int(x) for x in jax.__version__.split(".")[:2])
# P written in place through a jax Ref (jax >= 0.11; jax 0.10's Pallas cannot discharge a Ref into a Mosaic GPU kernel)
IN_PLACE = JAX_VERSION >= (0, 11)


def _compute_capability() -> float | None:
  """The default device's CUDA compute capability (None: not a GPU, or not reported)."""
  if jax.default_backend() != "gpu":
    return None
  cc = getattr(jax.devices()[0], "compute_capability", None)
  return None if cc is None else float(cc)


def lanes_kernel_supported() -> bool:
  """Whether the default device runs the lanes kernel: an NVIDIA GPU of compute capability 9.0 (Hopper) or newer."""
  cc = _compute_capability()
  return cc is not None and cc >= 9.0


def resolve_ekf_kernel(name) -> str:
  """An ekf_kernel setting ("auto", "xla" or "lanes") as the kernel that runs: "xla" or "lanes".

  "auto": "lanes" on an NVIDIA GPU of compute capability >= 9.0 with jax >= 0.11 (with jax 0.10 the kernel lowers but
  is opt-in), else "xla". A one-line ValueError for an unknown name, or for "lanes" on a device that cannot run it."""
  if name not in EKF_KERNELS:
    raise ValueError(f"ekf_kernel must be one of {', '.join(EKF_KERNELS)}; got {name!r}")
  if name == "auto":
    return "lanes" if lanes_kernel_supported() and JAX_VERSION >= (0, 11) else "xla"
  if name == "lanes":
    if jax.default_backend() != "gpu":
      raise ValueError(f"ekf_kernel='lanes' needs a GPU (the default backend is {jax.default_backend()}): "
                       f"use ekf_kernel='xla' or 'auto'")
    cc = _compute_capability()
    if cc is not None and cc < 9.0:
      raise ValueError(f"ekf_kernel='lanes' needs an NVIDIA Hopper GPU or newer (compute capability 9.0); "
                       f"{jax.devices()[0].device_kind} is {cc}: use ekf_kernel='xla' or 'auto'")
  return name


def ekf_step(cfg: ekf_lib.EKFConfig, state: ekf_lib.EKFState, readings, dt, stale: tuple = (), kernel: str = "xla",
             records: bool = True) -> ekf_lib.EKFState:
  """`ekf.ekf_step` on the resolved kernel (`resolve_ekf_kernel`): "xla" the XLA filter; "lanes" the tick's
  prediction, innovations and covariance work as `prep_tick` under vmap (dt a Python float; P best kept packed),
  the same filter to float32 rounding."""
  if kernel not in ("xla", "lanes"):
    raise ValueError(f"ekf_step: kernel must be 'xla' or 'lanes' (resolve_ekf_kernel); got {kernel!r}")
  return ekf_lib.ekf_step(cfg, state, readings, dt, stale=stale, records=records,
                          prep=_lanes_tick if kernel == "lanes" else None)


@dataclasses.dataclass(frozen=True)
class CovSpec:
  """Static description of one tick's covariance work (hashable: the kernel is traced for it).

  dt: tick (s). q: [15] process-noise variances added to P's diagonal. R, gate: [13] measurement variances and gates
  (sigma). used: [13] whether each row can be fused at all this tick (static). group_of_row: [13] gate group of each
  row (a group is rejected as a whole). var_min, var_max: [15] diagonal clamps. h_support: [13] tuples, the
  error-state columns each row of H can be non-zero in.
  """

  dt: float
  q: tuple
  R: tuple
  gate: tuple
  used: tuple
  group_of_row: tuple
  var_min: tuple
  var_max: tuple
  h_support: tuple

  def h_entries(self) -> tuple:
    """((row, column), ...) of H the kernel computes: the support of every usable row, in row order."""
    return tuple((i, c) for i in range(N_ROWS) if self.used[i] for c in self.h_support[i])


def cov_spec(cfg: ekf_lib.EKFConfig, dt: float, stale: tuple) -> CovSpec:
  """The static description of the tick's covariance work that the kernel is traced for."""
  noise, gate = ekf_lib.noise_and_gates(cfg)
  dt = float(dt)
  q = ekf_lib.process_noise(cfg, dt, np)
  return CovSpec(
    dt=dt, q=tuple(float(v) for v in q), R=tuple(float(v) for v in noise.astype(np.float32) ** 2),
    gate=tuple(float(v) for v in gate),
    used=tuple(ekf_lib.row_used(cfg, i, stale) for i in range(N_ROWS)), group_of_row=ekf_lib.GROUP_OF_ROW,
    var_min=tuple(float(v) for v in ekf_lib.VAR_MIN), var_max=tuple(float(v) for v in ekf_lib.VAR_MAX),
    h_support=ekf_lib.H_SUPPORT)


def resets_of(cfg: ekf_lib.EKFConfig) -> tuple:
  """ekf.RESETS with their variances, as the static tuple the kernel is traced for."""
  return tuple((tuple(cols), tuple(rows), how, float(v))
               for (cols, rows, how), v in zip(ekf_lib.RESETS, ekf_lib.reset_variances(cfg)))


@struct.dataclass
class _Nominal:
  """The nominal state's fields `ekf.predict_nominal` and `ekf.innovations` read (an EKFState's, without P and the
  records)."""
  pos: jnp.ndarray
  vel: jnp.ndarray
  quat: jnp.ndarray
  gyro_bias: jnp.ndarray
  accel_bias: jnp.ndarray


def reference_tick(cfg: ekf_lib.EKFConfig, dt: float, stale: tuple, P, quat, vel, pos, gyro_bias, accel_bias, gyro,
                   accel, z, enable, due):
  """What `prep_tick` computes, for one vehicle in XLA (the reference, and the unbatched path of `_lanes_tick`).
  enable [13] bool: the flow rows before the predicted-height check. Returns (P, dx [15], ratio [13], accept [13]
  bool, innov [13] before the gates, the predicted pos [3], vel [3], quat [4])."""
  noise, gate = ekf_lib.noise_and_gates(cfg)
  s, A, B = ekf_lib.predict_nominal(cfg, _Nominal(pos=pos, vel=vel, quat=quat, gyro_bias=gyro_bias,
                                                   accel_bias=accel_bias), gyro, accel, dt)
  rows = jnp.arange(N_ROWS)
  enable = enable & jnp.where((rows == 8) | (rows == 9), s.pos[2] >= cfg.flow_min_height, True)
  innov, H = ekf_lib.innovations(cfg, s, z)
  P, dx, ratio, accept = ekf_lib.cov_tick(cfg, P, A, B, dt, H, innov, jnp.asarray(noise) ** 2, jnp.asarray(gate),
                                           enable, due, stale, unrolled=True)
  return P, dx, ratio, accept, innov, s.pos, s.vel, s.quat


def _lanes_tick(cfg: ekf_lib.EKFConfig, P, quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due,
                dt: float, stale: tuple):
  """`ekf.ekf_step`'s prep hook: one vehicle's tick but the injection and the records, whose vmap runs `prep_tick`
  on the whole batch (unbatched: `reference_tick`). Arguments and results as `reference_tick`'s."""
  spec = cov_spec(cfg, dt, stale)

  @jax.custom_batching.custom_vmap
  def tick(*args):
    return reference_tick(cfg, dt, stale, *args)

  @tick.def_vmap
  def _(axis_size, in_batched, *args):
    args = [x if b else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, b in zip(args, in_batched)]
    return prep_tick(spec, resets_of(cfg), *args, flow_min_height=float(cfg.flow_min_height)), (True,) * 8

  return tick(P, quat, vel, pos, gyro_bias, accel_bias, gyro, accel, z, enable, due)


# ----------------------------------------------------------------------------------------------------------------------
# the kernel


def _finite(x):
  """Elementwise isfinite (Mosaic GPU lowers abs and compare, not is_finite)."""
  return jnp.abs(x) < jnp.inf


def tick_body(spec, resets, p_load, p_store, store, inputs, o):
  """The per-lane covariance tick (`ekf.cov_tick`'s filter) as straight-line code on [lanes] vectors, one vehicle
  per lane.

  p_load(i, j) -> P[i, j] and p_store(i, j, v) sets P[i, j] and P[j, i], both for i <= j; store(k, v) sets output row
  k; every value a [lanes] vector. P is read before the first store, so it may be overwritten in place.
  resets: ((cols, rows, how, var), ...) ekf.RESETS with their variances (`resets_of`).
  inputs: dict(A, B [3][3] F's blocks, hd {row: {col: h}} H on `spec.h_entries()`, innov [13], enable [13] bool,
  due [3] bool), as `prep_inputs` returns them. o: where the outputs go (attributes dx, ratio, acc: `PrepLayout`)."""
  n = N_ERR
  tri = [p_load(i, j) for (i, j) in TRI]
  P = [[tri[tri_index(i, j)] for j in range(n)] for i in range(n)]
  A, B = inputs["A"], inputs["B"]
  dt = spec.dt

  # ---- prediction (ekf.predict_cov): FP = P + E P, X = FP + FP E', + Q, then ekf.condition with symmetrisation
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
    """ekf.condition on the triangle: S[i][j] for i <= j."""
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

  # ---- gates (ekf.innovation_gate) and the sequential fusion of the accepted rows
  hd = inputs["hd"]
  used = [i for i in range(N_ROWS) if spec.used[i]]

  def hdot(i, v):   # h_i . v, v indexable by error-state column
    t = None
    for c, h in hd[i].items():
      t = h * v[c] if t is None else t + h * v[c]
    return t

  # Gates from the predicted P: S_i = h_i' P h_i + R_i as a quadratic form over h_i's few entries (no P h_i vector
  # is kept for later: a [15] vector per row held across the fusion would spill registers to local memory).
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

  # Sequential scalar fusion with P updated after each row (ekf.rows_rolled's form; ekf.rows_unrolled's low-rank
  # form, the XLA reference, is the same filter): per row P h_i from the current P, then P -= c (P h_i)(P h_i)' on
  # the triangle. Live across rows: P's 120 entries, dx, one [15] vector (the low-rank form would keep every row's
  # P_0 h_i and u_i, ~390 values, more than a thread's registers).
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

  # ---- timeout resets, closing clean-up (ekf.reset_and_condition)
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



def _packed_io(fn):
  """fn on P packed [B, 121] -> the same taking and returning P in any layout ("square" [B, 15, 15] or "packed")."""
  @functools.wraps(fn)
  def wrapped(spec, resets, P, *args, **kw):
    if p_layout(P) == "packed":
      return fn(spec, resets, P, *args, **kw)
    Pk, *rest = fn(spec, resets, pack_p(as_square(P)), *args, **kw)
    return (layout_like(as_square(Pk), P), *rest)
  return wrapped


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


# The tick's inputs are prepared in the kernel: F's blocks, H and the innovations computed per lane from the nominal
# state and the readings (what ekf.predict_nominal and ekf.innovations do in XLA), so XLA hands the kernel 51 rows,
# each a copy of one state or reading component, and the prepared inputs stay in registers.
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
  gyro [3], accel [3] (the IMU sample, unclipped), z [13] (`ekf.measurement_rows`), enable [13] (1.0 / 0.0, the flow
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
  """math3d.rotvec_to_quat on components."""
  a2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
  small = a2 < 1e-8
  a = _sqrt(jnp.where(small, 1.0, a2))
  s = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * a) / a)
  c = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * a))
  return [c, s * v[0], s * v[1], s * v[2]]


def _q_normalize(q):
  """math3d.normalize_quat on components."""
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
  """ekf.predict_nominal and ekf.innovations per lane. x: the `PrepLayout` inputs by name, lists of [lanes]
  vectors. Returns (`tick_body`'s inputs, the innovations before the gates [13],
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

  # ekf.linearise at the predicted state
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
  """The tick with its inputs prepared per lane (`prep_inputs`, held in registers), then `tick_body`. load(k) ->
  input row k, store(k, v) sets output row k (rows as `PrepLayout` places them; stores may overwrite the inputs)."""
  lay = PrepLayout()
  x = {name: [load(lay.inp[name] + k) for k in range(size)] for name, size in _PREP_IN}
  inputs, innov, pos, vel, quat = prep_inputs(spec, flow_min_height, x)
  # Stored before the tick (every input is loaded by now): the predicted state is not held in registers through it.
  for name, vals in (("innov", innov), ("pos", pos), ("vel", vel), ("quat", quat)):
    for k, v in enumerate(vals):
      store(lay.out[name] + k, v)
  tick_body(spec, resets, p_load, p_store, store, inputs, lay)


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
  H, the innovations (`prep_inputs`) and the covariance work (`tick_body`), per lane.

  P: [B, 121] packed (or any layout, returned in it). quat [B, 4], vel, pos, gyro_bias, accel_bias [B, 3]: the
  nominal state before the tick; gyro, accel [B, 3]: the IMU sample; z [B, 13]: `ekf.measurement_rows`; enable
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
