"""Train a SpecGuard recovery policy: phase 1 (compliance, no attacks) then phase 2 (adversarial, vs the attack agent).

  python train.py                                  # default drone SpecGuard-RC, sized to the backend
  specguard-train ...                              # the same, as installed by pip
  python train.py --vehicle rover --variant pc --envs 8192 --steps 200000000 --out runs/rover_pc
  python train.py --resume runs/drone_rc           # continue an interrupted run from its last checkpoint
  python train.py --config my.json                 # TrainConfig fields as JSON (flags override it)
  python train.py --sweep seed=0,1,2 sg.lr=1e-4,3e-4 --steps 2000000   # many runs, one comparison table
  python train.py --set env.clearance=6 sg.lr=1e-4  # any config field, nested ones dotted (values as JSON)
  python train.py --vehicle rover --params rover.parm   # the vehicle's own autopilot parameters set the specs
  python train.py --tune 32 --tune-space space.json --tune-batch 8   # an Optuna study (pip install '.[tune]')
  python train.py --devices 2 --envs 32768                     # data-parallel over 2 local devices (default: all)
  python train.py --coordinator host0:1234 --num-processes 2 --process-id 0   # multi-host (run on every host)

Writes runs/<name>/ (config.json, metrics.jsonl, tb/, checkpoints/, policy.onnx, policy.msgpack, summary.json) and
prints where they are.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from specguard_jax.types import EKF_KERNELS, REWARDS, SENSOR_NAMES, TRAIN_DETECTORS, VARIANTS, VEHICLES

DETERMINISTIC_XLA_FLAG = "--xla_gpu_deterministic_ops=true"
TUNE_OBJECTIVES = ("svr", "rsr", "return", "svr+rsr")   # ppo/tune.py's OBJECTIVES (not imported: it needs JAX)


def request_deterministic_gpu_ops(environ=os.environ):
  """Adds XLA's deterministic-ops flag to environ's XLA_FLAGS (read once, when JAX starts its backend).

  Why: XLA's autotuner picks GPU kernels by timing them as it compiles, so two cold compiles of one run can round
  differently; this flag makes them agree (cold-compiled runs repeat bit for bit) at a cost in env steps/s
  (docs/PERFORMANCE.md). Raises ValueError when the backend has already started (the flag would silently do nothing)
  or when XLA_FLAGS already turns the option off."""
  flags = environ.get("XLA_FLAGS", "")
  if "--xla_gpu_deterministic_ops" in flags:
    if DETERMINISTIC_XLA_FLAG not in flags.split():
      raise ValueError(f"--deterministic-gpu conflicts with XLA_FLAGS={flags!r}")
    return
  from jax._src import xla_bridge
  if xla_bridge.backends_are_initialized():
    raise ValueError("--deterministic-gpu must come before JAX starts its backend "
                     f"(in-process callers: set XLA_FLAGS={DETERMINISTIC_XLA_FLAG} before using JAX)")
  environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_XLA_FLAG}".strip()


def _csv(s):
  return tuple(x for x in s.split(",") if x)


CONFIG_DEST = "config:"
"""Prefix of the argparse dest of a flag that sets a config key: dest 'config:env.worlds' sets env.worlds."""


class _Parser(argparse.ArgumentParser):
  """train.py's parser: a bad flag is one line on stderr (exit 2), without the usage block. run_flags: {dest: flag}
  of the flags that change what a run trains (refused with --resume, whose config.json fixes the run)."""

  def __init__(self, *args, **kw):
    super().__init__(*args, **kw)
    self.run_flags = {}

  def error(self, message):
    print(f"train.py: error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(2)


def _config_flag(ap, *names, key: str, **kw):
  """A flag that sets config key `key` (dotted for a nested field, e.g. 'env.worlds'); build_config applies every
  such flag given (default None: not given) through config.from_dict, the type checks of a JSON config."""
  if kw.get("action", "store") == "store" and "choices" not in kw and "metavar" not in kw:
    kw["metavar"] = names[0].lstrip("-").replace("-", "_").upper()
  if key != "num_devices":   # --devices may change on a resume (the checkpoint restores onto other device counts)
    ap.run_flags[CONFIG_DEST + key] = names[0]
  return ap.add_argument(*names, dest=CONFIG_DEST + key, default=None, **kw)


def parse_args(argv=None):
  return _parser().parse_args(argv)


def _parser() -> _Parser:
  ap = _Parser(description=__doc__.split("\n")[0], formatter_class=argparse.RawTextHelpFormatter)
  _config_flag(ap, "--vehicle", key="vehicle", choices=VEHICLES)
  _config_flag(ap, "--variant", key="variant", choices=VARIANTS,
               help="rc: reactive control (default); pc: proactive control")
  ap.add_argument("--steps", type=int, help="total env steps (split evenly between phase 1 and phase 2)")
  _config_flag(ap, "--phase1-steps", key="phase1_steps", type=int)
  _config_flag(ap, "--phase2-steps", key="phase2_steps", type=int)
  _config_flag(ap, "--envs", key="num_envs", type=int, help="parallel envs (default: 16384 on a GPU, 256 on the CPU)")
  _config_flag(ap, "--unroll", key="unroll_length", type=int, help="env steps per env per iteration")
  _config_flag(ap, "--iters-per-call", key="iters_per_call", type=int, help="training iterations per compiled call")
  _config_flag(ap, "--seed", key="seed", type=int)
  ap.add_argument("--out", help="run directory (default runs/<vehicle>_<variant>_s<seed>_<time>)")
  ap.add_argument("--resume", metavar="DIR", help="resume the run in DIR from its newest checkpoint")
  _config_flag(ap, "--world", key="env.worlds", type=_csv, metavar="WORLDS",
               help="comma-separated world presets to train in")
  _config_flag(ap, "--params", key="env.params_file", metavar="FILE",
               help="autopilot parameter file (PX4 .params or ArduPilot .parm): the spec table's parameters, the "
                    "missions' speed and acceptance radius, the home-centred fence "
                    "(specguard_jax.specs.vehicle_params)")
  _config_flag(ap, "--mission", key="env.mission_file", metavar="FILE",
               help="QGroundControl mission (.plan or QGC WPL 110) every episode flies, with its geofence and rally "
                    "points (default: generated missions)")
  _config_flag(ap, "--reward", key="env.reward", choices=REWARDS,
               help="compliance: the paper's sigmoids; capped: 1 while a spec holds, the sigmoid only where it is "
                    "violated (specguard_jax/rewards/reward.py); binary: 1/0 per spec; survival: 1 per step in "
                    "flight, no specs (the FTC baseline, specguard_jax/baselines/ftc.py)")
  _config_flag(ap, "--action", key="action", choices=("gaussian", "discrete"),
               help="continuous velocity setpoint or the paper's 6")
  _config_flag(ap, "--attitude", key="env.override_attitude", action="store_const", const=True,
               help="the policy also adds a residual to the attitude + thrust (acceleration) setpoint, scaled by "
                    "accels (m/s^2; drone, gaussian action; EnvConfig.override_attitude)")
  _config_flag(ap, "--no-reconstruction", key="env.reconstruction", action="store_const", const=False,
               help="ablation: no state reconstruction in phase 2")
  _config_flag(ap, "--detector", key="env.detector", choices=TRAIN_DETECTORS,
               help="the training detector (phase 2; mixed, the default: per episode the oracle with probability "
                    "env.oracle_share, else the residual detector)")
  _config_flag(ap, "--attack-sensors", key="attack_sensors", type=_csv,
               help=f"sensors the attack agent may spoof ({','.join(SENSOR_NAMES)})")
  _config_flag(ap, "--converge-eps", key="converge_eps", type=float,
               help="stop phase 2 when both average returns change less than this")
  _config_flag(ap, "--eval-missions", key="eval_missions", type=int,
               help="held-out missions per setting evaluated after training")
  ap.add_argument("--config", help="JSON file of TrainConfig fields")
  ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                  help="set any config field, a nested one dotted (env.clearance=6 sg.lr=1e-4 env.ekf_records=false);\n"
                       "values as JSON (else a string), checked like a --config file's; applied after the other flags")
  ap.add_argument("--sweep", nargs="+", metavar="KEY=V1,V2",
                  help="train every combination of these config values (e.g. seed=0,1 sg.lr=1e-4,3e-4)")
  ap.add_argument("--sequential-sweep", action="store_true",
                  help="run sweep members one after another (default: members differing only in seed / "
                       "sg|aa.{lr,ent_coef,clip_eps,vf_coef} run as one vmapped program spread over the devices)")
  ap.add_argument("--tune", type=int, metavar="TRIALS",
                  help="an Optuna study (pip install 'specguard-jax[tune]') until it holds TRIALS finished trials;\n"
                       "rerun the same command to resume it (specguard_jax/ppo/tune.py)")
  ap.add_argument("--tune-space", metavar="FILE",
                  help='JSON {config key: distribution}, e.g. {"sg.lr": {"type": "log_uniform", "low": 1e-5, '
                       '"high": 1e-3}};\ntypes: log_uniform, uniform, int, categorical')
  ap.add_argument("--tune-batch", type=int, default=4, metavar="M",
                  help="trials asked at once; those differing only in vmapped sweep keys train as one program "
                       "(default 4)")
  ap.add_argument("--tune-objective", default="svr", choices=tuple(TUNE_OBJECTIVES),
                  help="held-out SVR (minimised), RSR or training return (maximised), or svr+rsr (multi-objective, "
                       "no pruning)")
  ap.add_argument("--tune-pruner", default="median", choices=("median", "halving", "none"),
                  help="Optuna pruner fed the objective at every host call (default median)")
  ap.add_argument("--study", metavar="URL", help="Optuna storage (default sqlite:///OUT/study.db)")
  ap.add_argument("--study-name", default="specguard", help="the study's name in its storage (default specguard)")
  _config_flag(ap, "--ekf-kernel", key="env.ekf_kernel", choices=EKF_KERNELS,
               help="the EKF tick: lanes (one Mosaic GPU kernel, NVIDIA Hopper or newer), xla, or auto (default: "
                    "lanes where the GPU and jax support it, else xla)")
  _config_flag(ap, "--unroll-ticks", key="env.unroll_ticks", action="store_true",
               help="unroll the env step's GPS-free autopilot ticks (no tick loop): quicker env steps, "
                    "more compile per phase; for long runs")
  _config_flag(ap, "--matmul-precision", key="matmul_precision", choices=("default", "bf16"),
               help="the agents' network matmuls in training: default (f32; TF32 on NVIDIA GPUs) or bf16 inputs "
                    "with f32 accumulation (env, evaluation and ONNX export stay f32)")
  _config_flag(ap, "--network-dtype", key="network_dtype", choices=("float32", "bfloat16"),
               help="the agents' networks' compute dtype in training: float32 (the CPU's default) or bfloat16 "
                    "(the GPU's: matmuls, bias adds and tanh in bf16; f32 parameters, optimizer and losses; "
                    "evaluation and ONNX export stay f32)")
  _config_flag(ap, "--devices", key="num_devices", type=int,
               help="data-parallel devices (default 0: all of every process's)")
  _config_flag(ap, "--env-groups", key="env_groups", type=int,
               help="independent auto-reset env groups (default 0: one per device); fix it to get the same "
                    "result on any device count")
  ap.add_argument("--coordinator", metavar="ADDR:PORT", help="multi-host: process 0's address (jax.distributed)")
  ap.add_argument("--num-processes", type=int, help="multi-host: number of processes")
  ap.add_argument("--process-id", type=int, help="multi-host: this process's index")
  ap.add_argument("--coordinator-timeout", type=float, default=300.0, metavar="S",
                  help="multi-host: give up (exit 2) when the processes have not all joined after S seconds")
  ap.add_argument("--no-progress", action="store_true")
  ap.add_argument("--no-export", action="store_true",
                  help="skip the ONNX export (policy.msgpack and policy_config.json, which evaluate.py loads, are "
                       "still written)")
  ap.add_argument("--compile-ahead", action=argparse.BooleanOptionalAction, default=None,
                  help="compile phase 2 and the held-out evaluation on background threads while phase 1 compiles "
                       "and trains (default: on unless the backend is the CPU)")
  ap.add_argument("--deterministic-gpu", action="store_true",
                  help=f"XLA's deterministic GPU ops (XLA_FLAGS={DETERMINISTIC_XLA_FLAG}): a cold-compiled GPU run "
                       "repeats bit for bit (without it only a run reusing the compile cache's programs does), "
                       "at fewer env steps/s")
  ap.add_argument("--compile-cache", metavar="DIR|off",
                  help="persistent XLA compilation cache (default $SPECGUARD_COMPILE_CACHE or "
                       "~/.cache/specguard_jax/xla; off: none)")
  ap.run_flags.update(steps="--steps", config="--config", set="--set", sweep="--sweep", tune="--tune")
  return ap


def _json_or_str(v: str):
  """A --set / --sweep value: JSON (1e-4, false, [1, 2], "x"), else the string itself (urban_park)."""
  try:
    return json.loads(v)
  except json.JSONDecodeError:
    return v


def _set_items(items) -> dict:
  """--set KEY=VALUE items as {key: value} (values: _json_or_str)."""
  out = {}
  for item in items:
    k, sep, v = item.partition("=")
    if not sep or not k:
      raise ValueError(f"bad --set item {item!r}; expected KEY=VALUE (e.g. env.clearance=6)")
    out[k] = _json_or_str(v)
  return out


def build_config(a):
  """The run's TrainConfig: the backend's default sizes, then --config, then the flags (each `_config_flag` by its
  config key, --steps split between the phases), then --set; every layer type-checked by config.from_dict."""
  import jax

  from specguard_jax.ppo import config as C
  from specguard_jax.ppo.runner import default_sizes
  cfg = C.TrainConfig(**default_sizes(jax.default_backend()))
  if a.config:
    cfg = C.load_config_file(a.config, cfg)
  flags = {k[len(CONFIG_DEST):]: v for k, v in vars(a).items() if k.startswith(CONFIG_DEST) and v is not None}
  if a.steps is not None:
    flags.update(phase1_steps=a.steps // 2, phase2_steps=a.steps - a.steps // 2)
  cfg = C.from_dict(C.nested(flags), cfg)
  cfg = C.from_dict(C.nested(_set_items(a.set)), cfg)
  if "num_envs" in flags and cfg.num_envs < 1024 and jax.default_backend() == "gpu":
    print(f"[train] note: {cfg.num_envs} envs leave most of the GPU idle", file=sys.stderr)
  return cfg.validate()


def check_user_files(cfg) -> None:
  """The run's parameter and mission files (env.params_file, env.mission_file) load for its vehicle: a bad one is a
  one-line ValueError before anything is built. Their notices are left to the env, which loads them again."""
  import warnings

  from envs import mission_files
  from specguard_jax.specs import vehicle_params
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    if cfg.env.params_file:
      vehicle_params.load_vehicle_settings(cfg.env.params_file, cfg.vehicle)
    if cfg.env.mission_file:
      mission_files.load_plan(cfg.env.mission_file, cfg.vehicle, max_episode_s=cfg.env.max_episode_s,
                              max_waypoints=cfg.env.mission_max_waypoints)


def _sweep_members(cfg, items):
  import itertools

  from specguard_jax.ppo import config as C
  axes = []
  for item in items:
    if "=" not in item:
      raise ValueError(f"bad --sweep item {item!r}; expected KEY=V1,V2 (e.g. seed=0,1)")
    k, vals = item.split("=", 1)
    axes.append([(k, _json_or_str(v)) for v in vals.split(",")])
  members = []
  for combo in itertools.product(*axes):
    members.append((dict(combo), C.from_dict(C.nested(dict(combo)), cfg).validate()))
  return members


def _sweep(members, out, a):
  """Members grouped by compiled program (structural keys); each group of several runs as one vmapped program
  (runner.train_sweep) unless --sequential-sweep. Writes out/sweep.json and out/sweep.md; returns the rows."""
  from specguard_jax.ppo import distributed, iteration, runner
  groups = {}
  for point, mcfg in members:
    key = iteration.program_config(mcfg) if not a.sequential_sweep else len(groups)
    groups.setdefault(key, []).append((point, mcfg))
  rows = []
  for grp in groups.values():
    names = ["_".join(f"{k}{v}" for k, v in point.items()).replace("/", "-") for point, _ in grp]
    if len(grp) > 1:
      summaries = runner.train_sweep([c for _, c in grp], names, out, progress=not a.no_progress,
                                     export=not a.no_export, compile_ahead=a.compile_ahead)
    else:
      summaries = [runner.train(grp[0][1], os.path.join(out, names[0]), progress=not a.no_progress,
                                export=not a.no_export, compile_ahead=a.compile_ahead)]
    for (point, _), s in zip(grp, summaries):
      fm = s["final_train_metrics"].get("2") or s["final_train_metrics"].get("1", {})
      rows.append({**point, "svr": fm.get("svr"), "rsr": fm.get("rsr"), "return": fm.get("return"),
                   "env_steps": s["env_steps"], "train_wall_s": s["train_wall_s"],
                   "program_members": s.get("sweep_members", 1), "run_dir": s["run_dir"]})
  if not distributed.is_main():
    return rows
  keys = list(rows[0])
  fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
  table = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
  table += ["| " + " | ".join(fmt(r[k]) for k in keys) + " |" for r in rows]
  with open(os.path.join(out, "sweep.json"), "w") as f:
    json.dump(rows, f, indent=1)
  with open(os.path.join(out, "sweep.md"), "w") as f:
    f.write("\n".join(table) + "\n")
  print("\n".join(table))
  print(f"[train] sweep of {len(rows)} runs in {len(groups)} program(s): {os.path.abspath(out)}/sweep.md, sweep.json")
  return rows


def check_up_front(a, run_flags: dict) -> None:
  """Checks of the flags that need no JAX (one-line ValueError): --resume refuses the flags that would change the
  run (its config.json fixes it) and needs its directory writable; a new run's --out (or runs/) must be a directory
  it can write in; the coordinator address is HOST:PORT."""
  from specguard_jax.cli import preflight
  from specguard_jax.ppo import distributed
  if a.resume:
    given = [flag for dest, flag in run_flags.items() if getattr(a, dest) not in (None, [])]
    if a.out is not None and os.path.abspath(a.out) != os.path.abspath(a.resume):
      given.append("--out")
    if given:
      raise ValueError(f"--resume continues {a.resume} as its config.json says; {', '.join(given)} would change the "
                       "run: drop them, or start a new run (--out) with them")
    preflight.check_output_dir(a.resume, "--resume")
  else:
    preflight.check_output_dir(a.out or "runs", "--out")
  if a.coordinator is not None:
    distributed.parse_address(a.coordinator)
  if a.tune is not None:
    _check_tune_flags(a)


def _check_tune_flags(a) -> None:
  """--tune's flag checks (one-line ValueError): a space file, positive counts, no --sweep, one process, optuna."""
  if a.tune < 1 or a.tune_batch < 1:
    raise ValueError(f"--tune ({a.tune}) and --tune-batch ({a.tune_batch}) must be >= 1")
  if not a.tune_space:
    raise ValueError("--tune needs --tune-space FILE (a JSON {config key: distribution})")
  if a.sweep:
    raise ValueError("--tune and --sweep exclude each other (put the swept keys in the --tune-space file)")
  if a.coordinator is not None:
    raise ValueError("--tune runs in one process (its devices share each batch); drop --coordinator")
  try:
    import optuna  # noqa: F401
  except ImportError:
    raise ValueError("--tune needs optuna: pip install 'specguard-jax[tune]' (or pip install optuna)") from None


def _give_up(message: str) -> None:
  """distributed.initialize's give_up: the one-line error, then exit 2 at once (the main thread is inside jax)."""
  print(f"train.py: error: {message}", file=sys.stderr, flush=True)
  os._exit(2)


def main(argv=None):
  ap = _parser()
  a = ap.parse_args(argv)
  from specguard_jax import compile_cache
  from specguard_jax.ppo import distributed   # importing runner starts the backend: join the processes first
  try:
    check_up_front(a, ap.run_flags)
    if a.deterministic_gpu:
      request_deterministic_gpu_ops()
    distributed.initialize(a.coordinator, a.num_processes, a.process_id, timeout_s=a.coordinator_timeout,
                           log=lambda m: print(f"[train] {m}", flush=True), give_up=_give_up)
    compile_cache.enable(a.compile_cache)
    from specguard_jax.ppo import runner
    if a.resume:
      cfg = runner.load_run_config(a.resume)
      out = a.resume
    else:
      cfg = build_config(a)
      check_user_files(cfg)
      out = a.out or os.path.join("runs", f"{cfg.vehicle}_{cfg.variant}_s{cfg.seed}_{time.strftime('%Y%m%d-%H%M%S')}")
    if a.tune is not None:
      from specguard_jax.ppo import tune
      out = a.out or os.path.join("runs", f"tune_{a.study_name}")   # no time stamp: the same command resumes
      dims = tune.load_space(a.tune_space, cfg)
      spec = tune.StudySpec(trials=a.tune, batch=a.tune_batch, name=a.study_name, objective=a.tune_objective,
                            pruner=a.tune_pruner,
                            storage=a.study or f"sqlite:///{os.path.abspath(os.path.join(out, 'study.db'))}")
    if a.sweep:
      members = _sweep_members(cfg, a.sweep)
    else:
      members = None
  except ValueError as e:
    print(f"train.py: error: {e}", file=sys.stderr)
    return 2
  try:
    if a.tune is not None:
      tune.run_study(cfg, dims, spec, out, progress=not a.no_progress, export=not a.no_export,
                     compile_ahead=a.compile_ahead, log=lambda m: print(m, flush=True))
      return 0
    if members:
      _sweep(members, out, a)
      return 0
    devices = vars(a)[CONFIG_DEST + "num_devices"]
    s = runner.train(cfg, out, resume=bool(a.resume), progress=not a.no_progress, export=not a.no_export,
                     num_devices=devices if a.resume else None, compile_ahead=a.compile_ahead)
  except ValueError as e:
    print(f"\ntrain.py: error: {e}", file=sys.stderr)
    return 2
  if s.get("interrupted"):
    return 130
  if not distributed.is_main():
    return 0
  print(f"[train] done: {s['env_steps']:,} env steps in {s['train_wall_s']:.0f} s of training calls")
  print(f"[train] run directory: {s['run_dir']}")
  for name in ("policy.onnx", "summary.json", "metrics.jsonl", "checkpoints", "tb"):
    print(f"  {os.path.join(s['run_dir'], name)}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
