"""What an auto-reset costs per env step: `Vmap(env).step` alone vs `AutoReset` with the reset pool refreshed inside
every step (the default; Brax's loop uses it) vs refreshed once per rollout (the trainer's form, refresh_pool amortised
over the unroll).

  python bench/autoreset_cost.py --vehicle drone --envs 16384 65536 [--unroll 32] [--fused-ekf] [--phase2]
  python bench/autoreset_cost.py --envs 65536 --step-only --raw-mjx [--fused-ekf]     # the env step vs raw MJX

Prints ms per env step (best of 3, each a jitted lax.scan of `--unroll` steps), phase-1 env (--phase2: the
phase-2 env), zero action.
"""

import argparse
import time

import jax
import jax.numpy as jnp


def timed(fn, carry, reps):
  @jax.jit
  def run(c):
    return jax.lax.scan(lambda c, _: (fn(c), None), c, None, length=reps)[0]
  jax.block_until_ready(run(carry))
  best = float("inf")
  for _ in range(3):
    t = time.perf_counter()
    jax.block_until_ready(run(carry))
    best = min(best, (time.perf_counter() - t) / reps)
  return best * 1e3


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--envs", type=int, nargs="+", default=[16384, 65536])
  p.add_argument("--unroll", type=int, default=32)
  p.add_argument("--fused-ekf", action="store_true", help="the EKF's covariance work as the fused GPU kernel")
  p.add_argument("--phase2", action="store_true",
                 help="the phase-2 env (reactive control, residual detector, reconstruction and its shadow EKF)")
  p.add_argument("--shadow-xla", action="store_true",
                 help="with --fused-ekf --phase2: the shadow EKF keeps the XLA form (the autopilot's uses the kernel)")
  p.add_argument("--step-only", action="store_true", help="time Vmap(env).step only (no AutoReset variants)")
  p.add_argument("--raw-mjx", action="store_true",
                 help="also time raw MJX physics per env step (mjx.step x ticks_per_step, same model and batch)")
  a = p.parse_args()
  import envs
  from brax.envs.wrappers.training import VmapWrapper
  from envs.wrappers import AutoReset
  phase2 = dict(control_mode="reactive", detector="residual", reconstruction=True) if a.phase2 else {}
  env = envs.make(a.vehicle, fused_ekf=a.fused_ekf, **phase2)
  if a.shadow_xla:
    env._fused_shadow = False
  label = f"phase {2 if a.phase2 else 1}, EKF {'kernel' if a.fused_ekf else 'XLA'}" + (
      ", shadow EKF XLA" if a.fused_ekf and a.phase2 and a.shadow_xla else "")
  for n in a.envs:
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    st = jax.jit(jax.vmap(env.reset))(keys)
    act = jnp.zeros((n, env.action_size))
    plain = timed(lambda s: jax.vmap(env.step)(s, act), st, a.unroll)
    if a.raw_mjx:
      from mujoco import mjx
      ticks = env.config.ticks_per_step
      raw = timed(lambda d: jax.lax.fori_loop(0, ticks, lambda _, d: jax.vmap(lambda d: mjx.step(env.mjx_model, d))(d),
                                              d), st.pipeline_state, a.unroll)
      print(f"{jax.devices()[0].device_kind}, {a.vehicle}, {n} envs: raw MJX per env step ({ticks} x mjx.step) "
            f"{raw:.3f} ms; Vmap(env).step ({label}) / raw MJX = {plain / raw:.2f}x")
    if a.step_only:
      print(f"{jax.devices()[0].device_kind}, {a.vehicle} {label}, {n} envs: Vmap(env).step {plain:.3f} ms")
      continue
    rows = {"Vmap(env).step (no reset)": plain}
    per_step = AutoReset(VmapWrapper(env))
    bs = jax.jit(per_step.reset)(keys)
    rows["AutoReset, pool refreshed per step"] = timed(lambda s: per_step.step(s, act), bs, a.unroll)
    per_roll = AutoReset(VmapWrapper(env), refresh_in_step=False)
    step = timed(lambda s: per_roll.step(s, act), bs, a.unroll)
    refresh = timed(lambda s: per_roll.refresh_pool(s, a.unroll), bs, 4) / a.unroll
    rows["AutoReset, pool refreshed per rollout"] = step + refresh
    rows["  of which the step"] = step
    rows[f"  of which refresh_pool({a.unroll}) / {a.unroll}"] = refresh
    print(f"{jax.devices()[0].device_kind}, {a.vehicle} {label}, {n} envs (ms per env step)")
    for k, v in rows.items():
      print(f"  {k:40s} {v:8.3f}")


if __name__ == "__main__":
  main()
