"""Jit compile time of reset + step (vmapped over a small batch) per vehicle, and CPU env throughput.

  JAX_PLATFORMS=cpu python bench/compile_time.py [--envs 64] [--steps 20]
"""

import argparse
import time

import jax
import jax.numpy as jnp


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--envs", type=int, default=64)
  p.add_argument("--steps", type=int, default=20)
  p.add_argument("--vehicles", nargs="+", default=["drone", "rover"])
  a = p.parse_args()
  import envs
  print(f"backend {jax.default_backend()}, {a.envs} envs")
  for v in a.vehicles:
    env = envs.make(v)
    keys = jax.random.split(jax.random.PRNGKey(0), a.envs)
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    t = time.perf_counter()
    reset_c = reset.lower(keys).compile()
    t_reset = time.perf_counter() - t
    state = reset_c(keys)
    act = jnp.zeros((a.envs, 3))
    t = time.perf_counter()
    step_c = step.lower(state, act).compile()
    t_step = time.perf_counter() - t
    state = step_c(state, act)
    jax.block_until_ready(state.obs)
    t = time.perf_counter()
    for _ in range(a.steps):
      state = step_c(state, act)
    jax.block_until_ready(state.obs)
    dt = time.perf_counter() - t
    print(f"{v:6s} compile reset {t_reset:5.1f} s + step {t_step:5.1f} s = {t_reset + t_step:5.1f} s;  "
          f"{a.envs * a.steps / dt:8.0f} env steps/s = {a.envs * a.steps * env.config.ticks_per_step / dt:8.0f} "
          f"ticks/s", flush=True)


if __name__ == "__main__":
  main()
