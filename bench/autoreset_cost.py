"""What an auto-reset costs per env step: `Vmap(env).step` alone vs `AutoReset` with the reset pool refreshed inside
every step (the default; Brax's loop uses it) vs refreshed once per rollout (the trainer's form, refresh_pool amortised
over the unroll).

  python bench/autoreset_cost.py --vehicle drone --envs 16384 65536 [--unroll 32] [--ekf-kernel xla] [--phase2]
  python bench/autoreset_cost.py --envs 65536 --step-only --raw-mjx [--ekf-kernel xla]     # the env step vs raw MJX
  python bench/autoreset_cost.py --envs 16384 --sparse-reset          # A/B: only the finished envs written
  python bench/autoreset_cost.py --envs 65536 --trainer-only --ab-nan-fallback   # A/B: the trainer's env
  python bench/autoreset_cost.py --envs 65536 --step-only --ab-tick-cond   # A/B: GPS schedule by lax.cond

Prints ms per env step (best of 3, each a jitted lax.scan of `--unroll` steps), phase-1 env (--phase2: the
phase-2 env), zero action.
"""

import argparse
import time

import jax
import jax.numpy as jnp


def timed(fn, carry, reps, first_call=None):
  """Best of 3 ms per step of `reps` steps of fn in one jitted scan; first_call: a list the first call's s (compile
  included) is appended to."""
  @jax.jit
  def run(c):
    return jax.lax.scan(lambda c, _: (fn(c), None), c, None, length=reps)[0]
  t = time.perf_counter()
  jax.block_until_ready(run(carry))
  if first_call is not None:
    first_call.append(time.perf_counter() - t)
  best = float("inf")
  for _ in range(3):
    t = time.perf_counter()
    jax.block_until_ready(run(carry))
    best = min(best, (time.perf_counter() - t) / reps)
  return best * 1e3


def sparse_autoreset(base, frac: int = 16):
  """A subclass of AutoReset `base` that, when at most B / frac envs finished (the usual case: episodes last tens to
  hundreds of steps), writes the fresh pool states into the finished envs only (a scatter of B / frac rows per state
  leaf) instead of selecting between two whole batches; more finished envs take `base`'s select (a lax.cond on the
  count). The same values as `base`'s."""
  class SparseAutoReset(base):
    def _take_fresh(self, out, pool, cursor):
      done = out.done > 0
      b, pool_n = done.shape[0], pool.done.shape[0]
      k = max(1, b // frac)
      count = jnp.sum(done.astype(jnp.int32))

      def sparse(out):
        env_idx = jnp.nonzero(done, size=k, fill_value=b)[0]          # finished envs in order, then out of range
        fresh = jax.tree.map(lambda x: x[(cursor + jnp.arange(k)) % pool_n], pool)
        merged = jax.tree.map(lambda o, f: o.at[env_idx].set(f, mode="drop"), out, fresh)
        return merged.replace(reward=out.reward, done=out.done, metrics=out.metrics)

      merged = jax.lax.cond(count <= k, sparse, lambda o: base._take_fresh(self, o, pool, cursor)[0], out)
      return merged, count

  return SparseAutoReset


def with_cond_gps_schedule(env):
  """`env` with the env's earlier tick loop: one scan over the step's ticks, the GPS-free ticks' EKF variant picked
  by a lax.cond on the (unbatched) tick index, instead of envs.base's static grouping (the same values)."""
  p = env._gps_period
  if p is None:
    raise SystemExit("--ab-tick-cond: this env has no GPS schedule (CPU backend, or the GPS period does not divide "
                     "ticks_per_step)")

  def tick_loop(tick, carry, keys):
    ticks = jnp.arange(keys.shape[0], dtype=jnp.int32)
    return jax.lax.scan(lambda c, xs: tick(c, xs[0], (xs[1] + 1) % p == 0), carry, (keys, ticks))

  env._tick_loop = tick_loop
  return env


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--envs", type=int, nargs="+", default=[16384, 65536])
  p.add_argument("--unroll", type=int, default=32)
  p.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                 help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  p.add_argument("--phase2", action="store_true",
                 help="the phase-2 env (reactive control, residual detector, reconstruction and its shadow EKF)")
  p.add_argument("--shadow-xla", action="store_true",
                 help="with --phase2 and the lanes kernel: the shadow EKF keeps the XLA form (the autopilot's "
                      "uses the kernel)")
  p.add_argument("--step-only", action="store_true", help="time Vmap(env).step only (no AutoReset variants)")
  p.add_argument("--sparse-reset", action="store_true",
                 help="also time the trainer's AutoReset step writing only the finished envs (sparse_autoreset) and "
                      "check that it gives the same states")
  p.add_argument("--no-check", action="store_true",
                 help="with --sparse-reset: time only, skip the same-states check (4 compiles each)")
  p.add_argument("--trainer-only", action="store_true",
                 help="skip the per-step pool refresh and refresh_pool timings (the trainer's step and variants only)")
  p.add_argument("--ab-nan-fallback", action="store_true",
                 help="also time the trainer's env (ppo/iteration.trainer_env_options: no NaN fallback, AutoReset "
                      "replaces NaN-terminated envs; no EKF records unless the detector reads them): Vmap(env).step "
                      "and, without --step-only, the trainer's step")
  p.add_argument("--raw-mjx", action="store_true",
                 help="also time raw MJX physics per env step (mjx.step x ticks_per_step, same model and batch)")
  p.add_argument("--unroll-ticks", action="store_true", help="EnvConfig.unroll_ticks in every env timed")
  p.add_argument("--ab-tick-cond", action="store_true",
                 help="also time Vmap(env).step with the GPS schedule picked per tick by a lax.cond (the earlier loop) "
                      "instead of the static grouping, and print both first-call (compile) times")
  a = p.parse_args()
  import envs
  from brax.envs.wrappers.training import VmapWrapper
  from envs.wrappers import AutoReset
  env_kw = dict(control_mode="reactive", detector="residual", reconstruction=True) if a.phase2 else {}
  if a.unroll_ticks:
    env_kw["unroll_ticks"] = True
  env = envs.make(a.vehicle, ekf_kernel=a.ekf_kernel, **env_kw)
  from specguard_jax import ekf as ekf_lib
  from specguard_jax.ppo.iteration import trainer_env_options
  trainer = trainer_env_options(env_kw.get("detector", "none"))
  env_nf = envs.make(a.vehicle, ekf_kernel=a.ekf_kernel, **trainer, **env_kw) if a.ab_nan_fallback else None
  if a.shadow_xla:
    env._shadow_kernel = "xla"
    if env_nf is not None:
      env_nf._shadow_kernel = "xla"
  env_cond = with_cond_gps_schedule(envs.make(a.vehicle, ekf_kernel=a.ekf_kernel, **env_kw)) if a.ab_tick_cond else None
  label = (f"phase {2 if a.phase2 else 1}, EKF {env._ekf_kernel}" + (", ticks unrolled" if a.unroll_ticks else "")
           + (", shadow EKF XLA" if env._ekf_kernel == "lanes" and a.phase2 and a.shadow_xla else ""))
  for n in a.envs:
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    st = jax.jit(jax.vmap(env.reset))(keys)
    act = jnp.zeros((n, env.action_size))
    first = []
    plain = timed(lambda s: jax.vmap(env.step)(s, act), st, a.unroll, first)
    if env_cond is not None:
      plain_cond = timed(lambda s: jax.vmap(env_cond.step)(s, act), st, a.unroll, first)
      print(f"{jax.devices()[0].device_kind}, {a.vehicle} {label}, {n} envs: Vmap(env).step {plain:.3f} ms (first "
            f"call {first[0]:.1f} s); with the GPS schedule by lax.cond {plain_cond:.3f} ms (first call "
            f"{first[1]:.1f} s)", flush=True)
    if a.raw_mjx:
      from mujoco import mjx
      ticks = env.config.ticks_per_step
      raw = timed(lambda d: jax.lax.fori_loop(0, ticks, lambda _, d: jax.vmap(lambda d: mjx.step(env.mjx_model, d))(d),
                                              d), jax.jit(jax.vmap(env.physics_data))(st.pipeline_state), a.unroll)
      print(f"{jax.devices()[0].device_kind}, {a.vehicle}, {n} envs: raw MJX per env step ({ticks} x mjx.step) "
            f"{raw:.3f} ms; Vmap(env).step ({label}) / raw MJX = {plain / raw:.2f}x")
    if env_nf is not None:
      plain_nf = timed(lambda s: jax.vmap(env_nf.step)(s, act), st, a.unroll)
      print(f"{jax.devices()[0].device_kind}, {a.vehicle} {label}, {n} envs: Vmap(env).step as the trainer configures "
            f"the env (no NaN fallback, EKF records {'on' if trainer['ekf_records'] else 'off'}) {plain_nf:.3f} ms "
            f"(EnvConfig's defaults {plain:.3f} ms)", flush=True)
    if a.step_only:
      print(f"{jax.devices()[0].device_kind}, {a.vehicle} {label}, {n} envs: Vmap(env).step {plain:.3f} ms")
      continue
    dev = jax.devices()[0].device_kind
    print(f"{dev}, {a.vehicle} {label}, {n} envs (ms per env step)")
    row = lambda k, v: print(f"  {k:40s} {v:8.3f}", flush=True)   # noqa: E731
    row("Vmap(env).step (no reset)", plain)
    per_step = AutoReset(VmapWrapper(env))
    bs = jax.jit(per_step.reset)(keys)
    per_roll = AutoReset(VmapWrapper(env), refresh_in_step=False)
    if not a.trainer_only:
      row("AutoReset, pool refreshed per step", timed(lambda s: per_step.step(s, act), bs, a.unroll))
    step = timed(lambda s: per_roll.step(s, act), bs, a.unroll)
    if not a.trainer_only:
      refresh = timed(lambda s: per_roll.refresh_pool(s, a.unroll), bs, 4) / a.unroll
      row("AutoReset, pool refreshed per rollout", step + refresh)
      row(f"  of which refresh_pool({a.unroll}) / {a.unroll}", refresh)
    row("  the step (the trainer's)", step)
    variants = {}
    if a.sparse_reset:
      variants["finished envs only"] = sparse_autoreset(AutoReset)(VmapWrapper(env), refresh_in_step=False)
    if env_nf is not None:   # same states after the auto-reset (a NaN-terminated env is replaced either way)
      variants["the trainer's env"] = AutoReset(VmapWrapper(env_nf), refresh_in_step=False)
    # every other (every 64th) env past its time limit, so that the first step ends those episodes and resets them
    ending = lambda every: bs.replace(info=dict(bs.info, time=jnp.where(jnp.arange(n) % every == 0, 1e6,  # noqa
                                                                        bs.info["time"])))
    roll = lambda w, s0: jax.jit(lambda s: jax.lax.scan(lambda s, _: (w.step(s, act), None), s, None,  # noqa: E731
                                                        length=a.unroll)[0])(s0)
    for name, w in variants.items():
      row(f"  the step, {name}", timed(lambda s: w.step(s, act), bs, a.unroll))   # noqa: B023
      if a.no_check:
        continue
      for what, s0 in (("half of the envs", ending(2)), ("1 in 64 envs", ending(64))):
        s_ref, s_var = roll(per_roll, s0), roll(w, s0)
        records = tuple("." + f for f in ekf_lib.RECORD_FIELDS)   # the trainer's env may skip the EKF records
        diff = max(float(jnp.max(jnp.abs(x - y))) for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(s_ref),
                                                                           jax.tree.leaves(s_var))
                   if jnp.issubdtype(x.dtype, jnp.number) and x.size
                   and not jax.tree_util.keystr(path).endswith(records))
        print(f"  ({name}: largest difference from the default over {a.unroll} steps, {what} ending on the first "
              f"step: {diff:.3g})")


if __name__ == "__main__":
  main()
