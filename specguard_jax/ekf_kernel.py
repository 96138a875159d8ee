"""The EKF tick's covariance work as one fused GPU kernel (Pallas, Triton backend).

What it computes, for a batch of vehicles, is `ekf._cov_tick` (the XLA form, which stays the reference and the CPU
path): P <- F P F' + Q, the tick's symmetrisation and clamps, the predicted innovation variances S = h P h' + R, the
grouped innovation gates, and the sequential scalar fusion of the accepted rows in low-rank form
(P - sum_i c_i u_i u_i'), returning the new P and its diagonal, the error-state correction dx and the gate records. The
nominal state (strapdown, linearisation, injection, resets) stays in XLA, where it is [B, <=13]-vector work that fuses
well.

Why a kernel: in XLA the vmapped covariance work is ~60 kernels per tick, each reading or writing [B, 15, 15] or
[B, 15]-sized buffers (BENCHMARKS.md, session 7), so at 65,536 vehicles the EKF was ~40 % of an env step against
physics' ~35 %. Here one program owns BLOCK vehicles and keeps each one's P in registers as a [BLOCK, 16, 16] tile
(Triton needs power-of-two shapes: P is padded with a zero row and column) for the whole tick: P is read once and
written once. The env keeps P in that padded layout between ticks when the kernel is on (`ekf_init(p_layout="padded")`),
and H comes in as its support entries only ([B, 32] instead of a padded [B, 16, 16]): at 65,536 vehicles the pad and
slice copies around the kernel had cost ~130 us per tick against the kernel's ~270 (bench/gpu_profile.py --ekf).
The timeout resets and the closing clean-up of P after the fusion stay in XLA (`ekf._reset_and_condition`) as one
elementwise pass over P, which the kernel's diagonal output keeps from re-reading P with a stride: the tick loop needs
that pass anyway, to copy the kernel's output into its carry (H100, 65,536 vehicles: done inside the kernel they
added ~47 us to it, and XLA then copied P, ~44 us per tick; bench/gpu_profile.py --env-step, BENCHMARKS.md session 13).
P's output is a new buffer: aliasing it to the input made no difference to the env step there.
Rows and columns of the tile are taken with one-hot masked sums (Triton cannot index a register tile); F's structure
(I + E, E's non-zero columns known statically) keeps the products to 12 outer products each way.

Numerics: the same operations as the XLA form in a different summation order (equal to float32 rounding;
tests/test_ekf_kernel.py runs the kernel in Pallas' interpret mode on the CPU against `ekf._cov_tick`). P stays
exactly symmetric: the symmetrisation is the last step of the prediction and every fusion term is c * (u_i * u_j).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

N = 16          # padded error-state size (15 -> 16: Triton shapes are powers of two)
BLOCK = 2       # vehicles per program (H100, 65,536 envs, bench/ekf_kernel.py: 2 x 1 warp 428 us, 4 x 1 707 us)
_N_ERR = 15
_N_ROWS = 13


@dataclasses.dataclass(frozen=True)
class CovSpec:
  """Static description of one tick's covariance work (hashable: it is part of the kernel's trace).

  dt: tick (s). q: [15] process-noise variances added to P's diagonal. R, gate: [13] measurement variances and gates
  (sigma). used: [13] whether each row can be fused at all this tick (static). group_of_row: [13] gate group of each
  row (a group is rejected as a whole). var_min, var_max: [15] diagonal clamps. h_support: [13] tuples, the
  error-state columns each row of H can be non-zero in (only those entries of H are passed to the kernel).
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
    """((row, column), ...) of H the kernel reads: the support of every usable row, in row order."""
    return tuple((i, c) for i in range(_N_ROWS) if self.used[i] for c in self.h_support[i])

  def h_width(self) -> int:
    """Columns of the kernel's H input (a power of two, >= 16)."""
    return max(N, 1 << (len(self.h_entries()) - 1).bit_length())

  def consts(self) -> np.ndarray:
    """[8, 16] float32 table the kernel reads its per-row constants from (padding rows: R = gate = 1, unused)."""
    c = np.zeros((8, N), np.float32)
    c[0, :_N_ERR] = self.q
    c[1, :] = 1.0
    c[1, :_N_ROWS] = self.R
    c[2, :] = 1.0
    c[2, :_N_ROWS] = self.gate
    c[3, :_N_ERR] = self.var_min
    c[4, :] = 1.0
    c[4, :_N_ERR] = self.var_max
    return c


def _kernel(P_ref, hd_ref, ab_ref, innov_ref, en_ref, c_ref, Po_ref, diag_ref, dx_ref, ratio_ref, acc_ref, *,
            spec: CovSpec):
  f32 = jnp.float32
  lane = jax.lax.broadcasted_iota(jnp.int32, (N,), 0)
  is_k = [lane == k for k in range(N)]
  oh = [x.astype(f32) for x in is_k]                                     # [16] one-hot vectors
  is_diag = (jax.lax.broadcasted_iota(jnp.int32, (N, N), 0) == jax.lax.broadcasted_iota(jnp.int32, (N, N), 1))[None]
  eye = is_diag.astype(f32)                                              # [1, 16, 16]

  # Masked sums pick one row / column / entry; a select, not a product with the one-hot mask, so that a non-finite
  # entry elsewhere (a NaN in P before the tick's clean-up) does not spread to the picked values.
  def row(X, k):  # [BLOCK, 16]: X[:, k, :]
    return jnp.sum(jnp.where(is_k[k][None, :, None], X, 0.0), axis=1)

  def col(X, k):  # [BLOCK, 16]: X[:, :, k]
    return jnp.sum(jnp.where(is_k[k][None, None, :], X, 0.0), axis=2)

  def entry(v, k):  # [BLOCK]: v[:, k]
    return jnp.sum(jnp.where(is_k[k][None, :], v, 0.0), axis=1)

  # ---- prediction: P <- (I + E) P (I + E)' + Q, E's non-zero columns built from the per-vehicle blocks A, B
  dt = spec.dt
  a = lambda i, m: ab_ref[:, 3 * i + m][:, None]        # A[i, m] = d(vel_i)/d(att_m), [BLOCK, 1]
  b = lambda i, m: ab_ref[:, 9 + 3 * i + m][:, None]    # B[i, m] = -R[i, m] dt
  ecol, erows = {}, {}   # E[:, k] as [BLOCK or 1, 16], and the rows it can be non-zero in (static)
  for m in range(3):
    ecol[3 + m], erows[3 + m] = (dt * oh[m])[None, :], (m,)                                  # d(pos)/d(vel)
    ecol[6 + m], erows[6 + m] = sum(a(i, m) * oh[3 + i][None, :] for i in range(3)), (3, 4, 5)   # d(vel)/d(att)
    ecol[9 + m], erows[9 + m] = sum(b(i, m) * oh[6 + i][None, :] for i in range(3)), (6, 7, 8)   # d(att)/d(gbias)
    ecol[12 + m], erows[12 + m] = sum(b(i, m) * oh[3 + i][None, :] for i in range(3)), (3, 4, 5)  # d(vel)/d(abias)
  # Each outer product is kept to E's structural rows by a select, so that a non-finite entry of P reaches exactly
  # the entries it reaches in the XLA form (which then zeroes them).
  on_rows = {k: sum(is_k[r].astype(jnp.int32) for r in rows) > 0 for k, rows in erows.items()}   # [16] bool
  P = P_ref[...]
  FP = P + sum(jnp.where(on_rows[k][None, :, None], ecol[k][:, :, None] * row(P, k)[:, None, :], 0.0)
               for k in sorted(ecol))
  P = FP + sum(jnp.where(on_rows[k][None, None, :], col(FP, k)[:, :, None] * ecol[k][:, None, :], 0.0)
               for k in sorted(ecol))
  P = P + eye * c_ref[0, :][None, None, :]
  # the tick's one symmetrisation, non-finite entries to zero, diagonal clamps (ekf._condition)
  P = 0.5 * (P + jnp.swapaxes(P, 1, 2))
  P = jnp.where(jnp.isfinite(P), P, 0.0)
  d = jnp.sum(jnp.where(is_diag, P, 0.0), axis=2)
  s = jnp.sqrt(jnp.minimum(1.0, c_ref[4, :][None, :] / jnp.maximum(d, 1e-30)))
  lift = jnp.maximum(c_ref[3, :][None, :] - d * (s * s), 0.0)
  P = P * (s[:, :, None] * s[:, None, :]) + eye * lift[:, None, :]

  # ---- gates on the predicted variances
  used = [i for i in range(_N_ROWS) if spec.used[i]]
  h = {}                                                                 # [BLOCK, 16] rows of H, from their support
  for e, (i, c) in enumerate(spec.h_entries()):
    term = hd_ref[:, e][:, None] * oh[c][None, :]
    h[i] = term if i not in h else h[i] + term
  pht = {i: jnp.sum(P * h[i][:, None, :], axis=2) for i in used}         # P h_i (P symmetric)
  hPh = sum(jnp.sum(h[i] * pht[i], axis=1)[:, None] * oh[i][None, :] for i in used)
  S = hPh + c_ref[1, :][None, :]
  innov = innov_ref[...]
  enable = en_ref[...] > 0.5
  g2 = c_ref[2, :][None, :]
  ratio = innov * innov / (g2 * g2 * S)
  ratio = jnp.where(jnp.isfinite(ratio), ratio, 1e6)
  bad = (enable & ~(ratio <= 1.0)).astype(f32)
  group_bad = jnp.zeros_like(ratio)
  for g in sorted(set(spec.group_of_row)):
    mask = sum(oh[i] for i in range(_N_ROWS) if spec.group_of_row[i] == g)[None, :]
    group_bad = group_bad + jnp.max(bad * mask, axis=1)[:, None] * mask
  accept = enable & (group_bad < 0.5)
  innov = jnp.where(accept, innov, 0.0)
  acc = accept.astype(f32)

  # ---- sequential fusion, low rank: u_i = P_{i-1} h_i = P h_i - sum_{j<i} c_j (h_i . u_j) u_j
  us, cs = [], []
  dx = jnp.zeros_like(ratio)
  for i in used:
    u = pht[i]
    for uj, cj in zip(us, cs):
      u = u - (cj * jnp.sum(h[i] * uj, axis=1))[:, None] * uj
    c = jnp.where(entry(acc, i) > 0.5, 1.0 / (jnp.sum(h[i] * u, axis=1) + spec.R[i]), 0.0)
    dx = dx + (c * (entry(innov, i) - jnp.sum(h[i] * dx, axis=1)))[:, None] * u
    us.append(u)
    cs.append(c)
  for u, c in zip(us, cs):
    P = P - c[:, None, None] * (u[:, :, None] * u[:, None, :])

  Po_ref[...] = P
  diag_ref[...] = jnp.sum(jnp.where(is_diag, P, 0.0), axis=2)
  dx_ref[...] = dx
  ratio_ref[...] = ratio
  acc_ref[...] = acc


def _pad(x, shape):
  return jnp.pad(x, [(0, n - m) for m, n in zip(x.shape, shape)])


@functools.partial(jax.jit, static_argnames=("spec", "interpret", "num_warps", "block"))
def cov_tick(spec: CovSpec, P, ab, H, innov, enable, interpret: bool = False, num_warps: int = 1,
             block: int = BLOCK):
  """The tick's covariance work for a batch of B vehicles.

  P: [B, 15, 15] covariance before the prediction, or [B, 16, 16] already padded with a zero row and column (the
  layout `ekf.ekf_init(p_layout="padded")` keeps it in: then P goes into and out of the kernel without a copy).
  ab: [B, 18], F's blocks A (d vel / d att, row-major) then B (-R dt). H: [B, 13, 15] observation Jacobian at the
  predicted state (only its entries on `spec.h_support` are read). innov: [B, 13] innovations. enable: [B, 13] bool,
  rows with a fresh sample. Returns (P in the layout it came in, dx [B, 15], test ratio [B, 13], accept [B, 13]
  bool, P's diagonal [B, 15 or 16]). interpret: run through Pallas' interpreter (any backend; for tests).
  """
  from jax.experimental import pallas as pl
  from jax.experimental.pallas import triton as plt

  nb = P.shape[0]
  bp = -(-nb // block) * block
  f32 = jnp.float32
  padded = P.shape[-1] == N
  P16 = _pad(P.astype(f32), (bp, N, N))
  # [bp, W]: H's entries on its support (static slices, which XLA fuses into the producer of H)
  hd = _pad(jnp.stack([H[:, i, c] for i, c in spec.h_entries()], axis=1).astype(f32), (bp, spec.h_width()))
  ab32 = _pad(ab.astype(f32), (bp, 32))
  innov16 = _pad(innov.astype(f32), (bp, N))
  en16 = _pad(enable.astype(f32), (bp, N))
  consts = jnp.asarray(spec.consts())
  tile = pl.BlockSpec((block, N, N), lambda i: (i, 0, 0))
  vec = pl.BlockSpec((block, N), lambda i: (i, 0))
  out = pl.pallas_call(
    functools.partial(_kernel, spec=spec),
    out_shape=[jax.ShapeDtypeStruct((bp, N, N), f32)] + [jax.ShapeDtypeStruct((bp, N), f32)] * 4,
    grid=(bp // block,),
    in_specs=[tile, pl.BlockSpec((block, spec.h_width()), lambda i: (i, 0)),
              pl.BlockSpec((block, 32), lambda i: (i, 0)), vec, vec, pl.BlockSpec((8, N), lambda i: (0, 0))],
    out_specs=[tile, vec, vec, vec, vec],
    interpret=interpret,
    compiler_params=None if interpret else plt.CompilerParams(num_warps=num_warps, num_stages=1),
  )(P16, hd, ab32, innov16, en16, consts)
  Po, diag, dx, ratio, acc = out
  Po = Po[:nb] if padded else Po[:nb, :_N_ERR, :_N_ERR]
  return Po, dx[:nb, :_N_ERR], ratio[:nb, :_N_ROWS], acc[:nb, :_N_ROWS] > 0.5, diag[:nb, :P.shape[-1]]
