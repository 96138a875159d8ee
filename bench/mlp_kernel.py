"""The fused MLP kernels (specguard_jax/mlp_kernel.py) against Flax/XLA on the PPO update's and the rollout's shapes.

  python bench/mlp_kernel.py [--rows 65536] [--minibatches 32] [--configs 128:8 64:8:2 128:8:1x] [--parts]

Workloads (policy 24 -> 256 x 3 -> 6 and value 24 -> 256 x 3 -> 1, hidden layers in bf16, as the trainer's):
  update   value_and_grad of a PPO-shaped loss through both nets + an SGD step, `minibatches` minibatches of `rows`
           rows in one jitted lax.scan (the trainer's update is 4 epochs x 8 minibatches of 65,536 at 16,384 envs);
  values   the value net's forward over 32 x 16,384 rows in 4 chunks (iteration.values after the rollout);
  acting   the policy's forward over 16,384 rows, 32 times in a lax.scan (the rollout's acting).
Prints ms per workload call (median of --repeats after the compile) for XLA and each kernel config (rows per
program : warps [: pipeline stages][x: the backward chain in XLA]), and the gradients' largest relative difference
to XLA's. --parts also times the kernel path's pieces on one minibatch. Results: BENCHMARKS.md, session 22.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from specguard_jax.mlp_kernel import KernelConfig, _forward, _mlp_bwd, _split, mlp  # noqa: E402
from specguard_jax.ppo import networks  # noqa: E402


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
    name = "xla" if cfg is None else (f"kernel {cfg.block}:{cfg.num_warps}:{cfg.num_stages}"
                                      + ("" if cfg.bwd_kernel else " xla-bwd"))
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
