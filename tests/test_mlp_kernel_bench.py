"""bench/mlp_kernel.py's fused MLP kernels (an experiment the trainer does not use) run in Pallas' interpret mode on
the CPU: forward and gradient equal `networks.MLP`'s in float32 and, in bfloat16, closer to float32 than Flax's own
bf16 layers (so BENCHMARKS.md session 22's timings compare like with like)."""

import os
import sys

import jax
import jax.numpy as jnp
import pytest

from specguard_jax.ppo import networks

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))
import mlp_kernel  # noqa: E402


def _setup(sizes, dtype, rows):
  mlp = networks.MLP(sizes, "tanh", 0.5, dtype)
  params = mlp.init(jax.random.PRNGKey(0), jnp.zeros((1, 24)))["params"]
  params = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.PRNGKey(1), a.shape), params)
  x = jax.random.normal(jax.random.PRNGKey(2), (rows, 24))
  w = jax.random.normal(jax.random.PRNGKey(3), (rows, sizes[-1]))
  return mlp, params, x, w


@pytest.mark.parametrize("bwd_kernel", [True, False])
def test_float32_kernels_equal_flax(bwd_kernel):
  mlp, params, x, w = _setup((64, 32, 6), "float32", 100)   # 100 rows: padded to 2 blocks of 64
  cfg = mlp_kernel.KernelConfig(dtype="float32", block=64, num_warps=4, bwd_kernel=bwd_kernel, interpret=True)
  ref = mlp.apply({"params": params}, x)
  out = mlp_kernel.mlp(params, x, cfg)
  assert out.shape == ref.shape
  assert jnp.allclose(out, ref, atol=1e-5)
  loss = lambda f: (lambda p, x: jnp.sum(jnp.tanh(f(p, x)) * w))  # noqa: E731
  g_ref = jax.grad(loss(lambda p, x: mlp.apply({"params": p}, x)), argnums=(0, 1))(params, x)
  g = jax.grad(loss(lambda p, x: mlp_kernel.mlp(p, x, cfg)), argnums=(0, 1))(params, x)
  for a, b in zip(jax.tree.leaves(g_ref), jax.tree.leaves(g)):
    assert a.shape == b.shape
    assert jnp.allclose(a, b, atol=2e-5, rtol=1e-4)


def test_bfloat16_kernels_closer_to_float32_than_flax_bf16():
  ref32, params, x, w = _setup((64, 64, 3), "float32", 64)
  flax16 = networks.MLP((64, 64, 3), "tanh", 0.5, "bfloat16")
  cfg = mlp_kernel.KernelConfig(dtype="bfloat16", block=32, num_warps=4, interpret=True)
  loss = lambda f: (lambda p: jnp.sum(jnp.tanh(f(p)) * w))  # noqa: E731
  g32 = jax.grad(loss(lambda p: ref32.apply({"params": p}, x)))(params)
  g16 = jax.grad(loss(lambda p: flax16.apply({"params": p}, x)))(params)
  gk = jax.grad(loss(lambda p: mlp_kernel.mlp(p, x, cfg)))(params)
  rel = lambda a, b: float(jnp.linalg.norm(a - b) / jnp.linalg.norm(a))  # noqa: E731
  for a, b, c in zip(jax.tree.leaves(g32), jax.tree.leaves(g16), jax.tree.leaves(gk)):
    assert rel(a, c) < 0.03
    assert rel(a, c) <= 1.5 * rel(a, b) + 1e-3
