"""A tanh MLP's forward and backward passes as fused GPU kernels (Pallas, Triton backend), timed against Flax/XLA
on the PPO update's and the rollout's shapes. An experiment: measured slower where it counts, so the trainer does not
use it (BENCHMARKS.md, session 22); kept so the figures can be reproduced and the kernels tuned further.

  python bench/mlp_kernel.py [--rows 65536] [--minibatches 32] [--configs 128:8 128:8:1x] [--parts]

The kernels compute `networks.MLP` (Flax Dense layers, tanh between them, hidden layers in `dtype`, the output layer
in float32) from its own parameter dict ({'dense_i': {'kernel': [K, N], 'bias': [N]}}):
* forward: one program owns `block` rows and runs every layer on them in registers (GEMMs on the tensor cores with
  f32 accumulation, bias + tanh in f32, rounded to `dtype` as the next layer's input); it writes only the output and,
  under differentiation, each hidden layer's activations;
* backward: one program per row block runs dz_l = (dz_{l+1} W_{l+1}') * (1 - h_l^2) down to the input, writing each
  dz_l and its per-block column sums (the bias gradients); the weight gradients h_{l-1}' dz_l are XLA GEMMs.
The idea: XLA runs every layer as a GEMM plus separate bias/tanh (and backwards tanh-derivative and bias-reduction)
passes over the [rows, 256] activations, memory-bound at 65,536 rows. What was measured instead (H100): the fused
forward runs the GEMMs at ~65 TFLOP/s (18.8 GFLOP per 65,536-row policy pass in 0.29 ms), far from the tensor cores'
rate, so the update is slower (36.1 against 34.0 ms) and, inside the trainer's rollout, the acting and value passes
on the kernel cost 9.6 % of the training throughput although they are faster alone.

Numerics: Flax's bf16 Dense rounds the GEMM's output to bf16 before the bias add and tanh; the kernel adds the bias
and applies tanh to the f32 accumulator and rounds once: against a float32 reference its gradients are closer than
Flax-bf16's (tests/test_mlp_kernel_bench.py runs the kernels in Pallas' interpret mode on the CPU).

Workloads (policy 24 -> 256 x 3 -> 6 and value 24 -> 256 x 3 -> 1, hidden layers in bf16, as the trainer's):
  update   value_and_grad of a PPO-shaped loss through both nets + an SGD step, `minibatches` minibatches of `rows`
           rows in one jitted lax.scan (the trainer's update is 4 epochs x 8 minibatches of 65,536 at 16,384 envs);
  values   the value net's forward over 32 x 16,384 rows in 4 chunks (iteration.values after the rollout);
  acting   the policy's forward over 16,384 rows, 32 times in a lax.scan (the rollout's acting).
Prints ms per workload call (median of --repeats after the compile) for XLA and each kernel config (rows per
program : warps [: stages][x = backward chain in XLA]), and the gradients' largest relative difference to XLA's.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from specguard_jax.ppo import networks  # noqa: E402

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
  k0p, np_ = wp[0].shape[0], wp[-1].shape[1]
  widths = [w.shape[1] for w in ws[:-1]]
  wts = [w.T for w in wp]
  gp = _pad2(g.astype(jnp.float32), rows, np_)
  if not cfg.bwd_kernel:
    return _xla_bwd(cfg, ws, bs, x, acts, g, wp)
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


def _timed(fn, *args, repeats: int):
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - t0)
  return 1e3 * float(np.median(times)), compile_s


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--rows", type=int, default=65536)
  ap.add_argument("--minibatches", type=int, default=32)
  ap.add_argument("--n-obs", type=int, default=24)
  ap.add_argument("--configs", nargs="+", default=["32:4", "64:4", "64:8", "128:8"])
  ap.add_argument("--repeats", type=int, default=5)
  ap.add_argument("--interpret", action="store_true", help="Pallas interpreter (CPU smoke run; tiny sizes)")
  ap.add_argument("--parts", action="store_true",
                  help="also time the kernel path's parts on one minibatch of the policy net: forward kernel "
                       "(with / without saving activations), backward kernel, weight-gradient GEMMs")
  args = ap.parse_args(argv)
  d = jax.devices()[0]
  print(f"device: {d.device_kind} ({d.platform}), jax {jax.__version__}")

  pol = networks.MLP((256, 256, 256, 6), "tanh", 0.01, "bfloat16")
  val = networks.MLP((256, 256, 256, 1), "tanh", 1.0, "bfloat16")
  k = jax.random.split(jax.random.PRNGKey(0), 8)
  params = {"p": pol.init(k[0], jnp.zeros((1, args.n_obs)))["params"],
            "v": val.init(k[1], jnp.zeros((1, args.n_obs)))["params"]}
  M, R = args.minibatches, args.rows
  xs = jax.random.normal(k[2], (M, R, args.n_obs))
  acts = jax.random.randint(k[3], (M, R), 0, 6)
  targets = jax.random.normal(k[4], (M, R))
  adv = jax.random.normal(k[5], (M, R))

  def applies(cfg):
    if cfg is None:
      return (lambda p, x: pol.apply({"params": p}, x)), (lambda p, x: val.apply({"params": p}, x))
    return (lambda p, x: mlp(p, x, cfg)), (lambda p, x: mlp(p, x, cfg))

  def update_fn(cfg):
    fp, fv = applies(cfg)

    def loss(p, x, a, t, g):
      logits = fp(p["p"], x)
      logp = jnp.take_along_axis(jax.nn.log_softmax(logits), a[:, None], axis=-1)[:, 0]
      v = fv(p["v"], x)[:, 0]
      return -jnp.mean(logp * g) + 0.5 * jnp.mean((v - t) ** 2)

    def body(p, mb):
      l, gr = jax.value_and_grad(loss)(p, *mb)
      return jax.tree.map(lambda w, d: w - 1e-3 * d, p, gr), l

    return jax.jit(lambda p, data: jax.lax.scan(body, p, data))

  def grads_fn(cfg):
    fp, fv = applies(cfg)
    return jax.jit(jax.grad(lambda p, data: jnp.mean(jax.nn.log_softmax(fp(p["p"], data[0]))[:, 0] * data[3])
                            + 0.5 * jnp.mean((fv(p["v"], data[0])[:, 0] - data[2]) ** 2)))

  obs_values = jax.random.normal(k[6], (32, 16384, args.n_obs)) if not args.interpret else jnp.tile(xs[:1], (4, 1, 1))
  obs_acting = obs_values

  def values_fn(cfg):
    _, fv = applies(cfg)
    return jax.jit(lambda p, obs: jax.lax.map(lambda x: fv(p["v"], x.reshape(-1, args.n_obs)),
                                              obs.reshape((4, -1) + obs.shape[1:])))

  def acting_fn(cfg):
    fp, _ = applies(cfg)
    return jax.jit(lambda p, obs: jax.lax.scan(lambda c, x: (c + jnp.sum(fp(p["p"], x)), None), 0.0, obs)[0])

  def parse(c):
    hybrid = c.endswith("x")
    b, w, *s = (int(v) for v in c.rstrip("x").split(":"))
    return KernelConfig(dtype="bfloat16", block=b, num_warps=w, num_stages=s[0] if s else 1,
                           bwd_kernel=not hybrid, interpret=args.interpret)

  cfgs = [None] + [parse(c) for c in args.configs]
  data = (xs, acts, targets, adv)
  data0 = tuple(a[0] for a in data)
  inputs = {"update": data, "values": obs_values, "acting": obs_acting}
  g_ref = grads_fn(None)(params, data0)
  for cfg in cfgs:
    name = "xla" if cfg is None else f"kernel {cfg.block}:{cfg.num_warps}:{cfg.num_stages}" + ("" if cfg.bwd_kernel else " xla-bwd")
    if args.parts and cfg is not None:
      _parts(cfg, params["p"], xs[0], args.repeats)
    try:
      row = []
      for wl, fn in (("update", update_fn), ("values", values_fn), ("acting", acting_fn)):
        ms, comp = _timed(fn(cfg), params, inputs[wl], repeats=args.repeats)
        row.append(f"{wl} {ms:8.2f} ms (compile {comp:5.1f} s)")
      g = grads_fn(cfg)(params, data0)
      err = max(float(jnp.linalg.norm(a - b) / (jnp.linalg.norm(a) + 1e-12))
                for a, b in zip(jax.tree.leaves(g_ref), jax.tree.leaves(g)))
      print(f"{name:14s} " + "  ".join(row) + f"  grad rel diff to xla {err:.4f}", flush=True)
    except Exception as e:  # noqa: BLE001 (a config Triton cannot compile is reported, the others still run)
      print(f"{name:14s} failed: {type(e).__name__}: {str(e).splitlines()[0][:300]}", flush=True)


def _parts(cfg, p, x, repeats):
  """ms of each piece of the kernel path on one minibatch x [R, K0] of the policy net."""
  ws, bs = _split(p)
  rows = x.shape[0]
  out, acts = jax.jit(lambda w, b, x: _forward(cfg, w, b, x, save=True))(ws, bs, x)
  g = jnp.ones_like(out)
  # every array is an argument (a closed-over array becomes a constant XLA may try to fold on the host)
  pieces = {
    "fwd": jax.jit(lambda w, b, x, acts, g: _forward(cfg, w, b, x, save=False)[0]),
    "fwd+save": jax.jit(lambda w, b, x, acts, g: _forward(cfg, w, b, x, save=True)),
    "bwd(all)": jax.jit(lambda w, b, x, acts, g: _mlp_bwd(cfg, (w, b, x, acts), g)),
    "dW gemms": jax.jit(lambda w, b, x, acts, g: [jnp.einsum("rk,rn->kn", a, a, preferred_element_type=jnp.float32)
                                                  for a in acts]),
  }
  line = []
  for name, fn in pieces.items():
    ms, _ = _timed(fn, ws, bs, x, acts, g, repeats=repeats)
    line.append(f"{name} {ms:.3f}")
  print(f"  parts, one {rows}-row minibatch of the policy net (ms): " + ", ".join(line), flush=True)


if __name__ == "__main__":
  main()
