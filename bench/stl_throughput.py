"""STL throughput: all drone specs (S1..S12) evaluated offline over a batch of episodes, plus the online monitor.

  python bench/stl_throughput.py --backend gpu   # 65,536 traces x 1,000 steps (dt 0.1 s)
  python bench/stl_throughput.py --backend cpu   # 4,096 traces x 500 steps, beside rtamt on the same work

rtamt (pure Python) is timed on a subset of the traces and extrapolated linearly to the full batch (its cost is
linear in the number of traces); the output says so. Its results are also compared with ours on that subset.
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def _parse_args():
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--backend", choices=["cpu", "gpu"], default="cpu")
  p.add_argument("--traces", type=int, default=None, help="batch size (default 65536 gpu / 4096 cpu)")
  p.add_argument("--steps", type=int, default=None, help="trace length (default 1000 gpu / 500 cpu)")
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--rtamt-subset", type=int, default=16, help="traces timed with rtamt (cpu backend)")
  p.add_argument("--no-rtamt", action="store_true")
  p.add_argument("--dt", type=float, default=0.1, help="seconds per env step")
  return p.parse_args()


ARGS = _parse_args()
os.environ.setdefault("JAX_PLATFORMS", "cuda" if ARGS.backend == "gpu" else "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from specguard_jax import specs, stl  # noqa: E402
from specguard_jax.signals import SIGNAL_NAMES  # noqa: E402


def make_signals(key, n, t, dt):
  """Synthetic mission-like traces on device: smooth random walks around nominal values, phases in order."""
  keys = jax.random.split(key, len(SIGNAL_NAMES) + 1)
  steps = jnp.arange(t)
  frac = steps / t
  phase_split = jax.random.uniform(keys[-1], (n, 1), minval=-0.03, maxval=0.03)
  in_takeoff = (frac < 0.1 + phase_split).astype(jnp.float32)
  in_landing = (frac >= 0.9 + phase_split).astype(jnp.float32)
  in_loiter = ((frac >= 0.8 + phase_split) & (in_landing == 0)).astype(jnp.float32)
  in_cruise = 1.0 - in_takeoff - in_landing - in_loiter
  base = {"obstacle_distance": 20.0, "path_deviation": 3.0, "altitude": 15.0, "dist_wp": 40.0, "dist_final": 150.0,
          "wp_slack": 10.0, "fence_margin": 6.0, "fence_h": 10.0, "fence_v": 6.0, "loiter_deviation": 2.0,
          "speed_xy": 8.0, "speed_z": 0.0, "descent_speed": 0.0}
  out = {}
  for i, name in enumerate(SIGNAL_NAMES):
    if name in base:
      walk = jnp.cumsum(jax.random.normal(keys[i], (n, t)), axis=-1) * 0.05
      out[name] = (base[name] + walk).astype(jnp.float32)
  out["speed_z"] = out["speed_z"] + 2.5 * in_takeoff
  out["descent_speed"] = jnp.maximum(0.0, -out["speed_z"]) + 0.4 * in_landing
  out["loiter_deviation"] = out["loiter_deviation"] * in_loiter
  out.update(in_takeoff=in_takeoff, in_landing=in_landing, in_loiter=in_loiter, in_cruise=in_cruise,
             time=jnp.broadcast_to(steps * dt, (n, t)).astype(jnp.float32))
  for name in SIGNAL_NAMES:  # phase indicators this synthetic mission never enters (in_turn, in_descent)
    out.setdefault(name, jnp.zeros((n, t), jnp.float32))
  return out


def timeit(fn, *args, repeats):
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    best = min(best, time.perf_counter() - t0)
  return compile_s, best


def rtamt_eval(formulas, names, sig_np, idx):
  import rtamt
  out = np.zeros((len(idx), len(formulas)))
  for j, f in enumerate(formulas):
    text = str(f)  # step intervals; rtamt's default 1 s sampling period makes [a,b] = samples
    spec = rtamt.StlDiscreteTimeSpecification()  # parsed once per spec (parsing is not timed per trace)
    used = stl.signals_of(f)
    for v in used:
      spec.declare_var(v, "float")
    spec.spec = text
    spec.parse()
    for r, i in enumerate(idx):
      ds = {"time": list(range(sig_np[used[0]].shape[1]))}
      ds.update({v: sig_np[v][i].astype(np.float64).tolist() for v in used})
      out[r, j] = spec.evaluate(ds)[0][1]
  return out


def main():
  gpu = ARGS.backend == "gpu"
  n = ARGS.traces or (65536 if gpu else 4096)
  t = ARGS.steps or (1000 if gpu else 500)
  dev = jax.devices()[0]
  print(f"device: {dev.platform} {getattr(dev, 'device_kind', '')}  jax {jax.__version__}")
  table = specs.drone_specs()
  ev = specs.compile_specs(table, ARGS.dt)
  print(f"work: {len(ev.names)} drone specs ({', '.join(ev.names)}) over {n:,} traces x {t:,} steps "
        f"(dt {ARGS.dt} s); windows of S7/S10 span {int(round(3.0 / ARGS.dt)) + 1} steps")
  sig = jax.jit(make_signals, static_argnums=(1, 2, 3))(jax.random.PRNGKey(0), n, t, ARGS.dt)
  jax.block_until_ready(sig)

  offline = jax.jit(lambda s: ev(s))
  c, best = timeit(offline, sig, repeats=ARGS.repeats)
  rob, viol = offline(sig)
  tps = n * t / best
  print(f"offline (whole-episode robustness + violation flags, all specs): compile {c:.2f} s, best of "
        f"{ARGS.repeats}: {best * 1e3:.1f} ms = {n / best:,.0f} traces/s = {tps / 1e6:,.1f} M trace-steps/s "
        f"= {tps * len(ev.names) / 1e6:,.1f} M spec-steps/s")
  print(f"  violation rate per spec on the synthetic traces: "
        + " ".join(f"{k}={v:.2f}" for k, v in zip(ev.names, np.asarray(viol).mean(0))))

  every = jax.jit(lambda s: ev.robustness_trace(s))
  c, best_all = timeit(every, sig, repeats=max(1, ARGS.repeats // 2))
  print(f"offline robustness at every index ([N, T, 12] output): compile {c:.2f} s, best {best_all * 1e3:.1f} ms "
        f"= {n * t / best_all / 1e6:,.1f} M trace-steps/s")

  def online_run(s):
    state = ev.monitor_init((n,))
    xs = {k: v.T for k, v in s.items()}
    state, out = jax.lax.scan(lambda st, x: ev.monitor_update(st, x)[:2], state, xs)
    return out[-1]

  online = jax.jit(online_run)
  c, best_on = timeit(online, sig, repeats=max(1, ARGS.repeats // 2))
  diff = float(jnp.max(jnp.abs(online(sig) - rob)))
  print(f"online monitor (lax.scan over {t} env steps, fixed state, all specs): compile {c:.2f} s, best "
        f"{best_on * 1e3:.1f} ms = {n * t / best_on / 1e6:,.1f} M env-steps/s; max |online final - offline| = "
        f"{diff:.2e}")

  if gpu or ARGS.no_rtamt:
    return
  m = min(ARGS.rtamt_subset, n)
  sig_np = {k: np.asarray(v[:m]) for k, v in sig.items()}
  t0 = time.perf_counter()
  ref = rtamt_eval(ev.formulas, ev.names, sig_np, range(m))
  rt = time.perf_counter() - t0
  est = rt * n / m
  print(f"rtamt 0.4.10 (offline discrete-time, pure Python): {m} traces took {rt:.2f} s -> EXTRAPOLATED linearly to "
        f"{n:,} traces: {est:.0f} s = {n * t / est / 1e3:,.1f} k trace-steps/s (not measured on the full batch)")
  print(f"speed-up of the JAX evaluator over rtamt on this CPU: {est / best:,.0f}x")
  d = np.abs(np.asarray(rob[:m], np.float64) - ref)
  print(f"agreement with rtamt on the subset: max |diff| = {np.max(d):.2e}")


if __name__ == "__main__":
  sys.exit(main())
