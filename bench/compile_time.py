"""Jit compile time of reset + step (vmapped over a small batch) per vehicle, and CPU env throughput; or, with
--trainer-parts, where a training phase's compile goes.

  JAX_PLATFORMS=cpu python bench/compile_time.py [--envs 64] [--steps 20]
  python bench/compile_time.py --trainer-parts [--phase 1] [--envs 16384] [--vehicles drone] [--ekf-kernel xla]

--trainer-parts compiles (lower + compile, abstract inputs, nothing run) the phase's whole training call
(`Phase.run`: `iters_per_call` iterations) and then, each alone, the parts it is made of: the rollout (the
trainer's auto-reset env step in a scan of `unroll_length` steps, zero actions), the pool refresh, the reset pool's
initial reset, and SG's PPO update on a rollout-sized batch. The parts' sum exceeds the whole when XLA shares work
between them; a part much slower to compile than its share of the run's time is where a compile-time cut would go.
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
  p.add_argument("--trainer-parts", action="store_true", help="compile times of a training phase and its parts")
  p.add_argument("--phase", type=int, default=1, choices=(1, 2))
  p.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                 help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  a = p.parse_args()
  if a.trainer_parts:
    for v in a.vehicles:
      trainer_parts(v, a.envs, a.phase, a.ekf_kernel)
    return
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


def _compile_s(fn, *args) -> float:
  t = time.perf_counter()
  jax.jit(fn).lower(*args).compile()
  return time.perf_counter() - t


def trainer_parts(vehicle: str, num_envs: int, number: int, ekf_kernel: str) -> None:
  """Prints the compile seconds of one training phase's call and of its parts (see the module docstring)."""
  from specguard_jax.ppo import attacker as attacker_lib
  from specguard_jax.ppo import config as config_lib
  from specguard_jax.ppo import distributed, losses
  from specguard_jax.ppo import iteration as it

  cfg = config_lib.TrainConfig(vehicle=vehicle, num_envs=num_envs, phase1_steps=10**7, phase2_steps=10**7,
                               num_devices=1).with_env(ekf_kernel=ekf_kernel).validate()
  t = time.perf_counter()
  phase = it.make_phase(cfg, number, distributed.make_mesh(1))
  env = phase.env if number == 1 else phase.env.env
  key = jax.random.PRNGKey(0)
  sg = losses.with_hparams(phase.sg.init(key, env.observation_size), cfg.sg)
  aa = losses.with_hparams(phase.aa.init(key, attacker_lib.N_OBS), cfg.aa)
  carry = jax.eval_shape(phase.init, key, sg, aa)
  t_build = time.perf_counter() - t
  rows = {"whole training call (Phase.run)": _compile_s(phase.run, carry)}
  batched = phase.batched   # the trainer's AutoReset(Vmap(env), refresh_in_step=False)
  keys = jax.random.split(key, num_envs)
  state = jax.eval_shape(batched.reset, keys)
  T = cfg.unroll_length
  act = jnp.zeros((num_envs, phase.env.action_size))
  rows[f"rollout: {T} auto-reset env steps"] = _compile_s(
      lambda s: jax.lax.scan(lambda c, _: (batched.step(c, act), None), s, None, length=T)[0], state)
  rows["pool refresh"] = _compile_s(lambda s: batched.refresh_pool(s, T), state)
  rows["initial reset (env + pool)"] = _compile_s(batched.reset, keys)
  batch = {"obs": jax.ShapeDtypeStruct((T, num_envs, env.observation_size), jnp.float32),
           "action": jax.ShapeDtypeStruct((T, num_envs, env.action_size), jnp.float32)}   # SG's actions
  batch.update({k: jax.ShapeDtypeStruct((T, num_envs), jnp.float32)
                for k in ("logp", "mask", "value", "adv", "target")})
  rows["SG's PPO update"] = _compile_s(lambda st, b, k: losses.update(phase.sg, st, b, k), sg, batch, key)
  print(f"{jax.devices()[0].device_kind}, {vehicle} phase {number}, {num_envs} envs, EKF kernel {ekf_kernel}: "
        f"build + trace setup {t_build:.1f} s; compile seconds:", flush=True)
  for k, v in rows.items():
    print(f"  {k:40s} {v:7.1f}", flush=True)


if __name__ == "__main__":
  main()
