"""Env throughput: full env step (sensors, EKF, navigator, autopilot, world queries, MJX) vs raw MJX physics.

  python bench/env_throughput.py [--vehicles drone rover] [--envs 4096 65536 262144] [--steps 50] [--json OUT]
      [--trainer-env] [--ekf-kernel auto|xla|lanes]

For each vehicle and batch size: env steps/s (one env step = ticks_per_step autopilot ticks = 0.1 s of flight),
control ticks/s, raw `mjx.step` steps/s of the same MJCF model at the same batch (ctrl/forces held constant), and
the cost ratio raw_mjx_steps_per_s / env_ticks_per_s (1.0 = the env costs no more than its physics). Auto-reset
(new mission + world per finished episode) is included, as in training. Timing excludes compilation (reported).
--trainer-env: the env as the trainer steps it (ppo/iteration.py: no NaN fallback, the reset pool refreshed once per
rollout of --steps steps instead of inside every step); --ekf-kernel: the EKF tick's kernel (EnvConfig.ekf_kernel).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp


def _time(fn, *args, repeats=3):
  out = fn(*args)
  jax.block_until_ready(out)
  best = float("inf")
  for _ in range(repeats):
    t = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    best = min(best, time.perf_counter() - t)
  return best, out


def bench_env(vehicle: str, n_envs: int, steps: int, autoreset: bool = True, trainer_env: bool = False,
              ekf_kernel: str = "auto") -> dict:
  import envs
  from brax.envs.wrappers.training import VmapWrapper
  from envs.wrappers import AutoReset

  from specguard_jax.ppo.iteration import trainer_env_options
  env = envs.make(vehicle, ekf_kernel=ekf_kernel, **(trainer_env_options() if trainer_env else {}))
  benv = AutoReset(VmapWrapper(env), refresh_in_step=not trainer_env) if autoreset else VmapWrapper(env)
  keys = jax.random.split(jax.random.PRNGKey(0), n_envs)
  t0 = time.perf_counter()
  state = jax.jit(benv.reset)(keys)
  jax.block_until_ready(state.obs)
  reset_compile = time.perf_counter() - t0

  @jax.jit
  def run(state):
    def body(s, _):
      return benv.step(s, jnp.zeros((n_envs, 3))), None
    out = jax.lax.scan(body, state, None, length=steps)[0]
    return benv.refresh_pool(out, steps) if autoreset and trainer_env else out

  t0 = time.perf_counter()
  state = run(state)
  jax.block_until_ready(state.obs)
  compile_s = time.perf_counter() - t0
  dt, _ = _time(run, state)
  sps = n_envs * steps / dt
  return {"env_steps_per_s": sps, "ticks_per_s": sps * env.config.ticks_per_step, "compile_s": compile_s,
          "reset_compile_s": reset_compile, "ticks_per_step": env.config.ticks_per_step}


def bench_mjx(vehicle: str, n_envs: int, steps: int) -> dict:
  import mujoco
  from mujoco import mjx

  from envs.base import ASSETS
  import os
  m = mujoco.MjModel.from_xml_path(os.path.join(ASSETS, f"{vehicle}.xml"))
  mx = mjx.put_model(m)
  d = mjx.make_data(mx)
  if m.nu:
    d = d.replace(ctrl=jnp.full((m.nu,), 1.5 * 9.81 / m.nu))
  else:
    d = d.replace(qfrc_applied=jnp.array([10.0, 0.0, 0.1]))
  batch = jax.vmap(lambda _: d)(jnp.arange(n_envs))

  @jax.jit
  def run(b):
    def body(x, _):
      return jax.vmap(lambda dd: mjx.step(mx, dd))(x), None
    return jax.lax.scan(body, b, None, length=steps)[0]

  dt, _ = _time(run, batch)
  return {"mjx_steps_per_s": n_envs * steps / dt}


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicles", nargs="+", default=["drone", "rover"])
  p.add_argument("--envs", nargs="+", type=int, default=[4096, 65536, 262144])
  p.add_argument("--steps", type=int, default=50, help="env steps per timed call")
  p.add_argument("--json", default=None, help="also write results to this JSON file")
  p.add_argument("--no-autoreset", action="store_true", help="time the bare vmapped env (episodes may end)")
  p.add_argument("--trainer-env", action="store_true",
                 help="no NaN fallback, the reset pool refreshed once per --steps rollout (as ppo/iteration.py)")
  p.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                 help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  args = p.parse_args()
  dev = jax.devices()[0]
  print(f"device: {dev.device_kind} ({jax.default_backend()}), jax {jax.__version__}")
  rows = []
  for vehicle in args.vehicles:
    for n in args.envs:
      r = {"vehicle": vehicle, "envs": n}
      r.update(bench_env(vehicle, n, args.steps, autoreset=not args.no_autoreset, trainer_env=args.trainer_env,
                         ekf_kernel=args.ekf_kernel))
      r.update(autoreset=not args.no_autoreset, trainer_env=args.trainer_env, ekf_kernel=args.ekf_kernel)
      r.update(bench_mjx(vehicle, n, args.steps * r["ticks_per_step"]))
      r["cost_ratio"] = r["mjx_steps_per_s"] / r["ticks_per_s"]
      rows.append(r)
      print(f"{vehicle:6s} envs={n:>8d}  env steps/s={r['env_steps_per_s']:>12.4g}  ticks/s={r['ticks_per_s']:>12.4g}  "
            f"raw mjx steps/s={r['mjx_steps_per_s']:>12.4g}  cost ratio={r['cost_ratio']:.2f}  "
            f"compile={r['compile_s']:.1f}s", flush=True)
  if args.json:
    with open(args.json, "w") as f:
      json.dump({"device": dev.device_kind, "date": time.strftime("%F"), "rows": rows}, f, indent=1)


if __name__ == "__main__":
  main()
