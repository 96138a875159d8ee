"""The fused MLP kernels (specguard_jax/mlp_kernel.py) in Pallas' interpret mode on the CPU: forward and gradient
equal `networks.MLP`'s in float32 and, in bfloat16, are closer to float32 than Flax's own bf16 layers; the agents'
acting and values on the kernel (train.py --fused-mlp) equal the XLA path's to bf16 rounding; bad configs are
refused."""

import dataclasses

import jax
import jax.numpy as jnp
import pytest

from specguard_jax import mlp_kernel
from specguard_jax.ppo import config as C
from specguard_jax.ppo import iteration, networks


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


def test_agents_act_and_value_on_the_kernel_like_xla():
  cfg = C.TrainConfig(num_envs=64, network_dtype="bfloat16", action="discrete")
  kernel = mlp_kernel.KernelConfig(dtype="bfloat16", block=32, num_warps=4, interpret=True)
  for agent, n_obs in zip(iteration.make_agents(cfg), (24, 17)):
    on_kernel = agent.replace(policy=dataclasses.replace(agent.policy, inference_kernel=kernel), value_kernel=kernel)
    state = agent.init(jax.random.PRNGKey(0), n_obs)
    # non-zero output layers, so the outputs depend on the hidden layers
    params = jax.tree.map(lambda a: a + 0.1 * jax.random.normal(jax.random.PRNGKey(4), a.shape), state.params)
    state = state.replace(params=params)
    obs = 3.0 * jax.random.normal(jax.random.PRNGKey(1), (40, n_obs))
    out = agent.policy.forward(params["policy"], agent.normalize(state, obs))
    out_k = on_kernel.policy._infer(params["policy"], on_kernel.normalize(state, obs))
    assert jnp.allclose(out, out_k, atol=0.05 * float(jnp.max(jnp.abs(out))))
    v, v_k = agent.value_of(state, obs), on_kernel.value_of(state, obs)
    assert v.shape == v_k.shape == (40,)
    assert jnp.allclose(v, v_k, atol=0.05 * float(jnp.max(jnp.abs(v))))
    a, _ = agent.sample(state, obs, jax.random.PRNGKey(2))
    a_k, _ = on_kernel.sample(state, obs, jax.random.PRNGKey(2))
    assert a.shape == a_k.shape
    # the kernel path really runs the Pallas kernel, and the loss keeps XLA's layers
    assert "pallas_call" in str(jax.make_jaxpr(on_kernel.sample)(state, obs, jax.random.PRNGKey(2)))
    assert "pallas_call" in str(jax.make_jaxpr(on_kernel.value_of)(state, obs))
    assert "pallas_call" not in str(jax.make_jaxpr(agent.value_of)(state, obs))


def test_fused_mlp_refuses_what_it_cannot_run():
  with pytest.raises(ValueError, match="fused_mlp needs a GPU"):
    C.TrainConfig(fused_mlp=True, network_dtype="bfloat16").validate()
  kernel = mlp_kernel.KernelConfig(interpret=True)
  with pytest.raises(ValueError, match="activation 'relu'"):
    networks.Policy("gaussian", 3, (256, 256), "relu", inference_kernel=kernel)
  with pytest.raises(ValueError, match=r"hidden widths \[100\]"):
    networks.Policy("gaussian", 3, (256, 100), "tanh", inference_kernel=kernel)
