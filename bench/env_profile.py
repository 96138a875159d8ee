"""Where an env step's time goes: each component jitted alone, vmapped over the batch, repeated in a lax.scan.

  python bench/env_profile.py --vehicle drone --envs 65536 [--reps 20]

Prints microseconds per call of the batch and the share of one env step (5 ticks). Components are measured in
isolation, so their sum differs from the fused step (XLA fuses across component boundaries in the real step).
The env is the phase-2 one (reactive control, residual detector, state reconstruction), so the residual detector's
and the reconstruction's per-tick costs are listed too; `--plain` profiles the phase-1 env (autopilot only).
"""

import argparse
import time

import jax
import jax.numpy as jnp
from mujoco import mjx


def timed(fn, carry, reps):
  @jax.jit
  def run(c):
    return jax.lax.scan(lambda c, _: (fn(c), None), c, None, length=reps)[0]
  out = run(carry)
  jax.block_until_ready(out)
  best = float("inf")
  for _ in range(3):
    t = time.perf_counter()
    out = run(carry)
    jax.block_until_ready(out)
    best = min(best, (time.perf_counter() - t) / reps)
  return best


def main():
  p = argparse.ArgumentParser()
  p.add_argument("--vehicle", default="drone")
  p.add_argument("--envs", type=int, default=65536)
  p.add_argument("--reps", type=int, default=20)
  p.add_argument("--plain", action="store_true", help="the phase-1 env (no detector, no reconstruction)")
  a = p.parse_args()
  import envs
  from brax.envs.wrappers.training import VmapWrapper
  from envs.wrappers import AutoReset
  from specguard_jax import ekf as ekf_lib
  from specguard_jax import ekf_lanes
  from specguard_jax import sensors as sensors_lib
  from envs import worlds
  phase2 = {} if a.plain else dict(control_mode="reactive", detector="residual", reconstruction=True)
  env = envs.make(a.vehicle, **phase2)
  n, k = a.envs, env.config.ticks_per_step
  keys = jax.random.split(jax.random.PRNGKey(0), n)
  state = jax.jit(jax.vmap(env.reset))(keys)
  info, sim = state.info, state.info["sim"]
  mission, world = info["mission"], info["world"]
  dt = env.config.tick_dt
  V = jax.vmap
  rows = []

  def add(name, fn, carry, per_step=1):
    t = timed(fn, carry, a.reps)
    rows.append((name, t, per_step))
    print(f"{name:34s} {t * 1e6:10.1f} us/call  x{per_step}", flush=True)

  data = jax.jit(V(env.physics_data))(state.pipeline_state)   # a full mjx.Data per env, as raw MJX carries it
  add("mjx.step (per-env model)", lambda d: V(lambda d, dr: mjx.step(env._model(dr), d))(d, sim["dr"]), data, k)
  add("mjx.step (shared model)", lambda d: V(lambda d: mjx.step(env.mjx_model, d))(d), data, k)
  add("sensors.sense", lambda c: V(lambda s, t, kk: sensors_lib.sense(env.sensor_cfg, s, t, kk, dt)[0])(
      c, sim["truth"], keys), sim["sensors"], k)
  for kernel in ("xla", "lanes") if ekf_lanes.resolve_ekf_kernel("auto") == "lanes" else ("xla",):
    add(f"ekf_step ({kernel})", lambda e: V(lambda e, r: ekf_lanes.ekf_step(
        env.ekf_cfg, e, r, dt, kernel=kernel))(e, sim["readings"]), sim["ekf"], k)
  add("ekf_step (xla, GPS rows stale)", lambda e: V(lambda e, r: ekf_lib.ekf_step(
      env.ekf_cfg, e, r, dt, stale=("gps",)))(e, sim["readings"]), sim["ekf"], k)

  if not a.plain:
    from specguard_jax import detection as detection_lib
    from specguard_jax.estimation import recon as recon_lib
    from specguard_jax.estimation import traces as traces_lib
    act = V(env._actuation)(sim)
    add("detector_update (residual)", lambda d: V(lambda d, r, e, u: detection_lib.detector_update(
        env.det_cfg, d, r, e, u, dt))(d, sim["readings"], sim["ekf"], act), sim["det"], k)
    u_prev = V(lambda s: traces_lib.vehicle_controls(env.vehicle, s))(sim)
    alarm = jnp.ones((n,), jnp.float32)     # under attack: the shadow filter and the replay carry real work
    mask = jnp.zeros((n, sim["det"].mask.shape[-1]), bool).at[:, 0].set(True)
    add("recon_tick (alarm up)", lambda r: V(lambda r, e, rd, u, m, al: recon_lib.recon_tick(
        env.recon_cfg, env.dyn_params, r, e, rd, u, m, al, dt)[0])(r, sim["ekf"], sim["readings"], u_prev, mask,
                                                                     alarm), sim["recon"], k)

  def tick_only(c):
    d, s = c
    return V(lambda d, s, m, w, kk: env._tick(d, s, m, w, jnp.zeros(3), jnp.asarray(False), kk))(
        d, s, mission, world, keys)
  add("whole tick (all of the above+nav+ctl)", tick_only, (state.pipeline_state, sim), k)
  add("world_queries", lambda p: p + 1e-3 * V(lambda w, m, p: worlds.world_queries(w, m, p, 0)["dist_wp"])(
      world, mission, p)[:, None], sim["truth"].pos)
  add("observation", lambda p: V(lambda w, m, s: env._observation(w, m, s))(world, mission, sim)[:, :3] * 1e-3 + p,
      sim["truth"].pos)
  add("STL monitor + reward", lambda m: V(lambda m, s: env.spec_eval.monitor_update(m, s)[0])(m, info["signals"]),
      info["spec_monitor"])
  add("env.step (vmapped, no reset)", lambda s: V(env.step)(s, jnp.zeros((n, 3))), state)
  benv = AutoReset(VmapWrapper(env))
  bstate = jax.jit(benv.reset)(keys)
  add("AutoReset(Vmap(env)).step", lambda s: benv.step(s, jnp.zeros((n, 3))), bstate)
  step = [t for name, t, _ in rows if name.startswith("AutoReset")][0]
  print(f"\n{a.vehicle}, {n} envs, {jax.devices()[0].device_kind}: share of one AutoReset env step")
  for name, t, per in rows:
    print(f"  {name:34s} {100 * t * per / step:6.1f} %")


if __name__ == "__main__":
  main()
