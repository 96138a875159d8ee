"""The host side of a training run: phases, logging, checkpoints, resume, export. The device does everything else.

run_dir layout:
  config.json          the TrainConfig
  metrics.jsonl        one line per iteration (phase, env steps, returns, SVR, RSR, collision rate, SPS, losses)
  tb/                  TensorBoard events (tensorboardX)
  checkpoints/<n>/     Orbax checkpoints of the whole Carry (both agents' params + Adam states + normalisers, env
                       states, rng, iteration) + host state (phase, calls, convergence history)
  policy.msgpack, policy_config.json, policy.onnx   the trained SpecGuard policy (specguard_jax.export)
  summary.json         final figures
Resume (`train(..., resume=True)`) restores the newest checkpoint and continues; with the same config the result is
bit-identical to an uninterrupted run (on CPU; tests/test_train.py).
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import time

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from envs import observation as obs_lib
from specguard_jax import export
from specguard_jax.ekf_lanes import resolve_ekf_kernel
from specguard_jax.ppo import ahead as ahead_lib
from specguard_jax.ppo import attacker as attacker_lib
from specguard_jax.ppo import distributed, losses
from specguard_jax.ppo import iteration as it
from specguard_jax.ppo.config import TRAIN_ENV, TrainConfig, load_config_file
from specguard_jax.types import SENSOR_NAMES

RATE_KEYS = ("complete", "collision", "crash", "stall", "nan", "fence_breach", "violated", "critical")
COMPILE_NOTE = "(first run takes a while; cached afterwards)"   # the persistent cache: specguard_jax.compile_cache


def derived(m: dict) -> dict:
  """Per-iteration rates from the summed counts of ppo.iteration (NaN where no episode finished)."""
  eps = m["episodes"]
  f = lambda a, b: float(a / b) if b > 0 else float("nan")
  out = {f"{k}_rate": f(m[k], eps) for k in RATE_KEYS}
  out["svr"] = out.pop("violated_rate")
  out["rsr"] = f(m["attacked_complete"], m["attacked"])
  out["svr_attacked"] = f(m["attacked_violated"], m["attacked"])
  out["return"] = f(m["return_sum"], eps)
  out["return_aa"] = f(m["return_aa_sum"], eps)
  if "aa_launches" in m:   # the attack agent's choices (phase 2): launches per episode, mean onset and duration (s),
    n = m["aa_launches"]   # and the share of its attacks that spoofed each sensor
    out["aa_launch_rate"] = f(n, eps)
    out["aa_onset_mean"] = f(m["aa_onset_sum"], n)
    out["aa_duration_mean"] = f(m["aa_attack_s"], n)
    out.update({f"{k}_share": f(m[k], n) for k in m if k.startswith("aa_") and k[3:] in SENSOR_NAMES})
  return out


class _Logger:
  def __init__(self, run_dir: str):
    self.f = open(os.path.join(run_dir, "metrics.jsonl"), "a")
    try:
      from tensorboardX import SummaryWriter
      self.tb = SummaryWriter(os.path.join(run_dir, "tb"))
    except Exception as e:  # noqa: BLE001 - TensorBoard is optional at run time
      print(f"[train] TensorBoard logging off ({type(e).__name__}: {e})", file=sys.stderr)
      self.tb = None

  def log(self, rec: dict):
    self.f.write(json.dumps(rec) + "\n")
    if self.tb is not None:
      for k, v in rec.items():
        if isinstance(v, (int, float)) and k != "env_steps" and math.isfinite(v):
          self.tb.add_scalar(k, v, rec["env_steps"])

  def close(self):
    self.f.close()
    if self.tb is not None:
      self.tb.close()


def _num(v: float, spec: str) -> str:
  """v formatted by spec (e.g. "5.3f"); "-" at the same width while the metric is undefined (NaN: no episode ended)."""
  return format(v, spec) if math.isfinite(v) else "-".rjust(int(spec.split(".")[0]))


class _Progress:
  """One-line progress: phase, steps, ETA, SPS, SVR, RSR (carriage return on a terminal, a line every 10 s else)."""

  def __init__(self, enabled: bool):
    self.enabled = enabled
    self.tty = sys.stderr.isatty()
    self.last = 0.0

  def show(self, phase, steps, total, sps, svr, rsr, ret, force=False):
    if not self.enabled:
      return
    now = time.time()
    if not self.tty and not force and now - self.last < 10.0:
      return
    self.last = now
    eta = (total - steps) / sps if sps > 0 else float("nan")
    eta_s = time.strftime("%H:%M:%S", time.gmtime(eta)) if math.isfinite(eta) else "--:--:--"
    frac = steps / max(total, 1)
    bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
    line = (f"phase {phase} [{bar}] {steps / 1e6:7.2f}/{total / 1e6:.2f}M steps  ETA {eta_s}  "
            f"{sps / 1e3:8.1f}k sps  SVR {_num(svr, '5.3f')}  RSR {_num(rsr, '5.3f')}  return {_num(ret, '8.2f')}")
    print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

  def compiling(self, what: str) -> None:
    """A line before a program compiles (the first call of a phase, the held-out evaluation): the wait that follows
    is the compile, not a hang."""
    if self.enabled:
      print(f"compiling {what} {COMPILE_NOTE}", file=sys.stderr, flush=True)


def converged(history, window: int, eps: float) -> bool:
  """Paper Algorithm 2's stop rule: the mean return of both agents changes by less than eps per iteration, relative
  to its size: |mean(last window) - mean(window before)| / window < eps x max(|mean(window before)|, 1), for both
  history columns (SpecGuard's and the attack agent's returns). eps <= 0: never."""
  if eps <= 0 or len(history) < 2 * window:
    return False
  h = np.asarray(history[-2 * window:], np.float64)
  before, last = np.nanmean(h[:window], 0), np.nanmean(h[window:], 0)
  d = np.abs(last - before) / window
  return bool(np.all(d < eps * np.maximum(np.abs(before), 1.0)))


def _checkpointer(run_dir):
  import orbax.checkpoint as ocp
  from specguard_jax import third_party
  third_party.quiet_checkpoint_logging()
  path = os.path.abspath(os.path.join(run_dir, "checkpoints"))
  return ocp.CheckpointManager(path, options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True))


def _pack(carry) -> dict:
  """Carry leaves by flat index (Orbax cannot store zero-size arrays such as an empty MJX `act`: they are left out
  and rebuilt from the abstract carry on restore)."""
  return {str(i): x for i, x in enumerate(jax.tree.leaves(carry)) if x.size}


def abstract_carry(phase, key, sg_state, aa_state):
  """The phase's carry as ShapeDtypeStructs with their shardings (env groups split over the mesh, the rest
  replicated): the target Orbax restores a checkpoint onto."""
  shapes = jax.eval_shape(phase.init, key, sg_state, aa_state)
  data, rep = distributed.data_sharding(phase.mesh), distributed.replicated(phase.mesh)
  split = {"env_state", "ep_return", "ep_return_aa"}
  return type(shapes)(**{f.name: jax.tree.map(
      lambda x, sh=(data if f.name in split else rep): jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh),
      getattr(shapes, f.name)) for f in dataclasses.fields(shapes)})


def _unpack(abstract, packed: dict):
  leaves, tree = jax.tree.flatten(abstract)
  out = [packed[str(i)] if str(i) in packed else _zero_size(a) for i, a in enumerate(leaves)]
  return jax.tree.unflatten(tree, out)


def _zero_size(a):
  """A zero-size carry leaf (not stored by Orbax) rebuilt with the abstract leaf's sharding: a leaf placed otherwise
  would make the phase's compiled call miss its cache and compile again on the restored carry. Built per shard, so
  a sharding spanning several processes' devices works too."""
  z = np.zeros(a.shape, a.dtype)
  sharding = getattr(a, "sharding", None)
  return jnp.asarray(z) if sharding is None else jax.make_array_from_callback(a.shape, sharding, lambda i: z[i])


def _save(mgr, carry, host: dict):
  import orbax.checkpoint as ocp
  host["saves"] = host.get("saves", 0) + 1
  step = host["saves"]
  mgr.save(step, args=ocp.args.Composite(carry=ocp.args.StandardSave(_pack(carry)), host=ocp.args.JsonSave(host)),
           force=True)
  mgr.wait_until_finished()


def _restore_host(mgr):
  import orbax.checkpoint as ocp
  step = mgr.latest_step()
  if step is None:
    return None, None
  try:
    return step, mgr.restore(step, args=ocp.args.Composite(host=ocp.args.JsonRestore()))["host"]
  except Exception as e:  # noqa: BLE001 - any Orbax/IO failure is a bad checkpoint to the user
    raise ValueError(f"cannot restore checkpoint {mgr.directory}/{step}: {type(e).__name__}: "
                     f"{str(e).splitlines()[0] if str(e) else ''}") from None


def _restore_carry(mgr, step, abstract):
  import orbax.checkpoint as ocp
  try:
    packed = mgr.restore(step, args=ocp.args.Composite(carry=ocp.args.StandardRestore(_pack(abstract))))["carry"]
  except Exception as e:  # noqa: BLE001
    raise ValueError(f"cannot restore checkpoint {mgr.directory}/{step} (corrupt, or written by another config): "
                     f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
  return _unpack(abstract, packed)


def load_run_config(run_dir: str) -> TrainConfig:
  path = os.path.join(run_dir, "config.json")
  if not os.path.exists(path):
    raise ValueError(f"cannot resume: {path} not found (not a run directory)")
  try:
    return load_config_file(path, run=True).validate()
  except ValueError as e:
    raise ValueError(f"cannot resume: {e}" if path in str(e) else f"cannot resume: {path}: {e}") from None


def train(cfg: TrainConfig, run_dir: str, *, resume: bool = False, progress: bool = True,
          stop_after_calls: int | None = None, export: bool = True, log=print, num_devices: int | None = None,
          compile_ahead: bool | None = None) -> dict:
  """Train SpecGuard (phase 1 then phase 2) into run_dir; returns the summary dict (also written to summary.json).

  resume: continue from run_dir's newest checkpoint (its config.json wins over `cfg`; num_devices may override its
  device count: the checkpoint restores onto any device count dividing its env_groups).  stop_after_calls: stop
  (after checkpointing) once this many compiled calls ran in this process: a deterministic stand-in for a kill.
  compile_ahead: compile the later phases and the held-out evaluation on background threads while the current
  phase compiles and trains (ppo/ahead.py); None: on unless the backend is the CPU (where the cores are few and
  the programs compile in seconds to minutes either way).
  """
  main = distributed.is_main()
  if resume:
    cfg = load_run_config(run_dir)
  else:
    cfg.validate()
  if num_devices is not None:
    cfg = dataclasses.replace(cfg, num_devices=num_devices)
  mesh = distributed.make_mesh(cfg.num_devices)
  # The env-group count and the EKF kernel fix the program (and the checkpoint's shapes: the kernel's P layout):
  # resolve them once and keep them in config.json, so a resume on another device count (dividing the groups)
  # continues the same run, and a resume where the kernel cannot run is a one-line error.
  cfg = dataclasses.replace(cfg, env_groups=distributed.groups_for(cfg.num_envs, cfg.env_groups, mesh)).with_env(
      ekf_kernel=resolve_ekf_kernel(cfg.env.ekf_kernel))
  os.makedirs(run_dir, exist_ok=True)   # after every check of the config and the devices: a refused run writes nothing
  if not resume and main:
    with open(os.path.join(run_dir, "config.json"), "w") as f:
      json.dump(cfg.to_dict(), f, indent=1)
  if not main:
    log = lambda *a, **k: None  # noqa: E731 - only process 0 talks
  mgr = _checkpointer(run_dir)
  logger = _Logger(run_dir) if main else None
  bar = _Progress(progress and main)
  phases = [p for p, n in ((1, cfg.phase1_steps), (2, cfg.phase2_steps)) if n > 0]
  key = jax.random.PRNGKey(cfg.seed)
  k_sg, k_aa, k_phase = jax.random.split(key, 3)

  host = {"phase_index": 0, "calls": 0, "env_steps": 0, "history": [], "wall_s": 0.0, "compile_s": {},
          "converged": False, "done": False}
  ckpt_step, saved_host = _restore_host(mgr) if resume else (None, None)
  if resume and saved_host is None:
    log(f"[train] no checkpoint in {run_dir}; starting from scratch")
  if saved_host is not None:
    host.update(saved_host)

  if compile_ahead is None:
    compile_ahead = jax.default_backend() != "cpu"
  ahead = ahead_lib.CompileAhead()
  if compile_ahead and not host["done"]:
    _compile_ahead(ahead, cfg, mesh, phases, host["phase_index"], (k_sg, k_aa, k_phase), main)

  stop = {"flag": False}

  def _on_signal(signum, _frame):
    stop["flag"] = True
    log(f"\n[train] signal {signum}: checkpointing after the current call, then stopping")

  old_handlers = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
  calls_here = 0
  summary_phase = {}
  sg_state = aa_state = None
  try:
    while host["phase_index"] < len(phases) and not host["done"]:
      number = phases[host["phase_index"]]
      phase = it.make_phase(cfg, number, mesh)
      if sg_state is None:
        sg_state = losses.with_hparams(phase.sg.init(k_sg, cfg.n_obs), cfg.sg)
        aa_state = losses.with_hparams(phase.aa.init(k_aa, attacker_lib.N_OBS), cfg.aa)
      sg_state, aa_state, k_init = distributed.replicate((sg_state, aa_state, jax.random.fold_in(k_phase, number)),
                                                         mesh)
      if ckpt_step is not None and saved_host is not None and saved_host.get("carry_phase", number) != number:
        # The newest checkpoint closed the previous phase (the run died before this phase's first save): its agents
        # start this phase exactly as they do in an uninterrupted run.
        before = it.make_phase(cfg, saved_host["carry_phase"], mesh)
        prev = _restore_carry(mgr, ckpt_step, abstract_carry(before, k_init, sg_state, aa_state))
        sg_state, aa_state = prev.sg, prev.aa
        del prev
        ckpt_step = None
        log(f"[train] resumed at the start of phase {number} from {run_dir}")
      if not compile_ahead or f"phase{number}" in ahead.pending():
        bar.compiling(f"phase {number}")
      waited = ahead.wait(f"phase{number}")   # a phase compiling ahead (init and run): wait for it
      fresh = phase.init(k_init, sg_state, aa_state)
      if ckpt_step is not None and saved_host is not None:
        carry = _restore_carry(mgr, ckpt_step, fresh)
        del fresh
        ckpt_step = None
        log(f"[train] resumed phase {number} at iteration {int(carry.iteration)} from {run_dir}")
      else:
        carry = fresh
      total_calls = -(-phase.iterations // cfg.iters_per_call)
      phase_total = total_calls * cfg.iters_per_call * cfg.steps_per_iter
      last_ckpt = time.time()
      while int(carry.iteration) < total_calls * cfg.iters_per_call:
        tc = time.time()
        carry, m = phase.run(carry)
        m = distributed.to_host(m)
        dt = time.time() - tc + waited   # a phase's first call: its compile, or the wait for its compile ahead
        waited = 0.0
        host["calls"] += 1
        calls_here += 1
        host["wall_s"] += dt
        first = str(number) not in host["compile_s"]
        if first:
          host["compile_s"][str(number)] = dt
        steps_call = cfg.iters_per_call * cfg.steps_per_iter
        sps = steps_call / dt
        it_end = int(carry.iteration)
        for i in range(cfg.iters_per_call):
          mi = {k: float(np.asarray(v)[i]) for k, v in m.items()}
          d = derived(mi)
          host["env_steps"] += cfg.steps_per_iter
          rec = {"phase": number, "iteration": it_end - cfg.iters_per_call + i + 1, "env_steps": host["env_steps"],
                 "sps": sps, "first_call": first, **d,
                 **{k: v for k, v in mi.items() if k.startswith(("sg_", "aa_")) or k in ("turn", "episodes")}}
          if logger is not None:
            logger.log(rec)
          if number == 2:
            host["history"].append([d["return"], d["return_aa"]])
            host["history"] = host["history"][-2 * cfg.converge_window:]
        steps_phase = it_end * cfg.steps_per_iter
        last = derived({k: float(np.asarray(v)[-1]) for k, v in m.items()})
        bar.show(number, steps_phase, phase_total, sps, last["svr"], last["rsr"], last["return"])
        summary_phase[number] = last
        if number == 2 and converged(host["history"], cfg.converge_window, cfg.converge_eps):
          host["converged"] = True
          log(f"\n[train] phase 2 converged at iteration {it_end} "
              f"(|d return / d iter| < {cfg.converge_eps} x |return|)")
          break
        interrupted = stop["flag"] or (stop_after_calls is not None and calls_here >= stop_after_calls)
        # Every process must take the same decision (the save is collective): OR-ed over the processes.
        interrupted, save_now = distributed.any_process(interrupted,
                                                        time.time() - last_ckpt >= cfg.checkpoint_every_s)
        if interrupted or save_now:
          host["carry_phase"] = number   # the saved carry's phase (a resume restores onto that phase's layout)
          _save(mgr, carry, host)
          last_ckpt = time.time()
        if interrupted:
          log(f"\n[train] stopped after {host['calls']} calls; resume with: python train.py --resume {run_dir}")
          if ahead.pending():
            log(f"[train] the process exits once its background compiles end ({', '.join(ahead.pending())}); the "
                "checkpoint is written, so killing it now loses nothing")
          return {"interrupted": True, "run_dir": run_dir, "calls": host["calls"]}
      if bar.tty and progress:
        print(file=sys.stderr)
      sg_state, aa_state = carry.sg, carry.aa
      host["phase_index"] += 1
      host["carry_phase"] = number
      _save(mgr, carry, host)
    # ---- finished (or restored a finished run) ----
    if sg_state is None:  # resumed after the last phase: restore the final carry
      number = phases[-1]
      phase = it.make_phase(cfg, number, mesh)
      sg0 = phase.sg.init(k_sg, cfg.n_obs)
      aa0 = phase.aa.init(k_aa, attacker_lib.N_OBS)
      fresh = abstract_carry(phase, jax.random.fold_in(k_phase, number), sg0, aa0)
      carry = _restore_carry(mgr, mgr.latest_step(), fresh)
      sg_state, aa_state = carry.sg, carry.aa
    host["done"] = True
    sg_state = distributed.to_host(sg_state)   # export and held-out evaluation run on process 0's devices
    summary = {"run_dir": os.path.abspath(run_dir), "config": cfg.to_dict(), "env_steps": host["env_steps"],
               "train_wall_s": host["wall_s"], "compile_s": host["compile_s"], "converged": host["converged"],
               "final_train_metrics": {str(k): v for k, v in summary_phase.items()},
               "device": str(jax.devices()[0].device_kind), "backend": jax.default_backend(),
               "devices": mesh.size, "processes": jax.process_count(), "env_groups": cfg.env_groups,
               "xla_flags": os.environ.get("XLA_FLAGS", ""), "date": time.strftime("%Y-%m-%d")}
    if not main:
      distributed.barrier("specguard_train_end")   # wait for process 0's export and evaluation
      return summary
    ex = export_policy(cfg, run_dir, sg_state, onnx=export)   # the policy always: evaluate.py loads it
    if ex:
      summary["export"] = ex
    if cfg.eval_missions > 0:
      te = time.time()
      if not compile_ahead or "heldout" in ahead.pending():
        bar.compiling("the held-out evaluation")
      ahead.wait("heldout")
      summary["heldout"] = it.heldout(cfg, sg_state, cfg.eval_missions)
      summary["heldout_wall_s"] = time.time() - te
      log(f"[train] held-out ({cfg.eval_missions} missions per setting): " + ", ".join(
          f"{k} SVR {v['svr']:.3f} RSR {v['rsr']:.3f}" for k, v in summary["heldout"].items() if k[0] != "_"))
    with open(os.path.join(run_dir, "summary.json"), "w") as f:
      json.dump(summary, f, indent=1, default=float)
    distributed.barrier("specguard_train_end")
    return summary
  finally:
    for s, h in old_handlers.items():
      signal.signal(s, h)
    if logger is not None:
      logger.close()
    mgr.close()


def _compile_ahead(ahead, cfg, mesh, phases, start: int, keys, main: bool) -> None:
  """Start compiling the phases after phases[start] (init and run) and the held-out evaluation on background
  threads (ppo/ahead.py). Their inputs are abstract: each phase's agent states as they arrive there (replicated
  over the mesh, the shapes of a fresh agent's), the evaluation's policy parameters as numpy arrays."""
  k_sg, k_aa, k_phase = keys
  first = it.make_phase(cfg, phases[start], mesh)   # built here, not on a thread: make_phase is cached per config
  sg = jax.eval_shape(lambda: losses.with_hparams(first.sg.init(k_sg, cfg.n_obs), cfg.sg))
  aa = jax.eval_shape(lambda: losses.with_hparams(first.aa.init(k_aa, attacker_lib.N_OBS), cfg.aa))
  for number in phases[start + 1:]:
    phase = it.make_phase(cfg, number, mesh)
    args = ahead_lib.replicated_spec((jax.random.fold_in(k_phase, number), sg, aa), mesh)
    ahead.submit(f"phase{number}", ahead_lib.compile_phase, phase, *args)
  if main and cfg.eval_missions > 0:
    ahead.submit("heldout", it.precompile_heldout, cfg, sg, cfg.eval_missions)


def export_policy(cfg: TrainConfig, run_dir: str, sg_state, onnx: bool = True) -> dict:
  """Save the SpecGuard policy (msgpack + config: what evaluate.py loads) and, with onnx, its ONNX with normalisation
  folded in; returns the ONNX parity / latency ({} without it)."""
  policy = it.sg_policy(cfg)
  params = jax.device_get(sg_state.params["policy"])
  norm = {"mean": np.asarray(sg_state.normalizer.mean), "std": np.asarray(sg_state.normalizer.std)}
  layout = obs_lib.describe(cfg.env.obs_layout, cfg.env.proximity_sectors, cfg.env.obs_history)
  export.save_policy(run_dir, policy, params, norm, cfg.action_scales, cfg.obs_clip, obs_layout=layout)
  if not onnx:
    return {}
  # The JAX reference must use exact float32 matmuls (GPUs default to TF32, ~1e-3 off the ONNX Runtime CPU result).
  with jax.default_matmul_precision("float32"):
    res = export.export_onnx(os.path.join(run_dir, "policy.onnx"), policy, params, norm, cfg.action_scales,
                             clip=cfg.obs_clip,
                             metadata={"vehicle": cfg.vehicle, "variant": cfg.variant, "obs_layout": layout})
  return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in res.items()}


def default_sizes(backend: str) -> dict:
  """Env count, step budgets and the networks' compute dtype for the backend. GPU: tens of thousands of envs and
  bfloat16 hidden layers in training (quicker at the same held-out quality, BENCHMARKS.md). CPU: hundreds of envs
  and float32 (XLA:CPU has no fast bf16 matmuls). The EKF kernel is TrainConfig.env.ekf_kernel's "auto"
  (ekf_lanes.resolve_ekf_kernel)."""
  if backend == "gpu":
    return dict(num_envs=16384, unroll_length=32, phase1_steps=30_000_000, phase2_steps=60_000_000,
                iters_per_call=5, eval_missions=1000, network_dtype="bfloat16")
  return dict(num_envs=256, unroll_length=32, phase1_steps=1_000_000, phase2_steps=1_000_000, iters_per_call=4,
              eval_missions=16)



SWEEP_DATA_KEYS = ("seed",) + tuple(f"{a}.{h}" for a in ("sg", "aa") for h in losses.HPARAMS)
"""Sweep keys that are data in one vmapped program (train_sweep); any other key is structural (its own program)."""


def _member_states(phase, cfgs, number, k_keys):
  """Per-member (SG state, AA state, phase init key), stacked on a leading member axis."""
  out = []
  for c, (k_sg, k_aa, k_phase) in zip(cfgs, k_keys):
    out.append((losses.with_hparams(phase.sg.init(k_sg, c.n_obs), c.sg),
                losses.with_hparams(phase.aa.init(k_aa, attacker_lib.N_OBS), c.aa),
                jax.random.fold_in(k_phase, number)))
  return jax.tree.map(lambda *x: np.stack([np.asarray(v) for v in x]), *out)


def train_sweep(cfgs: list, names: list, out: str, *, progress: bool = True, export: bool = True,
                log=print, compile_ahead: bool | None = None, on_call=None) -> list:
  """Train sweep members that differ only in SWEEP_DATA_KEYS as ONE compiled program per phase: the carry gets a
  leading member axis (vmapped), sharded over the devices (the largest device count dividing the member count);
  each member's hyperparameters live in its optimizer state (losses.HPARAMS), its seed in its keys. Each member
  gets out/<name>/ (config.json, metrics.jsonl, summary.json, policy export, held-out evaluation if asked); no
  checkpoints (a sweep restarts from scratch) and no early convergence stop (members run the full budget).
  compile_ahead: as in `train` (phase 2 compiles while phase 1 compiles and trains). on_call: None or a function
  called after every host call as on_call(step, last_call, sg_state, metrics) with step the host call's index over
  both phases (0, 1, ...), last_call True on the run's final call, sg_state the members' SpecGuard states on the host
  (leading member axis) and metrics each member's latest iteration's `derived` dict; a True return stops the
  program there (the tuner's pruned members, ppo/tune.py): no later call or phase runs, and the summaries say
  "stopped_early". Returns one summary per member."""
  import math as _math
  base = it.program_config(cfgs[0])
  for c in cfgs:
    c.validate()
    if it.program_config(c) != base:
      raise ValueError("train_sweep members may differ only in " + ", ".join(SWEEP_DATA_KEYS))
  S = len(cfgs)
  avail = cfgs[0].num_devices or len(jax.devices())
  mesh = distributed.make_mesh(_math.gcd(S, avail))
  main = distributed.is_main()
  dirs = [os.path.join(out, n) for n in names]
  loggers = []
  for c, d in zip(cfgs, dirs):
    os.makedirs(d, exist_ok=True)
    if main:
      with open(os.path.join(d, "config.json"), "w") as f:
        json.dump(c.to_dict(), f, indent=1)
      loggers.append(_Logger(d))
  bar = _Progress(progress and main)
  keys = [jax.random.split(jax.random.PRNGKey(c.seed), 3) for c in cfgs]
  msh = distributed.data_sharding(mesh)
  put = lambda t: jax.tree.map(lambda x: jax.make_array_from_callback(x.shape, msh, lambda i: x[i]), t)  # noqa: E731
  phases = [p for p, n in ((1, base.phase1_steps), (2, base.phase2_steps)) if n > 0]
  env_steps, wall, compile_s, last, per_phase = 0, 0.0, {}, [{} for _ in cfgs], [{} for _ in cfgs]
  sg_state = aa_state = None
  stopped, step = False, 0
  last_phase = phases[-1]
  log(f"[train] sweep of {S} members as one program per phase on {mesh.size} device(s)")
  ahead = ahead_lib.CompileAhead()
  if compile_ahead is None:
    compile_ahead = jax.default_backend() != "cpu"
  if compile_ahead:
    for number in phases[1:]:   # each later phase's init and run, on the members' states as they arrive there
      phase = it.make_phase(base, number, mesh, members=S)
      spec = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=msh)  # noqa: E731
      sg0, aa0, kinit = jax.tree.map(spec, _member_states(phase, cfgs, number, keys))
      ahead.submit(f"phase{number}", ahead_lib.compile_phase, phase, kinit, sg0, aa0)
  try:
    for number in phases:
      phase = it.make_phase(base, number, mesh, members=S)
      sg0, aa0, kinit = _member_states(phase, cfgs, number, keys)
      if sg_state is None:
        sg_state, aa_state = sg0, aa0
      if not compile_ahead or f"phase{number}" in ahead.pending():
        bar.compiling(f"phase {number}")
      waited = ahead.wait(f"phase{number}")
      carry = phase.init(*put((kinit, sg_state, aa_state)))
      calls = -(-phase.iterations // base.iters_per_call)
      total = calls * base.iters_per_call * base.steps_per_iter
      for call in range(calls):
        tc = time.time()
        carry, m = phase.run(carry)
        m = distributed.to_host(m)   # [S, K] (gathered where the members span processes)
        dt = time.time() - tc + waited
        waited = 0.0
        wall += dt
        compile_s.setdefault(str(number), dt)
        sps = S * base.iters_per_call * base.steps_per_iter / dt
        for i in range(base.iters_per_call):
          env_steps += base.steps_per_iter
          for s in range(S):
            mi = {k: float(np.asarray(v)[s, i]) for k, v in m.items()}
            d = derived(mi)
            last[s] = d
            per_phase[s][str(number)] = d
            if main:
              loggers[s].log({"phase": number, "iteration": call * base.iters_per_call + i + 1,
                              "env_steps": env_steps, "sps": sps / S, "first_call": call == 0, **d,
                              **{k: v for k, v in mi.items() if k.startswith(("sg_", "aa_")) or k == "turn"}})
        bar.show(number, (call + 1) * base.iters_per_call * base.steps_per_iter, total, sps,
                 float(np.nanmean([x["svr"] for x in last])), float(np.nanmean([x["rsr"] for x in last])),
                 float(np.nanmean([x["return"] for x in last])), force=call == calls - 1)
        if on_call is not None:
          final = number == last_phase and call == calls - 1
          stopped = bool(on_call(step, final, distributed.to_host(carry.sg), [dict(x) for x in last])) and not final
          step += 1
          if stopped:
            break
      if bar.tty and progress and main:
        print(file=sys.stderr)
      sg_state, aa_state = distributed.to_host((carry.sg, carry.aa))
      if stopped:
        log(f"[train] sweep stopped after {step} host call(s), as on_call asked")
        break
    summaries = []
    for s, (c, d) in enumerate(zip(cfgs, dirs)):
      sg_s = jax.tree.map(lambda x: x[s], sg_state)
      summ = {"run_dir": os.path.abspath(d), "config": c.to_dict(), "env_steps": env_steps, "train_wall_s": wall,
              "compile_s": compile_s, "sweep_members": S, "devices": mesh.size,
              "final_train_metrics": per_phase[s], "stopped_early": stopped,
              "backend": jax.default_backend(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
              "date": time.strftime("%Y-%m-%d")}
      ex = export_policy(c, d, sg_s, onnx=export) if main else {}
      if ex:
        summ["export"] = ex
      if main and c.eval_missions > 0:
        if s == 0:   # one program for every member
          bar.compiling("the held-out evaluation")
        summ["heldout"] = it.heldout(c, sg_s, c.eval_missions)
      if main:
        with open(os.path.join(d, "summary.json"), "w") as f:
          json.dump(summ, f, indent=1, default=float)
      summ["sg_state"] = sg_s
      summaries.append(summ)
    distributed.barrier("specguard_sweep_end")   # the other processes wait for process 0's exports
    return summaries
  finally:
    for lg in loggers:
      lg.close()
