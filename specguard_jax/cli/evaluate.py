"""Evaluate controllers the way the SpecGuard paper does (Sec. 5.4 metrics, Sec. 6 tables and figures).

  python evaluate.py --run runs/default --out runs/default/eval              # main experiments, default controllers
  python evaluate.py --run runs/default --suite paper --out runs/paper_eval  # every experiment our code can run
  python evaluate.py --run DIR --controllers no_protection,specguard_rc --sensors gps,gyro --profiles overt
  specguard-evaluate ...                                                     # the same, as installed by pip

Every controller (specguard_jax.controllers: no_protection, specguard_rc/pc, delorean, ablations, the prior-work
baselines of specguard_jax.baselines) flies the same missions (plan, world, attack, sensor-noise seed) in every
setting; the no-protection runs are the "intended violation" twins and the attack-free ground truth of the mission
delay (specguard_jax.metrics). One batched jitted rollout per (env config, policy) and group of worlds.
Writes <out>/report.json, report.md, figures/*.png and records/*.npz (per-mission records). Bad flags or paths: one
line, exit 2.

--suite paper adds: multi-sensor GPS+gyroscope attacks; unseen worlds when --runs suburban=DIR (trained in suburban
worlds, flown in urban_high_rise) and/or urban=DIR (the reverse) are given; the rover when --runs rover=DIR is given;
the binary-reward ablation when --runs binary=DIR; SpecGuard-PC when --runs specguard_pc=DIR (or --run is a PC run);
SpecGuard trained without reconstruction when --runs specguard_no_recon=DIR (else the run's policy with
reconstruction switched off).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import subprocess
import sys
import time

from specguard_jax.types import VEHICLES

RUN_NAMES = ("specguard_rc", "specguard_pc", "binary", "specguard_no_recon", "suburban", "urban", "rover")
DEFAULT_CONTROLLERS = ("no_protection", "specguard_rc", "specguard_pc", "delorean", "specguard_no_recon")
UNSEEN = {"suburban": ("suburban_to_urban", ("urban_high_rise",)),
          "urban": ("urban_to_suburban", ("suburban_residential",))}


class _Parser(argparse.ArgumentParser):
  def error(self, message):
    print(f"evaluate.py: error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(2)


def _parser() -> argparse.ArgumentParser:
  p = _Parser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--run", help="train.py run dir of the SpecGuard policy under evaluation")
  p.add_argument("--runs", nargs="*", default=[], metavar="NAME=DIR",
                 help=f"extra runs by role: {', '.join(RUN_NAMES)}")
  p.add_argument("--out", help="output dir (default <run>/eval, or runs/eval)")
  p.add_argument("--missions", type=int, help="missions per setting (default: GPU 1000, CPU 8)")
  p.add_argument("--controllers", help="comma-separated controller names (default: suite -> all available)")
  p.add_argument("--sensors", help="comma-separated attacked sensors; a+b = both at once (default: all)")
  p.add_argument("--profiles", default="overt,stealthy", help="overt,stealthy")
  p.add_argument("--worlds", help="comma-separated evaluation worlds (default: the run's training worlds)")
  p.add_argument("--vehicle", choices=VEHICLES, help="default: the run's vehicle, else drone")
  p.add_argument("--seed", type=int, default=10_000, help="mission/attack/noise seed (unseen by training)")
  p.add_argument("--suite", choices=("paper",), help="run every experiment of the paper our code can run")
  p.add_argument("--max-s", type=float, default=400.0, help="episode cap (s)")
  p.add_argument("--mission-s", help="LO,HI mission duration bounds (s) instead of the vehicle preset (small runs)")
  p.add_argument("--traj", type=int, default=2, help="missions per setting whose trajectories are recorded")
  p.add_argument("--train-budget", choices=("ci", "full"), help="baseline training size (default: GPU full, CPU ci)")
  p.add_argument("--no-figures", action="store_true")
  p.add_argument("--no-progress", action="store_true")
  p.add_argument("--compile-cache", metavar="DIR|off",
                 help="persistent XLA compilation cache (default $SPECGUARD_COMPILE_CACHE or "
                      "~/.cache/specguard_jax/xla; off: none)")
  return p


def _fail(msg: str) -> int:
  print(f"evaluate.py: error: {' '.join(str(msg).split())}", file=sys.stderr)
  return 2


def _csv(s):
  return tuple(x.strip() for x in s.split(",") if x.strip()) if s else ()


class Progress:
  """One-line progress bar on stderr: rollouts done / total, elapsed, ETA."""

  def __init__(self, total: int, enabled: bool = True):
    self.total, self.done, self.t0, self.enabled = max(total, 1), 0, time.time(), enabled

  def show(self, label: str) -> None:
    if not self.enabled:
      return
    el = time.time() - self.t0
    frac = self.done / self.total
    eta = f"{el / frac * (1 - frac):5.0f}s" if frac > 0 else "    ?"
    bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
    sys.stderr.write(f"\r[{bar}] {self.done}/{self.total} {el:6.0f}s eta {eta}  {label[:60]:<60}")
    sys.stderr.flush()

  def step(self, label: str) -> None:
    self.done += 1
    self.show(label)

  def close(self) -> None:
    if self.enabled:
      sys.stderr.write("\n")


def _git_commit() -> str | None:
  """The commit of the checkout this code runs from; None when installed from a wheel (no .git beside the package:
  site-packages may itself sit inside some other repository) or when git is missing."""
  root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))   # <root>/specguard_jax/cli
  if not os.path.exists(os.path.join(root, ".git")):     # a directory in a clone, a file in a worktree
    return None
  try:
    return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                          cwd=root).stdout.strip() or None
  except (OSError, subprocess.SubprocessError):
    return None


def plan(args) -> dict:
  """Validate flags and build the groups of rollouts: {group: {vehicle, worlds, settings, controllers: [names or
  (name, run dir)], ctx}}. Raises ValueError (one line) on bad input."""
  from specguard_jax import attacks as attacks_lib
  from specguard_jax import controllers as C
  from specguard_jax import evaluation as E
  from envs import worlds as worlds_lib

  runs = {}
  for item in args.runs:
    name, sep, d = item.partition("=")
    if not sep or not d:
      raise ValueError(f"--runs takes NAME=DIR, got {item!r}")
    if name not in RUN_NAMES:
      raise ValueError(f"unknown run role {name!r} in --runs; choose from {', '.join(RUN_NAMES)}")
    if not os.path.isfile(os.path.join(d, "config.json")):
      raise ValueError(f"--runs {name}: {d} is not a train.py run dir (no config.json)")
    runs[name] = d
  run_cfg = None
  if args.run:
    if not os.path.isdir(args.run):
      raise ValueError(f"--run {args.run}: no such directory")
    try:
      run_cfg = C.load_run_config(args.run)
    except C.NotAvailable as e:
      raise ValueError(f"--run: {e}") from None
  vehicle = args.vehicle or (run_cfg.vehicle if run_cfg else "drone")
  worlds = _csv(args.worlds) or (tuple(run_cfg.env.worlds) if run_cfg else C.DEFAULT_WORLDS)
  bad = [w for w in worlds if w not in worlds_lib.PRESETS]
  if bad:
    raise ValueError(f"unknown world(s) {', '.join(bad)}; choose from {', '.join(worlds_lib.PRESETS)}")
  profiles = _csv(args.profiles)
  bad = [p for p in profiles if p not in attacks_lib.PROFILES]
  if bad or not profiles:
    raise ValueError(f"unknown or no profile(s) {bad}; choose from {', '.join(attacks_lib.PROFILES)}")
  veh_sensors = tuple(s for s in attacks_lib.SENSOR_NAMES if not (vehicle == "rover" and s == "flow"))
  sensors = _csv(args.sensors) or veh_sensors
  for s in sensors:
    bad = [x for x in s.split("+") if x not in veh_sensors]
    if bad:
      raise ValueError(f"unknown sensor(s) {', '.join(bad)} for the {vehicle}; choose from {', '.join(veh_sensors)}")
  if args.missions is not None and args.missions < 1:
    raise ValueError("--missions must be >= 1")
  if args.max_s <= 0:
    raise ValueError("--max-s must be > 0")
  mission_s = None
  if args.mission_s:
    try:
      lo, hi = (float(x) for x in args.mission_s.split(","))
    except ValueError:
      raise ValueError(f"--mission-s takes LO,HI seconds, got {args.mission_s!r}") from None
    if not 0 < lo <= hi:
      raise ValueError(f"--mission-s needs 0 < LO <= HI, got {args.mission_s!r}")
    mission_s = (lo, hi)

  def settings_for(sens, multi=False):
    out = [E.setting(None)]
    out += [E.setting(tuple(s.split("+")), p) for s in sens for p in profiles]
    if multi and "gps" in veh_sensors and "gyro" in veh_sensors:
      out += [E.setting(("gps", "gyro"), p) for p in profiles if "gps+gyro" not in sens]
    return tuple(out)

  names = list(_csv(args.controllers)) or (C.available() if args.suite else list(DEFAULT_CONTROLLERS))
  known = C.available()
  bad = [c for c in names if c not in known]
  if bad:
    raise ValueError(f"unknown controller(s) {', '.join(bad)}; choose from {', '.join(known)}")
  if "no_protection" not in names:
    names.insert(0, "no_protection")   # the twins and ground truth of every metric
  budget = args.train_budget or ("full" if _backend() == "gpu" else "ci")
  out_dir = args.out or (os.path.join(args.run, "eval") if args.run else os.path.join("runs", "eval"))
  ctx = C.BuildContext(vehicle=vehicle, run_dir=args.run, cache_dir=os.path.join(out_dir, "baselines"),
                       seed=args.seed, worlds=worlds, train_budget=budget, runs=tuple(sorted(runs.items())))
  groups = {"main": {"vehicle": vehicle, "worlds": worlds, "settings": settings_for(sensors, multi=bool(args.suite)),
                     "controllers": names, "ctx": ctx}}
  skipped = {}
  if args.suite:
    single = tuple(s for s in sensors if "+" not in s)
    for role, (gname, gworlds) in UNSEEN.items():
      if role in runs:
        groups[gname] = {"vehicle": vehicle, "worlds": gworlds, "settings": settings_for(single),
                         "controllers": ["no_protection", ("specguard", runs[role])], "ctx": None}
      else:
        skipped[gname] = f"no run trained in {role} worlds given (--runs {role}=DIR)"
    if vehicle == "drone":
      if "rover" in runs:
        rs = tuple(s for s in single if s != "flow") or ("gps",)
        groups["rover"] = {"vehicle": "rover", "worlds": worlds, "settings": settings_for(rs),
                           "controllers": ["no_protection", ("specguard", runs["rover"]), "delorean"],
                           "ctx": C.BuildContext(vehicle="rover", run_dir=runs["rover"], seed=args.seed,
                                                 cache_dir=os.path.join(out_dir, "baselines_rover"),
                                                 worlds=worlds, train_budget=budget)}
      else:
        skipped["rover"] = "no rover run given (--runs rover=DIR)"
  return {"groups": groups, "skipped": skipped, "out": out_dir, "mission_s": mission_s, "runs": runs,
          "profiles": profiles}


MAX_MISSIONS = 1 << 20   # missions per setting: a larger count is a typo (1000 is the GPU default)


def check_up_front(args, p: dict) -> None:
  """Checks of the flags and of the plan `p` made before anything is built (one-line ValueError): numbers finite and
  in range, a list flag given empty, the output directory writable, every --runs directory a loadable run, and every
  controller asked for by name (--controllers) buildable as far as its cheap check tells (controllers.check); the
  default suite may still skip one, with the reason in the report."""
  from specguard_jax import controllers as C
  from specguard_jax.cli import preflight
  if not math.isfinite(args.max_s):
    raise ValueError(f"--max-s {args.max_s} must be a finite number of seconds > 0")
  if p["mission_s"] and not all(math.isfinite(x) for x in p["mission_s"]):
    raise ValueError(f"--mission-s {args.mission_s!r} must be finite seconds")
  if args.missions is not None and args.missions > MAX_MISSIONS:
    raise ValueError(f"--missions {args.missions} is not allowed; allowed: 1 to {MAX_MISSIONS}")
  if not 0 <= args.seed <= 2**32 - 1:
    raise ValueError(f"--seed {args.seed} is not allowed; allowed: 0 to {2**32 - 1}")
  if args.traj < 0:
    raise ValueError(f"--traj must be >= 0, got {args.traj}")
  for flag in ("controllers", "worlds", "sensors"):
    if getattr(args, flag) is not None and not _csv(getattr(args, flag)):
      raise ValueError(f"--{flag} {getattr(args, flag)!r} names none; leave the flag out for the default")
  preflight.check_output_dir(p["out"], "--out" if args.out else "--out (default)")
  for name, d in p["runs"].items():
    try:
      C.load_run_config(d)
    except C.NotAvailable as e:
      raise ValueError(f"--runs {name}: {e}") from None
  ctx = p["groups"]["main"]["ctx"]
  for name in _csv(args.controllers):
    try:
      C.check(name, ctx)
    except C.NotAvailable as e:
      raise ValueError(f"--controllers {name} cannot run: {e}") from None


def requested_not_run(args, not_run: dict) -> str | None:
  """The error when a controller asked for by name (--controllers, or a --runs run flown in its own group) could not
  be built after all (its builder raised), else None."""
  asked = set(_csv(args.controllers)) | {"specguard"}
  for key, why in not_run.items():
    if key.split("/", 1)[1] in asked:
      return f"controller {key} cannot run: {why}"
  return None


def _backend() -> str:
  import jax
  return jax.default_backend()


def main(argv=None) -> int:
  args = _parser().parse_args(argv)
  t_start = time.time()
  try:
    p = plan(args)
    check_up_front(args, p)
    from specguard_jax import compile_cache
    compile_cache.enable(args.compile_cache)
  except ValueError as e:
    return _fail(e)
  import jax

  from envs.missions import MissionConfig
  from specguard_jax import controllers as C
  from specguard_jax import evaluation as E
  from specguard_jax import report as R

  backend = jax.default_backend()
  missions = args.missions or (1000 if backend == "gpu" else 8)
  n_roll = sum(len(g["controllers"]) for g in p["groups"].values())
  bar = Progress(n_roll, enabled=not args.no_progress)
  results = {"groups": {}, "not_run": {}, "skipped_experiments": p["skipped"], "rollouts": []}
  records, trajs = {}, {}
  jobs = []   # (group name, controller, env): built first, compiled together, then flown one by one
  for gname, g in p["groups"].items():
    base = {"worlds": tuple(g["worlds"]), "max_episode_s": float(args.max_s)}
    if p["mission_s"]:
      mk = MissionConfig.drone if g["vehicle"] == "drone" else MissionConfig.rover
      base["mission"] = mk(min_duration_s=p["mission_s"][0], max_duration_s=p["mission_s"][1])
    results["groups"][gname] = {"vehicle": g["vehicle"], "worlds": list(g["worlds"]),
                                "settings": [s.name for s in g["settings"]], "controllers": {}}
    for c in g["controllers"]:
      label = c if isinstance(c, str) else c[0]
      bar.show(f"{gname}: building {label}")
      try:
        if isinstance(c, str):
          ctrl = C.build(c, g["ctx"])
        else:
          cfg = C.load_run_config(c[1])
          ctrl = C.specguard_from_run(f"specguard_{cfg.variant}", c[1])
          if cfg.vehicle != g["vehicle"]:
            raise C.NotAvailable(f"{c[1]} was trained for the {cfg.vehicle}")
      except C.NotAvailable as e:
        results["not_run"][f"{gname}/{label}"] = str(e)
        bar.step(f"{gname}: {label} not run")
        continue
      except Exception as e:  # noqa: BLE001  (a broken builder is reported, the other controllers still run)
        results["not_run"][f"{gname}/{label}"] = f"build failed: {type(e).__name__}: {' '.join(str(e).split())}"
        bar.step(f"{gname}: {label} not run")
        continue
      jobs.append((gname, ctrl, E.make_env(g["vehicle"], **base, **ctrl.overrides())))
  refused = requested_not_run(args, results["not_run"])
  if refused:
    bar.close()
    return _fail(refused)
  bar.show(f"compiling {len(jobs)} rollouts")
  compiled = E.precompile([{"env": env, "policy": ctrl.policy, "policy_params": ctrl.params,
                            "settings": p["groups"][gname]["settings"], "missions": missions, "max_s": args.max_s,
                            "n_traj": args.traj} for gname, ctrl, env in jobs])
  results["compile_wall_s"] = compiled["wall"]
  for i, (gname, ctrl, env) in enumerate(jobs):
    g, grp = p["groups"][gname], results["groups"][gname]
    bar.show(f"{gname}: {ctrl.name} ({len(g['settings'])} settings x {missions})")
    timing = {}
    rec, traj, steps = E.rollout(env, ctrl.policy, ctrl.params, g["settings"], missions=missions, seed=args.seed,
                                 max_s=args.max_s, n_traj=args.traj, timing=timing)
    timing["compile_s"] += compiled.get(i, 0.0)   # this job's own (overlapped) compile, 0 if shared
    records[(gname, ctrl.name)] = rec
    trajs[(gname, ctrl.name)] = traj
    grp["controllers"][ctrl.name] = {"description": ctrl.description,
                                     "env_overrides": {k: R.jsonable(v) for k, v in ctrl.env_overrides},
                                     "compile_s": timing["compile_s"], "run_s": timing["run_s"], "steps": steps}
    results["rollouts"].append({"group": gname, "controller": ctrl.name, "missions": int(len(rec["complete"])),
                                **timing})
    bar.step(f"{gname}: {ctrl.name} done")
    grp["env"] = {"dt": env.dt, "spec_names": list(env.spec_names),
                  "critical": [bool(x) for x in env.spec_table.critical]}
  for grp in results["groups"].values():
    grp.setdefault("env", {"dt": None, "spec_names": None})
  bar.close()
  wall = time.time() - t_start
  meta = {"command": "python evaluate.py " + " ".join(argv if argv is not None else sys.argv[1:]),
          "date": datetime.datetime.now().isoformat(timespec="seconds"), "backend": backend,
          "device": str(jax.devices()[0]), "git_commit": _git_commit(), "seed": args.seed,
          "missions_per_setting": missions, "max_s": args.max_s, "mission_s": p["mission_s"], "run": args.run,
          "runs": p["runs"], "suite": args.suite, "profiles": list(p["profiles"]),
          "simulator": "specguard-jax MJX simulator (not AirSim)"}
  report = R.build(results, records, meta)
  report["wall_s"] = time.time() - t_start
  report["meta"]["eval_wall_s"] = wall
  R.write(p["out"], report, records, trajs, figures=not args.no_figures)
  total = report["totals"]
  print(f"evaluated {total['missions']} missions ({total['rollouts']} rollouts) in {report['wall_s']:.1f} s "
        f"(compile {total['compile_s']:.1f} s, flying {total['run_s']:.1f} s); report: "
        f"{os.path.join(p['out'], 'report.md')}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
