"""Evaluate controllers the way the SpecGuard paper does (Sec. 5.4 metrics, Sec. 6 tables and figures).

  python evaluate.py --run runs/default --out runs/default/eval              # main experiments, default controllers
  python evaluate.py --run runs/default --suite paper --out runs/paper_eval  # every experiment our code can run
  python evaluate.py --run DIR --controllers no_protection,specguard_rc --sensors gps,gyro --profiles overt
  python evaluate.py --vehicle rover --mission my.plan --params rover.parm --controllers no_protection,fallback
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

--campaigns long,hazard,designed,multi adds attack campaigns (specguard_jax.evaluation.campaign_settings) to the
settings, named '<campaign>/<sensors>/<profile>'. The designed campaign's ramp rates come from --designed-rates, else
they are designed against the detector (calibration.stealthy.design_rates, a few CPU minutes) and saved to
<out>/designed_rates.json, which a later run with the same --out reuses.

--campaigns redteam (or --train-redteam) adds the red-team setting 'redteam/<sensors>/agent': each controller is
attacked by its own best-response attack agent (specguard_jax.ppo.redteam), loaded from <redteam-dir>/<controller>/
(default <out>/redteam), or trained there first against the frozen controller with --train-redteam (the same budget
for every controller: --redteam-budget ci (CPU minutes, default) | full (GPU), or --redteam-steps / --redteam-envs).
report.json's 'redteam' section logs each mission's chosen sensor, onset and duration; figures/redteam.png plots them.

--suite hard flies the campaigns benchmark: attack-free + every campaign (or --campaigns), on all worlds (or
--worlds), with no protection, DeLorean, the fallback and the baselines that are registered, and SpecGuard when --run
is given; report.md opens with SVR, critical-spec violations, RSR and MD per controller and campaign. More SpecGuard
runs fly beside the others under their role's name: --runs specguard_rc_s1=DIR specguard_rc_s2=DIR (e.g. seeds).

--merge DIR DIR ... --out OUT makes one report of evaluations run as parts (disjoint controllers, the same seed,
missions, worlds and settings, each with no protection): paired tests across every pair of controllers, as if one job
had flown them (specguard_jax.report_merge; parts that did not fly the same missions are refused).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import os
import re
import subprocess
import sys
import time
import warnings

from specguard_jax.types import RECON_MODES, VEHICLES

RUN_NAMES = ("specguard_rc", "specguard_pc", "binary", "capped", "specguard_no_recon", "suburban", "urban", "rover")
# More SpecGuard runs flown beside the others in the main group, under the role's name (e.g. specguard_rc_s1 for a
# second seed): specguard_rc_<tag> / specguard_pc_<tag>, tag of lowercase letters, digits and '_'.
TAGGED_RUN = re.compile(r"specguard_(rc|pc)_[a-z0-9_]+")
DEFAULT_CONTROLLERS = ("no_protection", "specguard_rc", "specguard_pc", "delorean", "specguard_no_recon")
# Registered controllers the hard suite leaves out (ablations that need their own training runs).
HARD_SKIP = ("specguard_no_recon", "specguard_binary", "specguard_capped")
# Controllers the hard suite flies under another name with extra EnvConfig overrides:
# (report name, registered controller, ((EnvConfig field, value), ...)); the registered one is then not flown itself.
HARD_VARIANTS = ()
UNSEEN = {"suburban": ("suburban_to_urban", ("urban_high_rise",)),
          "urban": ("urban_to_suburban", ("suburban_residential",))}


class _Parser(argparse.ArgumentParser):
  def error(self, message):
    print(f"evaluate.py: error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(2)


def parse_args(argv=None) -> argparse.Namespace:
  """evaluate.py's flags (argv None: sys.argv); a bad flag exits 2 with one line."""
  return _parser().parse_args(argv)


def _parser() -> argparse.ArgumentParser:
  p = _Parser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--run", help="train.py run dir of the SpecGuard policy under evaluation")
  p.add_argument("--runs", nargs="*", default=[], metavar="NAME=DIR",
                 help=f"extra runs by role: {', '.join(RUN_NAMES)}; or specguard_rc_<tag> / specguard_pc_<tag> "
                      "(e.g. specguard_rc_s1=runs/rc_s1: more seeds, flown beside the others under that name)")
  p.add_argument("--out", help="output dir (default <run>/eval, or runs/eval)")
  p.add_argument("--missions", type=int, help="missions per setting (default: GPU 1000, CPU 8)")
  p.add_argument("--controllers", help="comma-separated controller names (default: suite -> all available)")
  p.add_argument("--sensors", help="comma-separated attacked sensors; a+b = both at once (default: all)")
  p.add_argument("--profiles", default="overt,stealthy", help="overt,stealthy")
  p.add_argument("--worlds", help="comma-separated evaluation worlds (default: the run's training worlds)")
  p.add_argument("--vehicle", choices=VEHICLES, help="default: the run's vehicle, else drone")
  p.add_argument("--seed", type=int, default=10_000, help="mission/attack/noise seed (unseen by training)")
  p.add_argument("--suite", choices=("paper", "hard"),
                 help="paper: every experiment of the paper our code can run; hard: the attack-campaign benchmark")
  p.add_argument("--campaigns", help="comma-separated attack campaigns: long,hazard,designed,multi,redteam (default: "
                                     "none; --suite hard: all but redteam)")
  p.add_argument("--train-redteam", action="store_true",
                 help="train the red-team attack agent of every controller that has none in --redteam-dir (adds the "
                      "redteam campaign)")
  p.add_argument("--redteam-dir", help="red-team agents, one subdirectory per controller (default <out>/redteam)")
  p.add_argument("--redteam-budget", choices=("ci", "full"), default="ci",
                 help="red-team training budget: ci (CPU minutes, default) or full (GPU-sized)")
  p.add_argument("--redteam-steps", type=int, help="red-team training env steps (overrides the budget's)")
  p.add_argument("--redteam-envs", type=int, help="red-team training parallel envs (overrides the budget's)")
  p.add_argument("--redteam-seed", type=int, default=0, help="red-team training seed (networks, missions, noise)")
  p.add_argument("--designed-rates", metavar="FILE|SENSOR=RATE,...",
                 help="designed campaign ramp rates (bias units / s): a designed_rates.json or gps=1.1,baro=0.25,...")
  p.add_argument("--hazard-lead", default="2,5", metavar="LO,HI", help="hazard campaign lead time range (s)")
  p.add_argument("--recon", choices=RECON_MODES,
                 help="state reconstruction mode of the controllers that reconstruct and do not fix one themselves "
                      "(delorean, specguard_*; EnvConfig.recon_mode): fused (default), paper, or oracle (the truth: a "
                      "bound)")
  p.add_argument("--max-s", type=float, default=400.0, help="episode cap (s)")
  p.add_argument("--mission-s", help="LO,HI mission duration bounds (s) instead of the vehicle preset (small runs)")
  p.add_argument("--mission", metavar="FILE",
                 help="fly this QGroundControl mission (.plan or QGC WPL 110) in every setting instead of generated "
                      "missions, with its geoFence and rally points (EnvConfig.mission_file)")
  p.add_argument("--params", metavar="FILE",
                 help="autopilot parameter file (PX4 .params or ArduPilot .parm): spec parameters, mission speed and "
                      "acceptance radius, home-centred fence (EnvConfig.params_file)")
  p.add_argument("--false-alarms", metavar="SENSORS",
                 help="comma-separated sensors: a 'false_alarm' group flies attack-free missions on which the alarm is "
                      "raised anyway (a zero-bias attack on the sensor, the oracle detector: the paper's forced false "
                      "alarms), every controller but no protection (default: gps with --suite paper, else none)")
  p.add_argument("--traj", type=int, default=2, help="missions per setting whose trajectories are recorded")
  p.add_argument("--train-budget", choices=("ci", "full"), help="baseline training size (default: GPU full, CPU ci)")
  p.add_argument("--no-figures", action="store_true")
  p.add_argument("--merge", nargs="+", metavar="DIR",
                 help="merge finished evaluations (report.json + records/) of the same missions into one report in "
                      "--out; no rollout is flown")
  p.add_argument("--no-progress", action="store_true",
                 help="no progress bar on stderr: one line per stage on stdout instead (for a job's log)")
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
  """One-line progress bar on stderr: rollouts done / total, elapsed, ETA. Disabled (--no-progress), one plain line
  per stage on stdout instead, for a job's log: which stage a long evaluation is in (building, training a
  baseline, compiling, flying) and since when."""

  def __init__(self, total: int, enabled: bool = True):
    self.total, self.done, self.t0, self.enabled = max(total, 1), 0, time.time(), enabled

  def show(self, label: str) -> None:
    el = time.time() - self.t0
    if not self.enabled:
      print(f"[{el:5.0f} s] {self.done}/{self.total} rollouts; {label}", flush=True)
      return
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


FORCED_ALARM = (("detector", "oracle"), ("detector_delay", 0.0))
"""Env overrides of the false-alarm group: the oracle raises the alarm over the zero-bias attack's window."""


def _forced_alarm(c):
  """A main-group controller entry as a variant with the oracle detector (the false-alarm group)."""
  if isinstance(c, str):
    return ("variant", c, c, FORCED_ALARM)
  if c[0] in ("variant", "run"):
    return c[:3] + (tuple(c[3]) + FORCED_ALARM,)
  return c


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
    if name not in RUN_NAMES and not TAGGED_RUN.fullmatch(name):
      raise ValueError(f"unknown run role {name!r} in --runs; choose from {', '.join(RUN_NAMES)}, or "
                       "specguard_rc_<tag> / specguard_pc_<tag>")
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
  default_worlds = worlds_lib.PRESET_NAMES if args.suite == "hard" else C.DEFAULT_WORLDS
  worlds = _csv(args.worlds) or (tuple(run_cfg.env.worlds) if run_cfg and args.suite != "hard" else default_worlds)
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

  campaigns = _csv(args.campaigns) or (E.CAMPAIGNS if args.suite == "hard" else ())
  if args.train_redteam and E.REDTEAM not in campaigns:
    campaigns = tuple(campaigns) + (E.REDTEAM,)
  bad = [c for c in campaigns if c not in E.CAMPAIGNS + (E.REDTEAM,)]
  if bad:
    raise ValueError(f"unknown campaign(s) {', '.join(bad)}; choose from {', '.join(E.CAMPAIGNS + (E.REDTEAM,))}")
  try:
    lead = tuple(float(x) for x in args.hazard_lead.split(","))
  except ValueError:
    raise ValueError(f"--hazard-lead takes LO,HI seconds, got {args.hazard_lead!r}") from None
  if len(lead) != 2 or not 0 <= lead[0] <= lead[1]:
    raise ValueError(f"--hazard-lead needs 0 <= LO <= HI, got {args.hazard_lead!r}")
  designed_rates = _parse_rates(args.designed_rates, veh_sensors) if args.designed_rates else None
  single = tuple(s for s in sensors if "+" not in s)
  camp_settings = E.campaign_settings(tuple(c for c in campaigns if c not in ("designed", E.REDTEAM)), single,
                                      profiles, hazard_lead_s=lead)
  redteam = None
  if E.REDTEAM in campaigns:
    redteam = redteam_plan(args, single or veh_sensors, out_dir=args.out or (
        os.path.join(args.run, "eval") if args.run else os.path.join("runs", "eval")))
    camp_settings = camp_settings + (E.redteam_setting(redteam["sensors"]),)

  def settings_for(sens, multi=False):
    out = [E.setting(None)]
    out += [E.setting(tuple(s.split("+")), p) for s in sens for p in profiles]
    if multi and "gps" in veh_sensors and "gyro" in veh_sensors:
      out += [E.setting(("gps", "gyro"), p) for p in profiles if "gps+gyro" not in sens]
    return tuple(out)

  variants = {}
  if args.suite == "hard" and not args.controllers:
    names = [c for c in C.available() if c not in HARD_SKIP
             and not (c.startswith("specguard") and not (args.run or runs))]
    for vname, base_name, over in HARD_VARIANTS:
      if base_name in names:
        variants[vname] = (base_name, tuple(over))
    names = [c for c in names if c not in {b for b, _ in variants.values()}] + list(variants)
  else:
    names = list(_csv(args.controllers)) or (C.available() if args.suite else list(DEFAULT_CONTROLLERS))
  known = C.available()
  bad = [c for c in names if c not in known and c not in variants]
  if bad:
    raise ValueError(f"unknown controller(s) {', '.join(bad)}; choose from {', '.join(known)}")
  if "no_protection" not in names:
    names.insert(0, "no_protection")   # the twins and ground truth of every metric
  budget = args.train_budget or ("full" if _backend() == "gpu" else "ci")
  out_dir = args.out or (os.path.join(args.run, "eval") if args.run else os.path.join("runs", "eval"))
  ctx = C.BuildContext(vehicle=vehicle, run_dir=args.run, cache_dir=os.path.join(out_dir, "baselines"),
                       seed=args.seed, worlds=worlds, train_budget=budget, runs=tuple(sorted(runs.items())))
  if args.suite == "hard":
    main_settings = (E.setting(None),) + camp_settings
  else:
    main_settings = settings_for(sensors, multi=bool(args.suite)) + camp_settings
  names = [("variant", c) + variants[c] if c in variants else c for c in names]
  names += [("run", role, d, ()) for role, d in runs.items() if TAGGED_RUN.fullmatch(role)]
  groups = {"main": {"vehicle": vehicle, "worlds": worlds, "settings": main_settings, "controllers": names,
                     "ctx": ctx, "designed": single if "designed" in campaigns else ()}}
  skipped = {}
  fa = _csv(args.false_alarms) if args.false_alarms is not None else (("gps",) if args.suite == "paper" else ())
  bad = [s for s in fa if s not in attacks_lib.SENSOR_NAMES]
  if bad:
    raise ValueError(f"--false-alarms: unknown sensor(s) {', '.join(bad)}; choose from "
                     f"{', '.join(attacks_lib.SENSOR_NAMES)}")
  if fa:
    groups["false_alarm"] = {"vehicle": vehicle, "worlds": worlds,
                             "settings": tuple(E.false_alarm_setting(s) for s in fa), "ctx": ctx,
                             "controllers": ["no_protection"] + [_forced_alarm(c) for c in names
                                                                 if c != "no_protection"]}
  if args.suite == "paper":
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
          "profiles": profiles, "campaigns": campaigns, "designed_rates": designed_rates, "hazard_lead_s": lead,
          "redteam": redteam}


def redteam_plan(args, sensors, out_dir: str) -> dict:
  """The red-team campaign's plan: {dir, train, config (ppo.redteam.RedteamConfig), sensors}. ValueError (one
  line) on bad flags."""
  from specguard_jax.ppo import redteam as RT
  for flag in ("redteam_steps", "redteam_envs"):
    v = getattr(args, flag)
    if v is not None and not 1 <= v <= 1 << 40:
      raise ValueError(f"--{flag.replace('_', '-')} {v} is not allowed; allowed: 1 to {1 << 40}")
  if not 0 <= args.redteam_seed <= 2**32 - 1:
    raise ValueError(f"--redteam-seed {args.redteam_seed} is not allowed; allowed: 0 to {2**32 - 1}")
  base = RT.BUDGETS[args.redteam_budget]
  over = {"sensors": tuple(sensors), "seed": args.redteam_seed}
  if args.redteam_steps:
    over["steps"] = args.redteam_steps
  if args.redteam_envs:
    over["num_envs"] = args.redteam_envs
  try:
    cfg = dataclasses.replace(base, **over)
  except ValueError as e:
    raise ValueError(f"red-team budget: {e}") from None
  return {"dir": args.redteam_dir or os.path.join(out_dir, "redteam"), "train": bool(args.train_redteam),
          "config": cfg, "sensors": tuple(sensors)}


def redteam_agent(p: dict, ctrl, env, log=None) -> dict:
  """The red-team agent of controller `ctrl` flying `env`: loaded from <redteam dir>/<name>/, else trained there
  (--train-redteam) and saved, then reloaded from disk. Returns {agent, params, dir, trained, train_s, history}.
  Raises controllers.NotAvailable when there is none and training was not asked for, or the saved one attacks
  other sensors or steps at another rate."""
  from specguard_jax import controllers as C
  from specguard_jax.ppo import redteam as RT
  rt = p["redteam"]
  d = os.path.join(rt["dir"], ctrl.name)
  trained, train_s, history = False, 0.0, []
  if not RT.exists(d):
    if not rt["train"]:
      raise C.NotAvailable(f"no red-team agent at {d} (train one with --train-redteam)")
    t0 = time.time()
    agent, params, history = RT.train(env, ctrl.policy, ctrl.params, rt["config"], progress=log)
    train_s = time.time() - t0
    RT.save(d, agent, params, rt["config"], history, extra={"controller": ctrl.name, "train_s": train_s})
    trained = True
  try:
    agent, params, meta = RT.load(d)
  except ValueError as e:
    raise C.NotAvailable(str(e)) from None
  if tuple(agent.attack.sensors) != tuple(rt["sensors"]) or abs(agent.dt - env.dt) > 1e-9:
    raise C.NotAvailable(f"the red-team agent at {d} attacks {','.join(agent.attack.sensors)} at a {agent.dt} s "
                         f"step; this evaluation: {','.join(rt['sensors'])} at {env.dt} s (another --redteam-dir)")
  return {"agent": agent, "params": params, "dir": d, "trained": trained,
          "train_s": train_s if trained else meta.get("train_s"), "history": meta.get("history", history),
          "config": meta.get("training")}


def _parse_rates(spec: str, sensors) -> dict:
  """--designed-rates: a JSON file ({sensor: rate} or design_rates' {sensor: {rate, feasible, ...}}) or
  SENSOR=RATE,... -> {sensor: rate > 0} (infeasible or non-finite entries dropped)."""
  import json
  import math
  if os.path.isfile(spec):
    try:
      with open(spec) as f:
        raw = json.load(f)
    except (OSError, ValueError) as e:
      raise ValueError(f"--designed-rates {spec}: {' '.join(str(e).split())}") from None
    raw = {k: ((v.get("rate") if v.get("feasible", True) else None) if isinstance(v, dict) else v)
           for k, v in raw.items()}
  else:
    raw = {}
    for item in _csv(spec):
      k, sep, v = item.partition("=")
      if not sep:
        raise ValueError(f"--designed-rates takes a file or SENSOR=RATE,..., got {item!r}")
      raw[k] = v
  out = {}
  for k, v in raw.items():
    if k not in sensors:
      raise ValueError(f"--designed-rates: unknown sensor {k!r}; choose from {', '.join(sensors)}")
    try:
      v = float(v) if v is not None else math.nan
    except (TypeError, ValueError):
      raise ValueError(f"--designed-rates: bad rate {v!r} for {k}") from None
    if math.isfinite(v) and v > 0:
      out[k] = v
  return out


def designed_settings(p: dict, group: dict, mission, max_s: float) -> tuple:
  """The designed campaign's settings of a group: rates from --designed-rates, else from <out>/designed_rates.json
  (a previous run's), designing the sensors it lacks against the group's detector (calibration.stealthy.design_rates)
  and saving them there. Sensors without a feasible rate get no designed setting."""
  import json

  from specguard_jax import attacks as attacks_lib
  from specguard_jax import evaluation as E
  sensors = group["designed"]
  rates = p["designed_rates"]
  if rates is None:
    path = os.path.join(p["out"], "designed_rates.json")
    saved = {}
    if os.path.isfile(path):
      with open(path) as f:
        saved = json.load(f)
    todo = [x for x in sensors if x not in saved]
    if todo:
      from specguard_jax.calibration import stealthy
      base = {"worlds": tuple(group["worlds"]), "max_episode_s": float(max_s), "detector": "residual"}
      if mission is not None:
        base["mission"] = mission
      design = stealthy.design_rates(E.make_env(group["vehicle"], **base), todo)
      saved.update({k: {kk: (vv if vv == vv else None) for kk, vv in v.items()} for k, v in design.items()})
      os.makedirs(p["out"], exist_ok=True)
      with open(path, "w") as f:
        json.dump(saved, f, indent=1)
    rates = _parse_rates(path, attacks_lib.SENSOR_NAMES)
  rates = {k: v for k, v in rates.items() if k in sensors}
  return E.campaign_settings(("designed",), sensors, designed_rates=rates)


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
  check_user_files(args, {g["vehicle"] for g in p["groups"].values()})
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
  rt = p.get("redteam")
  if rt and not rt["train"]:
    from specguard_jax.ppo import redteam as RT
    for c in p["groups"]["main"]["controllers"]:
      name = c if isinstance(c, str) else (c[1] if c[0] == "variant" else c[0])
      d = os.path.join(rt["dir"], name)
      if not RT.exists(d) and (name == "no_protection" or name in _csv(args.controllers)):
        raise ValueError(f"--campaigns redteam: no red-team agent at {d} for {name}; train the agents with "
                         f"--train-redteam (or give --redteam-dir)")
  for name in _csv(args.controllers):
    try:
      C.check(name, ctx)
    except C.NotAvailable as e:
      raise ValueError(f"--controllers {name} cannot run: {e}") from None


def check_user_files(args, vehicles) -> None:
  """--mission and --params load for every vehicle evaluated (one-line ValueError naming the file and the problem;
  their notices, e.g. a home taken from the first waypoint, are shown once here)."""
  import warnings

  from envs import mission_files
  from specguard_jax.specs import vehicle_params
  for flag, path in (("--mission", args.mission), ("--params", args.params)):
    if path is not None and not os.path.isfile(path):
      raise ValueError(f"{flag}: file not found: {path}")
  with warnings.catch_warnings():
    warnings.showwarning = lambda message, *_, **__: print(f"evaluate.py: note: {message}", file=sys.stderr)
    for vehicle in sorted(vehicles):
      if args.params:
        vehicle_params.load_vehicle_settings(args.params, vehicle)
      if args.mission:
        mission_files.load_plan(args.mission, vehicle, max_episode_s=args.max_s)


def requested_not_run(args, not_run: dict) -> str | None:
  """The error when a controller asked for by name (--controllers, or a --runs run flown in its own group) could not
  be built after all (its builder raised), else None."""
  roles = {x.partition("=")[0] for x in args.runs or ()}
  asked = set(_csv(args.controllers)) | {"specguard"} | {r for r in roles if TAGGED_RUN.fullmatch(r)}
  for key, why in not_run.items():
    if key.split("/", 1)[1] in asked:
      return f"controller {key} cannot run: {why}"
  return None


def baseline_build(ctx, name: str) -> dict:
  """A trained baseline's build record for report.json: its cache's meta (baselines.common.build_meta: held-out
  errors, monitor drift and threshold, a 10-point loss curve; FTC-RL's return curve), or the error reading it."""
  from specguard_jax import report as R
  from specguard_jax.baselines import common
  try:
    meta = common.build_meta(ctx, name)
  except Exception as e:  # noqa: BLE001 - a record it cannot read is reported, the evaluation goes on
    return {"error": f"{type(e).__name__}: {' '.join(str(e).split())[:200]}"}
  return R.jsonable(meta)


def _attacker(red) -> dict:
  """evaluation.rollout's attacker arguments of a job's red-team agent (none: {})."""
  return {"attacker": red["agent"], "attacker_params": red["params"]} if red else {}


def _backend() -> str:
  import jax
  return jax.default_backend()


MERGE_FLAGS = ("merge", "out", "no_figures", "no_progress", "compile_cache")
"""The flags --merge takes; the others choose what to fly, which the parts fixed."""


def merge_main(args, argv) -> int:
  """evaluate.py --merge DIR ... --out OUT: report.build over the parts' records (report_merge.merge)."""
  from specguard_jax import report as R
  from specguard_jax import report_merge as RM
  from specguard_jax.cli import preflight
  defaults = parse_args([])
  given = [k for k, v in vars(args).items() if k not in MERGE_FLAGS and v != getattr(defaults, k)]
  try:
    if given:
      raise ValueError(f"--merge takes only --out and --no-figures; the parts fixed --{given[0].replace('_', '-')}")
    if not args.out:
      raise ValueError("--merge needs --out, the merged report's directory")
    if os.path.abspath(args.out) in {os.path.abspath(d) for d in args.merge}:
      raise ValueError(f"--merge: --out {args.out} is one of the parts; write the merged report elsewhere")
    preflight.check_output_dir(args.out, "--out")
    results, records, meta = RM.merge([RM.load_part(d) for d in args.merge],
                                      "python evaluate.py " + " ".join(argv if argv is not None else sys.argv[1:]))
  except ValueError as e:
    return _fail(e)
  report = R.build(results, records, meta)
  report["wall_s"] = meta["eval_wall_s"]
  R.write(args.out, report, records, {}, figures=not args.no_figures)
  print(f"merged {len(args.merge)} evaluations: {report['totals']['missions']} missions, "
        f"{len(records)} rollouts; report: {os.path.join(args.out, 'report.md')}")
  return 0


def main(argv=None) -> int:
  args = parse_args(argv)
  if args.merge:
    return merge_main(args, argv)
  t_start = time.time()
  # the code and the moment this evaluation started (a long one may outlive its checkout's HEAD)
  commit, started = _git_commit(), datetime.datetime.now().isoformat(timespec="seconds")
  try:
    p = plan(args)
    check_up_front(args, p)
    from specguard_jax import compile_cache
    compile_cache.enable(args.compile_cache)
  except ValueError as e:
    return _fail(e)
  import jax

  from envs.missions import MissionConfig
  from specguard_jax import baselines as baselines_lib
  from specguard_jax import controllers as C
  from specguard_jax import evaluation as E
  from specguard_jax import report as R

  backend = jax.default_backend()
  missions = args.missions or (1000 if backend == "gpu" else 8)
  n_roll = sum(len(g["controllers"]) for g in p["groups"].values())
  bar = Progress(n_roll, enabled=not args.no_progress)
  results = {"groups": {}, "not_run": {}, "skipped_experiments": p["skipped"], "rollouts": []}
  records, trajs = {}, {}
  jobs = []   # (group name, controller, env, red team): all built first, then compiled and flown (below)
  builds = {}   # "group/controller": a flown trained baseline's build record (baseline_build)
  for gname, g in p["groups"].items():
    base = {"worlds": tuple(g["worlds"]), "max_episode_s": float(args.max_s), "mission_file": args.mission or "",
            "params_file": args.params or ""}
    if args.recon:
      base["recon_mode"] = args.recon
    if p["mission_s"]:
      mk = MissionConfig.drone if g["vehicle"] == "drone" else MissionConfig.rover
      base["mission"] = mk(min_duration_s=p["mission_s"][0], max_duration_s=p["mission_s"][1])
    if g.get("designed"):
      bar.show(f"{gname}: designing stealthy ramps")
      g["settings"] = tuple(g["settings"]) + designed_settings(p, g, base.get("mission"), args.max_s)
    results["groups"][gname] = {"vehicle": g["vehicle"], "worlds": list(g["worlds"]),
                                "settings": [s.name for s in g["settings"]], "controllers": {}}
    for c in g["controllers"]:
      label = c if isinstance(c, str) else (c[1] if c[0] in ("variant", "run") else c[0])
      bar.show(f"{gname}: building {label}")
      try:
        if isinstance(c, str):
          ctrl = C.build(c, g["ctx"])
        elif c[0] == "variant":   # ("variant", report name, registered controller, extra env overrides)
          ctrl = C.build(c[2], g["ctx"])
          over = dict(ctrl.env_overrides, **dict(c[3]))
          ctrl = dataclasses.replace(ctrl, name=c[1], env_overrides=tuple(over.items()),
                                     description=f"{ctrl.description} ({', '.join(f'{k}={v}' for k, v in c[3])})")
        elif c[0] == "run":   # ("run", role, dir, extra env overrides): a tagged --runs run, e.g. another seed
          cfg = C.load_run_config(c[2])
          if not c[1].startswith(f"specguard_{cfg.variant}_") or cfg.vehicle != g["vehicle"]:
            raise C.NotAvailable(f"--runs {c[1]}: {c[2]} is a {cfg.vehicle} SpecGuard-{cfg.variant.upper()} run")
          ctrl = C.specguard_from_run(c[1], c[2])
          if c[3]:
            ctrl = dataclasses.replace(ctrl, env_overrides=tuple(dict(ctrl.env_overrides, **dict(c[3])).items()))
        else:   # ("specguard", dir): the run of an unseen-world or rover group
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
      with warnings.catch_warnings():   # the files' notices were shown by check_user_files
        warnings.simplefilter("ignore")
        env = E.make_env(g["vehicle"], **{**base, **ctrl.overrides()})
      red = None
      if p["redteam"] and any(st.redteam for st in g["settings"]):
        try:
          red = redteam_agent(p, ctrl, env, log=lambda i, n, row, lab=f"{gname}: red-team agent vs {label}": bar.show(
              f"{lab} {i}/{n}"))
        except C.NotAvailable as e:
          results["not_run"][f"{gname}/{label}"] = str(e)
          bar.step(f"{gname}: {label} not run")
          continue
        results.setdefault("redteam", {})[ctrl.name] = {k: red[k] for k in ("dir", "trained", "train_s", "history",
                                                                            "config")}
      if isinstance(c, str) and c in baselines_lib.TRAINED:   # what its cache says of its training, for the report
        builds[f"{gname}/{ctrl.name}"] = baseline_build(g["ctx"], c)
      jobs.append((gname, ctrl, env, red))
  refused = requested_not_run(args, results["not_run"])
  if refused:
    bar.close()
    return _fail(refused)
  specs = [{"env": env, "policy": ctrl.policy, "policy_params": ctrl.params, "settings": p["groups"][gname]["settings"],
            "missions": missions, "max_s": args.max_s, "n_traj": args.traj, **_attacker(red)}
           for gname, ctrl, env, red in jobs]
  # A compiled rollout on the CPU holds ~4,000 memory mappings: 16 at once exceed the kernel's limit
  # (vm.max_map_count, 65,530 by default) and LLVM fails. So on the CPU each rollout compiles just before its flight
  # and is freed after it unless a later job shares it; an accelerator's host compiles them all together, overlapped.
  one_by_one = backend == "cpu"
  keys = [E.rollout_key(s) for s in specs] if one_by_one else []
  compiled = {}
  if not one_by_one:
    bar.show(f"compiling {len(jobs)} rollouts")
    compiled = E.precompile(specs)
    results["compile_wall_s"] = compiled["wall"]
  for i, (gname, ctrl, env, red) in enumerate(jobs):
    g, grp = p["groups"][gname], results["groups"][gname]
    bar.show(f"{gname}: {ctrl.name} ({len(g['settings'])} settings x {missions})")
    timing = {}
    rec, traj, steps = E.rollout(**specs[i], seed=args.seed, timing=timing,
                                 cache=not one_by_one or keys[i] in keys[i + 1:])
    timing["compile_s"] += compiled.get(i, 0.0)   # this job's own (overlapped) compile, 0 if shared
    if one_by_one:   # jax's own caches keep a flown executable (~4,000 mappings of code) alive: drop them too
      jax.clear_caches()
    records[(gname, ctrl.name)] = rec
    trajs[(gname, ctrl.name)] = traj
    grp["controllers"][ctrl.name] = {"description": ctrl.description,
                                     "env_overrides": {k: R.jsonable(v) for k, v in ctrl.env_overrides},
                                     "compile_s": timing["compile_s"], "run_s": timing["run_s"], "steps": steps,
                                     "recon_mode": env.config.recon_mode if env.config.reconstruction else None,
                                     "recovery_rule": env.config.recovery_rule}
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
          "date": started, "backend": backend, "device": str(jax.devices()[0]), "git_commit": commit,
          "seed": args.seed,
          "missions_per_setting": missions, "max_s": args.max_s, "mission_s": p["mission_s"], "run": args.run,
          "mission_file": args.mission, "params_file": args.params,
          "runs": p["runs"], "suite": args.suite, "profiles": list(p["profiles"]),
          "campaigns": list(p["campaigns"]), "hazard_lead_s": list(p["hazard_lead_s"]),
          "designed_rates": {x: r for g in p["groups"].values() for st in g["settings"]
                             if E.campaign_of(st.name) == "designed" for x, r in st.attack.ramp_rate},
          "redteam": ({"dir": p["redteam"]["dir"], "budget": args.redteam_budget,
                       "config": R.jsonable(dataclasses.asdict(p["redteam"]["config"]))} if p["redteam"] else None),
          "simulator": "specguard-jax MJX simulator (not AirSim)", "recon": args.recon or "fused",
          "recon_modes": {f"{g}/{c}": v["recon_mode"] for g, grp in results["groups"].items()
                          for c, v in grp["controllers"].items()},
          "recovery_rules": {f"{g}/{c}": v["recovery_rule"] for g, grp in results["groups"].items()
                             for c, v in grp["controllers"].items() if v["recovery_rule"] != "none"},
          "baseline_builds": builds}
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
