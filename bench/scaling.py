"""Training throughput and scaling of the data-parallel trainer (ppo/distributed.py), memory headroom, a 1-vs-N-device
quality check, a profiler trace and a per-component breakdown of one training iteration.

  python bench/scaling.py --vehicle drone --envs 4096 65536 262144 --devices 1 --out /tmp/scal    # one GPU
  python bench/scaling.py --envs 16384 65536 --per-device --devices 1 2 --out /tmp/scal             # 2 GPUs
  python bench/scaling.py --envs 16384 --per-device --devices 1 2 --ekf-kernel xla --out /tmp/scal   # XLA EKF
  python bench/scaling.py --max-envs 262144 --out /tmp/scal        # largest env count that fits (doubling to OOM)
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.95 python bench/scaling.py --no-throughput --max-envs 524288 --out /tmp/scal
  python bench/scaling.py --quality 20000000 --devices 1 2 --out /tmp/scal   # same steps, 1 vs 2 devices
  python bench/scaling.py --profile --breakdown --envs 65536 --out /tmp/scal
  python bench/scaling.py --no-throughput --memory-plan --envs 262144 1048576 --out /tmp/scal   # compile only
  python bench/scaling.py --smoke --out /tmp/scal                   # tiny sizes on the CPU (checks it runs)

Throughput = env steps per second of whole training calls (acting + GAE + PPO epochs of SpecGuard; phase 2 also the
attack agent's turn), first call (compile) excluded. Prints markdown tables and writes <out>/scaling.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from specguard_jax.ppo import attacker, config, distributed, iteration, losses, runner  # noqa: E402


def _cfg(a, envs, devices, **kw):
  base = runner.default_sizes("gpu")
  c = config.TrainConfig(vehicle=a.vehicle, num_envs=envs, unroll_length=a.unroll, iters_per_call=a.iters_per_call,
                         phase1_steps=base["phase1_steps"], phase2_steps=base["phase2_steps"], num_devices=devices,
                         seed=a.seed, env_groups=kw.pop("env_groups", 0), network_dtype=a.network_dtype,
                         **kw).with_env(ekf_kernel=a.ekf_kernel)
  if a.smoke:
    tiny = config.PPOConfig(num_minibatches=2, update_epochs=1)
    c = dataclasses.replace(c, hidden=(32, 32), sg=tiny, aa=tiny).with_env(worlds=("suburban_residential",))
  return c.validate()


def _init_args(ph, cfg):
  """(key, SG state, AA state) replicated over the phase's mesh: the arguments of ph.init."""
  k = jax.random.PRNGKey(cfg.seed)
  sg = losses.with_hparams(ph.sg.init(k, cfg.n_obs), cfg.sg)
  aa = losses.with_hparams(ph.aa.init(k, attacker.N_OBS), cfg.aa)
  return distributed.replicate((k, sg, aa), ph.mesh)


def _fresh(ph, cfg):
  return ph.init(*_init_args(ph, cfg))


def _mem():
  try:
    st = jax.local_devices()[0].memory_stats() or {}
    if not st:
      return {}
    return {"in_use_gb": st.get("bytes_in_use", 0) / 2**30, "peak_gb": st.get("peak_bytes_in_use", 0) / 2**30,
            "limit_gb": st.get("bytes_limit", 0) / 2**30}
  except Exception:  # noqa: BLE001 - not every backend reports memory
    return {}


def throughput(a, envs, devices, phase):
  """(env steps/s, compile+first call s, memory) of `a.calls` timed calls of one phase."""
  cfg = _cfg(a, envs, devices)
  ph = iteration.make_phase(cfg, phase, distributed.make_mesh(devices))
  carry = _fresh(ph, cfg)
  t = time.perf_counter()
  carry, m = ph.run(carry)
  jax.block_until_ready(m)
  first = time.perf_counter() - t
  t = time.perf_counter()
  for _ in range(a.calls):
    carry, m = ph.run(carry)
    jax.device_get(m)     # what the runner does every call (metrics to the host)
  dt = time.perf_counter() - t
  sps = a.calls * cfg.iters_per_call * cfg.steps_per_iter / dt if a.calls else float("nan")
  del carry
  return sps, first, _mem()


def memory_plan(a, envs, devices, phase):
  """XLA's per-device memory plan of a phase's two programs at `envs` envs, compiled but never run (nothing of that
  size is allocated, so it answers "does N fit" without an out-of-memory trial): init (the first reset of the envs
  and their pool) and run (one training call). Bytes; peak = the larger of init's temporaries + its output and
  run's temporaries + its donated carry."""
  cfg = _cfg(a, envs, devices)
  ph = iteration.make_phase(cfg, phase, distributed.make_mesh(devices))
  args = _init_args(ph, cfg)
  init = ph.init.lower(*args).compile()
  carry = jax.tree.map(lambda s, sh: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sh),
                       jax.eval_shape(ph.init, *args), init.output_shardings)
  run = ph.run.lower(carry).compile()
  mi, mr = init.memory_analysis(), run.memory_analysis()
  out = {"envs": envs, "devices": devices, "phase": phase,
         "init_temp": mi.temp_size_in_bytes, "init_output": mi.output_size_in_bytes,
         "run_temp": mr.temp_size_in_bytes, "run_carry": mr.argument_size_in_bytes,
         "carry_bytes_global": sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(carry))}
  out["peak"] = max(out["init_temp"] + out["init_output"], out["run_temp"] + out["run_carry"])
  return out


def _is_oom(e):
  s = f"{type(e).__name__}: {e}"
  return any(k in s for k in ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory", "OOM", "Resource exhausted"))


def max_envs(a, start, devices, limit, on_step=lambda result: None):
  """Double the env count from `start` until a phase-2 call (compile + one call, the run's unroll and
  iterations per call) fails with an out-of-memory error (or `limit`); on_step gets the result so far after each
  size (a run cut short keeps what it measured)."""
  ok, tried, n = None, [], start
  while n <= limit:
    try:
      sps, first, mem = throughput(argparse.Namespace(**{**vars(a), "calls": 0}), n, devices, 2)
      tried.append({"envs": n, "ok": True, "sps": sps, "first_call_s": first, **mem})
      ok = n
      peak = (f", peak {mem['peak_gb']:.1f} GB of the {mem['limit_gb']:.1f} GB the allocator may use"
              if "peak_gb" in mem else "")   # backends without memory stats (CPU) report none
      print(f"  {n:>9} envs: ok (compile + one call {first:.0f} s{peak})", flush=True)
    except Exception as e:  # noqa: BLE001
      if not _is_oom(e):
        raise
      tried.append({"envs": n, "ok": False, "error": str(e).splitlines()[0][:200]})
      print(f"  {n:>9} envs: out of memory", flush=True)
      break
    finally:
      jax.clear_caches()
      on_step({"largest_ok": ok, "tried": tried})
    n *= 2
  return {"largest_ok": ok, "tried": tried}


_COMPILES = []   # (seconds since the run started, function, thread, XLA compile seconds) of the run being timed


def _on_compile(event, secs, fun_name="", **_):
  if event.endswith("backend_compile_duration") and secs > 1.0:
    _COMPILES.append((round(time.time() - _COMPILES_T0[0], 1), fun_name, threading.current_thread().name,
                      round(secs, 1)))


_COMPILES_T0 = [0.0]


def quality(a, steps, devices_list, envs):
  """The same short phase-1 + phase-2 run (same global batch and seed) on each device count. Each row has wall_s
  (the whole run), until_trained_s (wall_s less the held-out evaluation: time to target), train_wall_s (the
  training calls, compiles and compile waits included) and compiles: every XLA compile over 1 s, with its end time,
  function, thread and seconds."""
  jax.monitoring.register_event_duration_secs_listener(_on_compile)
  rows = []
  for d in devices_list:
    cfg = dataclasses.replace(_cfg(a, envs, d), phase1_steps=steps // 2, phase2_steps=steps - steps // 2,
                              eval_missions=a.eval_missions, checkpoint_every_s=1e9)
    t = time.time()
    _COMPILES.clear()
    _COMPILES_T0[0] = t
    s = runner.train(cfg, os.path.join(a.out, f"quality_d{d}"), progress=False, export=False,
                     compile_ahead=a.compile_ahead)
    fm = s["final_train_metrics"]
    wall = time.time() - t
    row = {"devices": d, "env_groups": s["env_groups"], "env_steps": s["env_steps"], "wall_s": wall,
           "until_trained_s": wall - s.get("heldout_wall_s", 0.0), "compiles": list(_COMPILES),
           "train_wall_s": s["train_wall_s"], "compile_s": s["compile_s"], "heldout_wall_s": s.get("heldout_wall_s"),
           "phase1": fm.get("1", {}), "phase2": fm.get("2", {})}
    if "heldout" in s:
      row["heldout"] = {k: {m: v[m] for m in ("svr", "rsr", "collision_rate") if m in v}
                        for k, v in s["heldout"].items() if k[0] != "_"}
    rows.append(row)
    print(f"  {d} device(s): return {row['phase2'].get('return', float('nan')):.2f}  SVR "
          f"{row['phase2'].get('svr', float('nan')):.3f}  RSR {row['phase2'].get('rsr', float('nan')):.3f}  "
          f"training calls {row['train_wall_s']:.0f} s, until trained {row['until_trained_s']:.0f} s; compiles (end s, "
          f"function, thread, s): {row['compiles']}", flush=True)
  return rows


def _timed(fn, *args, reps=3):
  f = jax.jit(fn)
  jax.block_until_ready(f(*args))
  best = float("inf")
  for _ in range(reps):
    t = time.perf_counter()
    jax.block_until_ready(f(*args))
    best = min(best, time.perf_counter() - t)
  return best


def breakdown(a, envs):
  """Seconds per training iteration of its pieces, each jitted alone on one device (XLA fuses across them in the
  real program, so they do not sum exactly): physics, env step (phase 1 / phase 2 = + attacker, detector,
  reconstruction), policy forward, PPO update, and the host's share of a call."""
  from mujoco import mjx
  cfg = _cfg(a, envs, 1)
  T = cfg.unroll_length
  ph1 = iteration.make_phase(cfg, 1, distributed.make_mesh(1))
  ph2 = iteration.make_phase(cfg, 2, distributed.make_mesh(1))
  c1, c2 = _fresh(ph1, cfg), _fresh(ph2, cfg)
  env = ph1.env
  s1 = jax.tree.map(lambda x: x[0], c1.env_state)   # group 0 = all envs on one device
  s2 = jax.tree.map(lambda x: x[0], c2.env_state)
  B = s1.obs.shape[0]
  ticks = env.config.ticks_per_step

  def scan(fn, x):
    return jax.lax.scan(lambda c, _: (fn(c), None), x, None, length=T)[0]

  rows = {}
  d = jax.jit(jax.vmap(env.physics_data))(s1.pipeline_state)   # a full mjx.Data per env, as raw MJX carries it
  rows["physics (mjx.step x ticks)"] = _timed(lambda d: scan(
      lambda d: jax.lax.fori_loop(0, ticks, lambda _, d: jax.vmap(lambda d: mjx.step(env.mjx_model, d))(d), d), d), d)
  rows["env step, phase 1 (AutoReset(Vmap(env)))"] = _timed(
      lambda s: scan(lambda s: ph1.batched.step(s, jnp.zeros((B, 3))), s), s1)
  rows["env step, phase 2 (+ attacker, detector, reconstruction)"] = _timed(
      lambda s: scan(lambda s: ph2.batched.step(s, jnp.zeros((B, 3 + attacker.N_ACT))), s), s2)
  sg = c1.sg
  k = jax.random.PRNGKey(0)
  rows["SG policy + value forward"] = _timed(lambda o: scan(lambda o: o + 1e-6 * ph1.sg.act(sg, o, k)[2][:, None], o),
                                             s1.obs)
  tr = {"obs": jnp.tile(s1.obs[None], (T, 1, 1)), "action": jnp.zeros((T, B, 3)), "logp": jnp.zeros((T, B)),
        "value": jnp.zeros((T, B)), "adv": jax.random.normal(k, (T, B)), "target": jnp.zeros((T, B)),
        "mask": jnp.ones((T, B))}
  rows["SG PPO update (epochs x minibatches)"] = _timed(lambda st, b: losses.update(ph1.sg, st, b, k)[0], sg, tr)
  def calls(ph, c, sync):
    c, m = ph.run(c)          # compile / warm up
    jax.block_until_ready(m)
    t = time.perf_counter()
    for _ in range(3):
      c, m = ph.run(c)
      if sync:
        jax.device_get(m)     # the runner's pattern: metrics to the host after every call
    jax.block_until_ready(c)
    return c, (time.perf_counter() - t) / (3 * cfg.iters_per_call)

  c1, it1 = calls(ph1, c1, False)
  c1, it1_host = calls(ph1, c1, True)
  c2, it2 = calls(ph2, c2, False)
  rows["whole iteration, phase 1"] = it1
  rows["whole iteration, phase 2"] = it2
  rows["host work per iteration (synced call loop - async loop, phase 1)"] = max(it1_host - it1, 0.0)
  print(f"\n### Per-iteration breakdown ({a.vehicle}, {envs} envs, unroll {T}, {jax.devices()[0].device_kind})\n")
  print("| piece | ms / iteration | share of phase-1 iteration |\n|---|---:|---:|")
  for name, v in rows.items():
    print(f"| {name} | {v * 1e3:.2f} | {100 * v / it1:.0f} % |")
  return {k_: v for k_, v in rows.items()}


def profile(a, envs, out):
  cfg = _cfg(a, envs, 1)
  ph = iteration.make_phase(cfg, 2, distributed.make_mesh(1))
  carry = _fresh(ph, cfg)
  carry, m = ph.run(carry)
  jax.block_until_ready(m)
  path = os.path.join(out, "trace")
  with jax.profiler.trace(path):
    carry, m = ph.run(carry)
    jax.block_until_ready(m)
  print(f"[scaling] profiler trace of one phase-2 call ({cfg.iters_per_call} iterations): {path} "
        "(open with TensorBoard's profile plugin or perfetto)")
  return path


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--vehicle", default="drone", choices=config.VEHICLES)
  ap.add_argument("--envs", type=int, nargs="+", default=[4096, 65536, 262144])
  ap.add_argument("--devices", type=int, nargs="+", help="device counts (default: 1 and all)")
  ap.add_argument("--per-device", action="store_true", help="--envs are per device (global = envs x devices)")
  ap.add_argument("--phases", type=int, nargs="+", default=[1, 2])
  ap.add_argument("--unroll", type=int, default=32)
  ap.add_argument("--iters-per-call", type=int, default=2)
  ap.add_argument("--calls", type=int, default=3, help="timed calls per measurement (after the compile call)")
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                  help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  ap.add_argument("--network-dtype", default="bfloat16", choices=("float32", "bfloat16"),
                  help="the agents' networks' compute dtype in training (train.py's flag; default: its GPU "
                       "default)")
  ap.add_argument("--no-throughput", action="store_true")
  ap.add_argument("--max-envs", type=int, metavar="START", help="double the env count from START until OOM")
  ap.add_argument("--max-envs-limit", type=int, default=1 << 22)
  ap.add_argument("--memory-plan", action="store_true",
                  help="compile (not run) init and one training call per --envs x --phases on the largest --devices "
                       "count and print XLA's per-device memory plan")
  ap.add_argument("--quality", type=int, metavar="STEPS", help="phase-1+2 run of STEPS env steps per device count")
  ap.add_argument("--quality-envs", type=int, default=16384)
  ap.add_argument("--eval-missions", type=int, default=0, help="held-out missions per setting after --quality runs")
  ap.add_argument("--compile-ahead", action=argparse.BooleanOptionalAction, default=None,
                  help="--quality runs: compile phase 2 and the evaluation ahead (train.py's flag; default: on "
                       "unless on the CPU)")
  ap.add_argument("--profile", action="store_true", help="jax.profiler trace of one phase-2 call to <out>/trace")
  ap.add_argument("--breakdown", action="store_true", help="per-component timing of one iteration")
  ap.add_argument("--smoke", action="store_true", help="tiny sizes (CPU check)")
  ap.add_argument("--out", default="/tmp/scaling")
  a = ap.parse_args(argv)
  if a.smoke:
    a.envs, a.unroll, a.calls, a.quality_envs = [16], 8, 1, 16
    a.max_envs_limit = min(a.max_envs_limit, 32)
  os.makedirs(a.out, exist_ok=True)
  ndev = len(jax.devices())
  devices = a.devices or sorted({1, ndev})
  if max(devices) > ndev:
    ap.error(f"--devices {max(devices)} > {ndev} available")
  res = {"device": jax.devices()[0].device_kind, "backend": jax.default_backend(), "available_devices": ndev,
         "vehicle": a.vehicle, "unroll": a.unroll, "iters_per_call": a.iters_per_call, "date": time.strftime("%F"),
         "throughput": []}
  save = lambda: json.dump(res, open(os.path.join(a.out, "scaling.json"), "w"), indent=1)  # noqa: E731
  if not a.no_throughput:
    print(f"### Training throughput ({a.vehicle}, {res['device']}, unroll {a.unroll}, compile excluded)\n")
    print("| devices | envs (global) | envs / device | phase | M env steps/s | x 1 device | first call s | peak GB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    for e in a.envs:
      for p in a.phases:
        base = None
        for d in devices:
          n = e * d if a.per_device else e
          sps, first, mem = throughput(a, n, d, p)
          base = base or (sps if d == 1 else None)
          row = {"devices": d, "envs": n, "envs_per_device": n // d, "phase": p, "env_steps_per_s": sps,
                 "first_call_s": first, **mem}
          res["throughput"].append(row)
          rel = f"{sps / base:.2f}" if base else "-"
          print(f"| {d} | {n} | {n // d} | {p} | {sps / 1e6:.3f} | {rel} | {first:.1f} | "
                f"{mem.get('peak_gb', float('nan')):.1f} |", flush=True)
          save()
          jax.clear_caches()
  if a.memory_plan:
    d = max(devices)
    print(f"\n### Memory plan ({a.vehicle}, {res['device']}, {d} device(s), unroll {a.unroll}, compiled, not run; "
          f"GiB per device)\n")
    print("| envs (global) | phase | init temporaries | init output | training call temporaries | carry | peak | "
          "bytes / env |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    res["memory_plan"] = []
    for e in a.envs:
      for p in a.phases:
        n = e * d if a.per_device else e
        row = memory_plan(a, n, d, p)
        res["memory_plan"].append(row)
        g = lambda b: f"{b / 2**30:.2f}"  # noqa: E731
        print(f"| {n} | {p} | {g(row['init_temp'])} | {g(row['init_output'])} | {g(row['run_temp'])} | "
              f"{g(row['run_carry'])} | {g(row['peak'])} | {row['peak'] * d / n:.0f} |", flush=True)
        save()
        jax.clear_caches()
  if a.max_envs:
    print(f"\n### Largest env count (phase 2, {max(devices)} device(s))", flush=True)
    res["max_envs"] = max_envs(a, a.max_envs, max(devices), a.max_envs_limit,
                               on_step=lambda r: (res.update(max_envs=r), save()))
    print(f"largest that ran: {res['max_envs']['largest_ok']}")
    save()
  if a.quality:
    print(f"\n### Same steps ({a.quality}), same global batch ({a.quality_envs} envs) and seed on {devices} devices",
          flush=True)
    res["quality"] = quality(a, a.quality, devices, a.quality_envs)
    save()
  if a.breakdown:
    res["breakdown_s_per_iteration"] = breakdown(a, a.envs[0])
    save()
  if a.profile:
    res["trace"] = profile(a, a.envs[0], a.out)
    save()
  print(f"\n[scaling] {os.path.join(a.out, 'scaling.json')}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
