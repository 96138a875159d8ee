"""A tanh MLP's forward and backward passes as fused GPU kernels (Pallas, Triton backend).

What it computes is `networks.MLP` (Flax Dense layers, tanh between them, hidden layers in `dtype`, the output layer
in float32), which stays the reference and the CPU path, from the MLP's own parameter dict ({'dense_i': {'kernel':
[K, N], 'bias': [N]}}), so checkpoints, the ONNX export and evaluation see no difference.
* forward: one program owns `block` rows and runs every layer on them in registers (GEMMs on the tensor cores with
  f32 accumulation, bias + tanh in f32, rounded to `dtype` as the next layer's input); it writes only the output and,
  under differentiation, each hidden layer's activations (needed by the backward pass);
* backward: one program per row block runs the chain dz_l = (dz_{l+1} W_{l+1}') * (1 - h_l^2) down to the input,
  writing each dz_l (for the weight gradients) and its per-block column sums (the bias gradients); the weight
  gradients h_{l-1}' dz_l are XLA GEMMs.

Where it is used: `train.py --fused-mlp` runs the rollout's acting and value passes (forward only) on it. The PPO
update stays in XLA: at 65,536 rows the kernels' GEMMs run at ~65 TFLOP/s, and fwd + bwd of both nets took 36.1 ms
against XLA's 33.6-35.0 (H100, `bench/mlp_kernel.py`, BENCHMARKS.md session 22), where the forward-only shapes were
15-30 % faster alone.

Numerics: Flax's bf16 Dense rounds the GEMM's output to bf16 before the bias add and tanh; the kernel adds the bias
and applies tanh to the f32 accumulator and rounds once: against a float32 reference its outputs and gradients are
closer than Flax-bf16's (tests/test_mlp_kernel.py runs the kernels in Pallas' interpret mode on the CPU).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp

BLOCK = 128         # rows per program (H100: 128 x 8 warps the fastest of 16-128 rows x 4-8 warps)
NUM_WARPS = 8
_MIN_DIM = 16       # Triton's dot needs every dimension >= 16 (and a power of two)


@dataclasses.dataclass(frozen=True)
class KernelConfig:
  """Static description of the kernels (hashable: part of the trace). dtype: the hidden layers' compute dtype
  ('bfloat16' or 'float32'); block, num_warps: rows per program and warps per program; interpret: run through
  Pallas' interpreter (any backend; for tests)."""
  dtype: str = "bfloat16"
  block: int = BLOCK
  num_warps: int = NUM_WARPS
  num_stages: int = 1
  bwd_kernel: bool = True   # False: the backward chain in XLA (the forward kernel still saves the activations)
  interpret: bool = False


def _pow2(n: int) -> int:
  return max(_MIN_DIM, 1 << (int(n) - 1).bit_length())


def supported(sizes, activation: str) -> str | None:
  """None when an MLP of these layer sizes (hidden..., output) and activation can run on the kernels, else why not."""
  if activation != "tanh":
    return f"activation {activation!r} (the kernels implement tanh)"
  if len(sizes) < 2:
    return "no hidden layer"
  bad = [n for n in sizes[:-1] if n < _MIN_DIM or n & (n - 1)]
  if bad:
    return f"hidden widths {bad} (the kernels need powers of two >= {_MIN_DIM})"
  return None


def _split(params: dict):
  n = len(params)
  layers = [params[f"dense_{i}"] for i in range(n)]
  return [p["kernel"] for p in layers], [p["bias"] for p in layers]


def _pad2(x, rows, cols):
  return jnp.pad(x, ((0, rows - x.shape[0]), (0, cols - x.shape[1])))


def _dt(cfg: KernelConfig):
  return jnp.bfloat16 if cfg.dtype == "bfloat16" else jnp.float32


def _fwd_kernel(*refs, n_hidden: int, save: bool, dt):
  """refs: x [blk, K0p] f32, W_0..W_L (hidden in dt, output f32 [.., Np]), b_0..b_L [1, N] f32; out [blk, Np] f32;
  then (if save) h_1..h_L [blk, N_l] dt."""
  n_layers = n_hidden + 1
  x_ref, w_refs, b_refs = refs[0], refs[1:1 + n_layers], refs[1 + n_layers:1 + 2 * n_layers]
  out_ref, act_refs = refs[1 + 2 * n_layers], refs[2 + 2 * n_layers:]
  h = x_ref[...].astype(dt)
  for layer in range(n_hidden):
    z = jnp.dot(h, w_refs[layer][...], preferred_element_type=jnp.float32) + b_refs[layer][...]
    h = jnp.tanh(z).astype(dt)
    if save:
      act_refs[layer][...] = h
  out_ref[...] = jnp.dot(h.astype(jnp.float32), w_refs[-1][...], preferred_element_type=jnp.float32) + b_refs[-1][...]


def _bwd_kernel(*refs, n_hidden: int, dt):
  """refs: g [blk, Np] f32 (output cotangent), h_1..h_L [blk, N_l] dt, W_1'..W_L' transposed (W_L' = the output
  layer's, f32 [Np, N_L]; the others dt [N_l, N_{l-1}], W_0' [N_0, K0p]); outputs dz_1..dz_L [blk, N_l] dt,
  dx [blk, K0p] f32, then dz_l's column sums over the block [1, N_l] f32."""
  g_ref = refs[0]
  act_refs = refs[1:1 + n_hidden]
  wt_refs = refs[1 + n_hidden:1 + 2 * n_hidden + 1]
  outs = refs[2 + 2 * n_hidden:]
  dz_refs, dx_ref, db_refs = outs[:n_hidden], outs[n_hidden], outs[n_hidden + 1:]
  dh = jnp.dot(g_ref[...], wt_refs[-1][...], preferred_element_type=jnp.float32)     # d out / d h_L
  for layer in reversed(range(n_hidden)):
    h = act_refs[layer][...].astype(jnp.float32)
    dz = (dh * (1.0 - h * h)).astype(dt)
    dz_refs[layer][...] = dz
    db_refs[layer][...] = jnp.sum(dz.astype(jnp.float32), axis=0, keepdims=True)
    dh = jnp.dot(dz, wt_refs[layer][...], preferred_element_type=jnp.float32)
  dx_ref[...] = dh


def _call(kernel, cfg: KernelConfig, rows: int, inputs, row_shapes, const_shapes, out_rows, out_blocks, out_types):
  """pallas_call over rows / cfg.block programs: inputs are row-blocked arrays then whole-array constants;
  outputs are row-blocked [rows, n] arrays and per-block [rows / block, n] partials."""
  from jax.experimental import pallas as pl
  from jax.experimental.pallas import triton as plt

  blk = cfg.block
  in_specs = ([pl.BlockSpec((blk, n), lambda i: (i, 0)) for n in row_shapes]
              + [pl.BlockSpec(s, lambda i: (0, 0)) for s in const_shapes])
  out_specs = ([pl.BlockSpec((blk, n), lambda i: (i, 0)) for n in out_rows]
               + [pl.BlockSpec((1, n), lambda i: (i, 0)) for n in out_blocks])
  out_shape = ([jax.ShapeDtypeStruct((rows, n), t) for n, t in zip(out_rows, out_types)]
               + [jax.ShapeDtypeStruct((rows // blk, n), jnp.float32) for n in out_blocks])
  return pl.pallas_call(
    kernel, out_shape=out_shape, grid=(rows // blk,), in_specs=in_specs, out_specs=out_specs,
    interpret=cfg.interpret,
    compiler_params=None if cfg.interpret else plt.CompilerParams(num_warps=cfg.num_warps, num_stages=cfg.num_stages),
  )(*inputs)


def _prepare(cfg: KernelConfig, ws, bs):
  """Padded weights: hidden layers' in dt (the first one's input rows padded to K0p), the output layer's f32 with
  its columns padded to Np; biases [1, N] f32."""
  dt = _dt(cfg)
  k0p, np_ = _pow2(ws[0].shape[0]), _pow2(ws[-1].shape[1])
  wp = [_pad2(w, k0p if i == 0 else w.shape[0], w.shape[1]).astype(dt) for i, w in enumerate(ws[:-1])]
  wp.append(_pad2(ws[-1].astype(jnp.float32), ws[-1].shape[0], np_))
  bp = [b.astype(jnp.float32)[None] for b in bs[:-1]] + [_pad2(bs[-1].astype(jnp.float32)[None], 1, np_)]
  return wp, bp


def _forward(cfg: KernelConfig, ws, bs, x, save: bool):
  """x [R, K0] with R a multiple of cfg.block -> (out [R, N_out] f32, hidden activations [R, N_l] dt if save)."""
  rows = x.shape[0]
  wp, bp = _prepare(cfg, ws, bs)
  k0p, np_ = wp[0].shape[0], wp[-1].shape[1]
  widths = [w.shape[1] for w in ws[:-1]]
  dt = _dt(cfg)
  out = _call(functools.partial(_fwd_kernel, n_hidden=len(widths), save=save, dt=dt), cfg, rows,
              [_pad2(x.astype(jnp.float32), rows, k0p)] + wp + bp, [k0p],
              [w.shape for w in wp] + [b.shape for b in bp],
              [np_] + (widths if save else []), [], [jnp.float32] + ([dt] * len(widths) if save else []))
  return out[0][:, :ws[-1].shape[1]], out[1:]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _mlp(cfg: KernelConfig, ws, bs, x):
  return _forward(cfg, ws, bs, x, save=False)[0]


def _mlp_fwd(cfg, ws, bs, x):
  out, acts = _forward(cfg, ws, bs, x, save=True)
  return out, (ws, bs, x, acts)


def _mlp_bwd(cfg, res, g):
  ws, bs, x, acts = res
  dt = _dt(cfg)
  rows, k0 = x.shape
  wp, _ = _prepare(cfg, ws, bs)
  if not cfg.bwd_kernel:
    return _xla_bwd(cfg, ws, bs, x, acts, g, wp)
  k0p, np_ = wp[0].shape[0], wp[-1].shape[1]
  widths = [w.shape[1] for w in ws[:-1]]
  wts = [w.T for w in wp]
  gp = _pad2(g.astype(jnp.float32), rows, np_)
  out = _call(functools.partial(_bwd_kernel, n_hidden=len(widths), dt=dt), cfg, rows,
              [gp] + list(acts) + wts, [np_] + widths, [w.shape for w in wts],
              widths + [k0p], widths, [dt] * len(widths) + [jnp.float32])
  # row-blocked outputs first (dz_1..dz_L, dx), then the per-block partial sums
  dzs, dx, dbs = out[:len(widths)], out[len(widths)], out[len(widths) + 1:]
  inputs = [_pad2(x.astype(jnp.float32), rows, k0p).astype(dt)] + list(acts)
  dws = [jnp.einsum("rk,rn->kn", a, dz, preferred_element_type=jnp.float32) for a, dz in zip(inputs, dzs)]
  dws[0] = dws[0][:k0]
  dws.append(jnp.einsum("rk,rn->kn", acts[-1].astype(jnp.float32), g.astype(jnp.float32),
                        preferred_element_type=jnp.float32))
  dbs = [jnp.sum(d, axis=0) for d in dbs] + [jnp.sum(g.astype(jnp.float32), axis=0)]
  dws = [d.astype(w.dtype) for d, w in zip(dws, ws)]
  dbs = [d.astype(b.dtype) for d, b in zip(dbs, bs)]
  return dws, dbs, dx[:, :k0].astype(x.dtype)


def _xla_bwd(cfg, ws, bs, x, acts, g, wp):
  """The backward pass of `_mlp` in plain XLA ops (same rounding points as the backward kernel)."""
  dt = _dt(cfg)
  k0 = x.shape[1]
  g32 = g.astype(jnp.float32)
  inputs = [x.astype(dt)] + list(acts)
  dh = g32 @ ws[-1].astype(jnp.float32).T
  dws, dbs = [None] * len(ws), [None] * len(ws)
  dws[-1] = jnp.einsum("rk,rn->kn", acts[-1].astype(jnp.float32), g32)
  dbs[-1] = jnp.sum(g32, axis=0)
  for layer in reversed(range(len(acts))):
    h = acts[layer].astype(jnp.float32)
    dz = (dh * (1.0 - h * h)).astype(dt)
    dws[layer] = jnp.einsum("rk,rn->kn", inputs[layer], dz, preferred_element_type=jnp.float32)
    dbs[layer] = jnp.sum(dz.astype(jnp.float32), axis=0)
    dh = jnp.dot(dz, wp[layer].T if layer else ws[0].astype(dt).T, preferred_element_type=jnp.float32)
  dws = [d.astype(w.dtype) for d, w in zip(dws, ws)]
  dbs = [d.astype(b.dtype) for d, b in zip(dbs, bs)]
  return dws, dbs, dh[:, :k0].astype(x.dtype)


_mlp.defvjp(_mlp_fwd, _mlp_bwd)


def mlp(params: dict, x, cfg: KernelConfig = KernelConfig()) -> Any:
  """The MLP `params` (networks.MLP's Flax dict, tanh hidden layers) applied to x [..., K0] -> [..., N_out] f32,
  differentiable in params and x. Rows are padded to a multiple of cfg.block (zeros, dropped again)."""
  ws, bs = _split(params)
  lead = x.shape[:-1]
  x2 = x.reshape((-1, x.shape[-1]))
  rows = x2.shape[0]
  rp = -(-max(rows, 1) // cfg.block) * cfg.block
  out = _mlp(cfg, ws, bs, jnp.pad(x2, ((0, rp - rows), (0, 0))))
  return out[:rows].reshape(lead + (out.shape[-1],))
