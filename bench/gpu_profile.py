"""Where the GPU time of one training call (or of one vmapped EKF tick) goes, from a jax.profiler trace.

  python bench/gpu_profile.py --envs 16384 --phase 1 [--ekf-kernel xla] [--matmul-precision bf16]   # one training call, by stage
  python bench/gpu_profile.py --ekf --envs 65536 [--ekf-kernel xla]         # one vmapped ekf_step, by kernel
  python bench/gpu_profile.py --env-step --envs 65536 [--ekf-kernel xla] [--phase 2]   # vmapped env steps, by stage
  python bench/gpu_profile.py --env-step --raw-mjx --envs 65536             # the same steps' raw MJX physics
  python bench/gpu_profile.py --envs 16384 --iters-per-call 5 --keep-command-buffers --gaps   # where the GPU idles

The function is compiled ahead of time, so every GPU kernel event of the trace (its `hlo_op`) can be mapped to the
instruction's `op_name` in the optimised HLO, whose name stack carries the `jax.named_scope`s of ppo/iteration.py
and envs/ (rollout: policy, env_step > sensors, ekf, detector, reconstruction (> recon_replay, shadow_ekf),
navigator, autopilot, physics, stl_reward, collision, autoreset; then pool_refresh, gae, ppo_update). Prints the GPU time per stage (the innermost named scope
a kernel's fusion root carries, or for kernels without metadata the scope of their fused computation or operands;
XLA fuses across scope boundaries, so a fused kernel counts once, to its root's scope), the largest kernels, and the
host's share (wall time of the call minus the GPU's busy time).
Run it with XLA command buffers off (the script sets it unless --keep-command-buffers): kernels replayed inside a
CUDA graph are not always attributed to their HLO instruction.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Innermost first: a kernel is charged to the first of these found in its op_name's scope path.
STAGES = ("physics", "autopilot", "sensors", "ekf", "detector", "recon_replay", "shadow_ekf", "reconstruction",
          "navigator", "stl_reward", "collision", "autoreset", "env_step", "attack_agent", "policy", "bootstrap_value", "values",
          "episode_stats", "pool_refresh", "gae", "ppo_update")   # bootstrap_value: older traces' scope
_COMP = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s*(?:\(|\{)")
_DEF = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*)$")


def _parse(hlo_text: str):
  """One pass over an HLO module's text: ({name: op_name} of the instructions with metadata, {fusion: called
  computation}, {name: operand names}, {computation: op_names of its instructions})."""
  direct, calls, operands, comp_ops = {}, {}, {}, {}
  comp = None
  for line in hlo_text.splitlines():
    if line and not line[0].isspace():
      m = _COMP.match(line)
      comp = m.group(1) if m else comp
      continue
    m = _DEF.match(line)
    if not m:
      continue
    name, rest = m.groups()
    on = re.search(r'op_name="([^"]*)"', rest)
    if on:
      direct[name] = on.group(1)
      comp_ops.setdefault(comp, []).append(on.group(1))
    c = re.search(r"calls=%?([\w.\-]+)", rest)
    if c:
      calls[name] = c.group(1)
    args = rest.split("(", 1)[1] if "(" in rest else ""
    operands[name] = re.findall(r"%([\w.\-]+)", args.split("), ", 1)[0])
  return direct, calls, operands, comp_ops


def op_names(hlo_text: str) -> dict:
  """{instruction name: op_name} of every instruction of an HLO module's text that carries metadata."""
  return _parse(hlo_text)[0]


def attributed_op_names(hlo_text: str) -> dict:
  """{instruction name: op_name} like `op_names`, plus a guess for instructions without metadata (the copies,
  transposes and some fusions XLA creates): a fusion takes the op_name its fused computation's instructions carry
  most often (by stage), anything else that of its first operand that has one (two levels deep)."""
  direct, calls, operands, comp_ops = _parse(hlo_text)

  def guess(name, depth):
    if name in direct:
      return direct[name]
    if name in calls and comp_ops.get(calls[name]):
      ops = comp_ops[calls[name]]
      by_stage = collections.Counter(stage_of(o) for o in ops)
      best = max(by_stage, key=lambda st: (st != "other", by_stage[st]))
      return next(o for o in ops if stage_of(o) == best)
    if depth:
      for o in operands.get(name, ()):
        g = guess(o, depth - 1)
        if g:
          return g
    return ""

  return {name: guess(name, 2) for name in operands}


def stage_of(op_name: str) -> str:
  parts = set(re.split(r"[/()\[\]]", op_name))
  for s in STAGES:
    if s in parts:
      return s
  return "other"


def gpu_events(trace_dir: str) -> list:
  """[(name, hlo_op, dur us, ts us)] of the kernel events on the GPU lines of the trace's perfetto JSON."""
  paths = glob.glob(os.path.join(trace_dir, "**", "perfetto_trace.json.gz"), recursive=True)
  if not paths:
    raise FileNotFoundError(f"no perfetto_trace.json.gz under {trace_dir}")
  d = json.load(gzip.open(sorted(paths)[-1]))
  ev = d["traceEvents"] if isinstance(d, dict) else d
  gpu_pids = {e["pid"] for e in ev if e.get("ph") == "M" and e.get("name") == "process_name"
              and "GPU" in str(e.get("args", {}).get("name", ""))}
  out = []
  for e in ev:
    if e.get("ph") == "X" and e.get("pid") in gpu_pids:
      args = e.get("args", {})
      hlo = args.get("hlo_op") or args.get("long_name") or ""
      out.append((e.get("name", ""), str(hlo), float(e.get("dur", 0.0)), float(e.get("ts", 0.0))))
  return out


def busy_us(events) -> float:
  """GPU busy time (us): the union of the kernel intervals (overlapping streams counted once)."""
  iv = sorted((ts, ts + dur) for _, _, dur, ts in events)
  total, end = 0.0, -1e300
  for a, b in iv:
    if b <= end:
      continue
    total += b - max(a, end)
    end = b
  return total


def idle_gaps(events, names: dict, top: int = 15) -> dict:
  """The GPU's idle gaps between busy intervals (us, summed over the events), grouped by the kernel that ends the
  interval before the gap and the one that starts the next (hlo op, or kernel name, and its stage)."""
  iv = sorted(((ts, ts + dur, hlo or name[:50]) for name, hlo, dur, ts in events), key=lambda x: x[0])
  gaps, bins = collections.Counter(), collections.Counter()
  count = collections.Counter()
  end, last = None, None
  for a, b, k in iv:
    if end is not None and a > end:
      g = a - end
      key = (last, k)
      gaps[key] += g
      count[key] += 1
      bins["<5 us" if g < 5 else "5-20 us" if g < 20 else "20-100 us" if g < 100 else ">=100 us"] += g
    if end is None or b > end:
      end, last = b, k
  st = lambda k: stage_of(names.get(k, "")) if names.get(k) else "?"   # noqa: E731
  total = sum(gaps.values())
  print(f"\nGPU idle between kernels: {total / 1e3:.2f} ms in {sum(count.values())} gaps; by gap length: "
        + ", ".join(f"{b} {v / 1e3:.2f} ms" for b, v in sorted(bins.items())))
  print("\n| gap after (stage) | before (stage) | idle us | gaps |\n|---|---|---:|---:|")
  for (p, n), v in gaps.most_common(top):
    print(f"| {p} ({st(p)}) | {n} ({st(n)}) | {v:.0f} | {count[(p, n)]} |")
  return {"idle_us": total, "idle_bins_us": dict(bins)}


def profile(compiled, args, label: str, top: int = 15, runs: int = 1, show: tuple = (), gaps: bool = False):
  """Trace `runs` calls of an AOT-compiled function and print GPU time by stage, the largest kernels, and the
  largest kernels of each stage in `show`."""
  import jax
  names = attributed_op_names(compiled.as_text())
  jax.block_until_ready(compiled(*args))          # warm-up (allocations, autotuning caches)
  d = tempfile.mkdtemp(prefix="gpu_profile_")
  with jax.profiler.trace(d, create_perfetto_trace=True):
    t = time.perf_counter()
    for _ in range(runs):
      out = compiled(*args)
    jax.block_until_ready(out)
    wall = (time.perf_counter() - t) * 1e6 / runs
  ev = gpu_events(d)
  total = sum(dur for _, _, dur, _ in ev) / runs
  busy = busy_us(ev) / runs
  by_stage = collections.Counter()
  stage_kernels = collections.Counter()
  by_kernel = collections.Counter()
  count = collections.Counter()
  for name, hlo, dur, _ in ev:
    op = names.get(hlo, "")
    st = stage_of(op) if op else ("unattributed" if not hlo else "other")
    by_stage[st] += dur / runs
    stage_kernels[st] += 1
    key = (hlo or name[:60], st, op[-90:])
    by_kernel[key] += dur / runs
    count[key] += 1
  print(f"\n### {label}\n")
  print(f"wall {wall / 1e3:.2f} ms per call, GPU busy {busy / 1e3:.2f} ms (kernel time {total / 1e3:.2f} ms, "
        f"{len(ev) // max(runs, 1)} kernels), host/idle {max(wall - busy, 0) / 1e3:.2f} ms\n")
  print("| stage | GPU ms per call | share of kernel time | kernels per call |\n|---|---:|---:|---:|")
  for st, v in by_stage.most_common():
    print(f"| {st} | {v / 1e3:.2f} | {100 * v / max(total, 1e-9):.1f} % | {stage_kernels[st] // max(runs, 1)} |")
  print("\n| largest kernels (hlo op) | stage | us per call | launches | op_name (tail) |\n|---|---|---:|---:|---|")
  for (k, st, op), v in by_kernel.most_common(top):
    print(f"| {k} | {st} | {v:.0f} | {count[(k, st, op)] // max(runs, 1)} | {op} |")
  for want in show:
    print(f"\n| largest kernels of stage {want} | us per call | launches | op_name (tail) |\n|---|---:|---:|---|")
    for (k, st, op), v in [kv for kv in by_kernel.most_common() if kv[0][1] == want][:top]:
      print(f"| {k} | {v:.0f} | {count[(k, st, op)] // max(runs, 1)} | {op} |")
  res = {"wall_us": wall, "busy_us": busy, "kernel_us": total, "stages_us": dict(by_stage),
         "stage_kernels": {k: v // max(runs, 1) for k, v in stage_kernels.items()}}
  if gaps:
    res.update(idle_gaps(ev, names, top))
  return res


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  ap.add_argument("--envs", type=int, default=16384)
  ap.add_argument("--phase", type=int, default=1, choices=(1, 2))
  ap.add_argument("--unroll", type=int, default=32)
  ap.add_argument("--iters-per-call", type=int, default=1)
  ap.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                  help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  ap.add_argument("--matmul-precision", default="default", choices=("default", "bf16"),
                  help="the agents' network matmuls (train.py's flag; training call only)")
  ap.add_argument("--network-dtype", default="bfloat16", choices=("float32", "bfloat16"),
                  help="the agents' networks' compute dtype (train.py's flag; default: its GPU default)")
  ap.add_argument("--ekf", action="store_true", help="profile one vmapped ekf_step (every sensor fresh) instead")
  ap.add_argument("--env-step", action="store_true",
                  help="profile --steps vmapped env steps (zero action, no auto-reset) instead of a training call")
  ap.add_argument("--raw-mjx", action="store_true",
                  help="with --env-step: only the physics, mjx.step x ticks_per_step per env step (same model, batch)")
  ap.add_argument("--steps", type=int, default=4, help="env steps per profiled call (--env-step)")
  ap.add_argument("--no-nan-fallback", action="store_true",
                  help="--env-step: the trainer's env (ppo/iteration.trainer_env_options: no NaN fallback, no EKF "
                       "records in phase 1)")
  ap.add_argument("--top", type=int, default=15)
  ap.add_argument("--show", nargs="*", default=["other"], help="stages whose largest kernels are listed too")
  ap.add_argument("--keep-command-buffers", action="store_true")
  ap.add_argument("--gaps", action="store_true",
                  help="also list the GPU's idle gaps by the kernels around them (use with --keep-command-buffers "
                       "to see a normal run's idle time)")
  ap.add_argument("--json", help="write the figures here")
  ap.add_argument("--hlo-out", help="training call or --env-step: also write its optimised HLO text here (to look "
                                    "up a kernel's shapes and operands by its hlo op name)")
  a = ap.parse_args(argv)
  if not a.keep_command_buffers:
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_gpu_enable_command_buffer="
  import jax
  dev = jax.devices()[0].device_kind
  if a.ekf:
    import envs
    from specguard_jax import ekf_lanes
    env = envs.make(a.vehicle, ekf_kernel=a.ekf_kernel)   # with the kernel, P in its packed layout as in the env
    keys = jax.random.split(jax.random.PRNGKey(0), a.envs)
    sim = jax.jit(jax.vmap(env.reset))(keys).info["sim"]
    fn = jax.jit(jax.vmap(lambda e, r: ekf_lanes.ekf_step(env.ekf_cfg, e, r, env.config.tick_dt,
                                                          kernel=env._ekf_kernel)))
    args = (sim["ekf"], sim["readings"])
    label = (f"one vmapped ekf_step ({env._ekf_kernel}), {a.vehicle}, {a.envs} envs, "
             f"{dev}")
    res = profile(fn.lower(*args).compile(), args, label, a.top, runs=5, show=a.show)
  elif a.env_step:
    import jax.numpy as jnp

    import envs
    phase2 = dict(control_mode="reactive", detector="residual", reconstruction=True) if a.phase == 2 else {}
    from specguard_jax.ppo.iteration import trainer_env_options
    trainer = trainer_env_options(phase2.get("detector", "none")) if a.no_nan_fallback else {}
    env = envs.make(a.vehicle, ekf_kernel=a.ekf_kernel, **trainer, **phase2)
    st = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), a.envs))
    act = jnp.zeros((a.envs, env.action_size))
    if a.raw_mjx:
      from mujoco import mjx
      ticks = env.config.ticks_per_step
      phys = jax.vmap(lambda d: mjx.step(env.mjx_model, d))
      one = lambda d: jax.lax.fori_loop(0, ticks, lambda _, d: phys(d), d)   # noqa: E731
      args = (jax.jit(jax.vmap(env.physics_data))(st.pipeline_state),)   # a full mjx.Data per env, as raw MJX has it
      what = f"raw MJX ({ticks} x mjx.step per env step)"
    else:
      one = lambda s: jax.vmap(env.step)(s, act)   # noqa: E731
      args, what = (st,), (f"Vmap(env).step, phase {a.phase}, EKF {env._ekf_kernel}, "
                           f"{'the trainer env' if a.no_nan_fallback else 'nan_fallback=True'}")
    fn = jax.jit(lambda c: jax.lax.scan(lambda c, _: (one(c), None), c, None, length=a.steps)[0])
    label = f"{a.steps} env steps per call, {what}, {a.vehicle}, {a.envs} envs, {dev}"
    compiled = fn.lower(*args).compile()
    if a.hlo_out:
      with open(a.hlo_out, "w") as f:
        f.write(compiled.as_text())
    res = profile(compiled, args, label, a.top, runs=2, show=a.show, gaps=a.gaps)
  else:
    from specguard_jax import ekf_lanes
    from specguard_jax.ppo import attacker, config, distributed, iteration, losses, runner
    base = runner.default_sizes("gpu")
    cfg = config.TrainConfig(vehicle=a.vehicle, num_envs=a.envs, unroll_length=a.unroll,
                             iters_per_call=a.iters_per_call, phase1_steps=base["phase1_steps"],
                             phase2_steps=base["phase2_steps"], num_devices=1, matmul_precision=a.matmul_precision,
                             network_dtype=a.network_dtype).with_env(ekf_kernel=a.ekf_kernel).validate()
    ph = iteration.make_phase(cfg, a.phase, distributed.make_mesh(1))
    k = jax.random.PRNGKey(0)
    sg = losses.with_hparams(ph.sg.init(k, cfg.n_obs), cfg.sg)
    aa = losses.with_hparams(ph.aa.init(k, attacker.N_OBS), cfg.aa)
    carry = ph.init(k, sg, aa)
    t = time.perf_counter()
    # without donation (the traced calls reuse the same carry)
    compiled = jax.jit(ph.run.__wrapped__ if hasattr(ph.run, "__wrapped__") else ph.run).lower(carry).compile()
    print(f"[gpu_profile] compiled in {time.perf_counter() - t:.0f} s", flush=True)
    if a.hlo_out:
      with open(a.hlo_out, "w") as f:
        f.write(compiled.as_text())
    label = (f"one training call, phase {a.phase}, {a.vehicle}, {a.envs} envs x {a.unroll} steps x "
             f"{a.iters_per_call} iteration(s), EKF {ekf_lanes.resolve_ekf_kernel(cfg.env.ekf_kernel)}, {dev}")
    res = profile(compiled, (carry,), label, a.top, runs=2, show=a.show, gaps=a.gaps)
  if a.json:
    json.dump(dict(res, device=dev, args=vars(a), date=time.strftime("%F")), open(a.json, "w"), indent=1)


if __name__ == "__main__":
  main()
