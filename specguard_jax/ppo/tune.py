"""An Optuna study over the training config (train.py --tune): trials asked in batches, each batch trained as vmapped
sweep programs (runner.train_sweep), intermediate held-out figures reported at every host call so the pruner can stop
a trial, the study kept in an Optuna storage (default SQLite in the output directory) so a rerun of the same command
resumes it, and the best trial's config written as a JSON that `train.py --config` reads.

Space file: a JSON object {config key: distribution}, keys dotted for nested fields as in --set:
  {"sg.lr": {"type": "log_uniform", "low": 1e-5, "high": 1e-3},
   "sg.ent_coef": {"type": "uniform", "low": 0.0, "high": 0.02},
   "seed": {"type": "int", "low": 0, "high": 9},
   "env.clearance": {"type": "categorical", "choices": [6, 9]}}
Types: log_uniform, uniform (floats, low < high, log_uniform needs low > 0), int (integers low <= high, optional
"step" > 0 and "log": true), categorical (a non-empty list of JSON values; lists and objects are offered to Optuna as
their JSON text). Both ends of a range and every choice must give a valid config.

Objectives: svr / rsr are the held-out evaluation's (iteration.heldout with the config's eval_missions per setting,
averaged over its settings), scored after every host call while pruning (only after the last one otherwise);
return is the SpecGuard agent's training return: the mean over the episodes that ended in the last iteration of the
latest host call that had any (a call before the first such one reports nothing). A trial's scores (all three where
evaluated) are its user attribute 'scores'.

A batch's members are grouped by compiled program (iteration.program_config): members differing only in
runner.SWEEP_DATA_KEYS (seed, the agents' learning rate, entropy/value coefficients, clip range) train as ONE vmapped
program whose member axis is sharded over the devices; other groups train one after another.

Pruning: a pruned member's trial is told PRUNED at once and gets no further held-out evaluations; its lane in the
vmapped program keeps training until the program ends (the lanes run in lockstep) and its results are ignored; when
every member of a program is pruned, the program stops at that host call. Multi-objective studies (svr and rsr) are
not pruned (Optuna's pruners take one objective) and evaluate only after the last call.

Interruptions: a trial left RUNNING in the storage by a killed process is told FAIL when the study is loaded again,
and its parameters are enqueued, so the next batch asks that point again as a new trial; a Ctrl-C does the same at
once. The study counts finished trials (COMPLETE or PRUNED): `--tune 8` stops when the storage holds 8.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np

from specguard_jax.ppo import config as C
from specguard_jax.ppo import iteration as it
from specguard_jax.ppo import runner

KINDS = ("log_uniform", "uniform", "int", "categorical")
OBJECTIVES = {   # objective name -> ((metric, direction), ...)
    "svr": (("svr", "minimize"),), "rsr": (("rsr", "maximize"),), "return": (("return", "maximize"),),
    "svr+rsr": (("svr", "minimize"), ("rsr", "maximize"))}
PRUNERS = ("median", "halving", "none")


@dataclasses.dataclass(frozen=True)
class Dim:
  """One searched config key: kind (KINDS); low/high the range (floats, or ints for 'int'); step/log of an 'int';
  choices of a 'categorical' (JSON values)."""
  key: str
  kind: str
  low: float | int | None = None
  high: float | int | None = None
  step: int = 1
  log: bool = False
  choices: tuple = ()


def _real(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _dim(key: str, spec) -> Dim:
  """A space entry as a Dim; a bad one is a ValueError whose one line names the key."""
  if not isinstance(spec, dict):
    raise ValueError(f"{key}: expected an object like {{\"type\": \"uniform\", \"low\": 0, \"high\": 1}}, "
                     f"got {json.dumps(spec)}")
  kind = spec.get("type")
  if kind not in KINDS:
    raise ValueError(f"{key}: type {kind!r} is not one of {', '.join(KINDS)}")
  allowed = {"type", "choices"} if kind == "categorical" else {"type", "low", "high"} | (
      {"step", "log"} if kind == "int" else set())
  extra = sorted(set(spec) - allowed)
  if extra:
    raise ValueError(f"{key}: {kind} takes {', '.join(sorted(allowed - {'type'}))}, not {', '.join(extra)}")
  if kind == "categorical":
    ch = spec.get("choices")
    if not isinstance(ch, list) or not ch:
      raise ValueError(f"{key}: categorical needs \"choices\": a non-empty list")
    return Dim(key, kind, choices=tuple(ch))
  lo, hi = spec.get("low"), spec.get("high")
  if kind == "int":
    step, log = spec.get("step", 1), spec.get("log", False)
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (lo, hi, step)):
      raise ValueError(f"{key}: int needs integer \"low\" and \"high\" (and \"step\"), got low={lo!r} high={hi!r}")
    if lo > hi or step < 1 or not isinstance(log, bool) or (log and (lo < 1 or step != 1)):
      raise ValueError(f"{key}: int needs low <= high, step >= 1, and low >= 1 with step 1 when log "
                       f"(got low={lo} high={hi} step={step} log={log!r})")
    return Dim(key, kind, lo, hi, step, log)
  if not (_real(lo) and _real(hi)):
    raise ValueError(f"{key}: {kind} needs numeric \"low\" and \"high\", got low={lo!r} high={hi!r}")
  if not lo < hi or (kind == "log_uniform" and lo <= 0):
    raise ValueError(f"{key}: {kind} needs {'0 < ' if kind == 'log_uniform' else ''}low < high, "
                     f"got low={lo} high={hi}")
  return Dim(key, kind, float(lo), float(hi), log=kind == "log_uniform")


def _values(d: Dim) -> list:
  """The values a Dim's check tries: both ends of a range, every choice."""
  if d.kind == "categorical":
    return list(d.choices)
  if d.kind == "int":
    return [d.low, d.low + (d.high - d.low) // d.step * d.step]
  return [d.low, d.high]


def load_space(path: str, base: C.TrainConfig) -> tuple:
  """The space file at path as Dims, checked against base: every key exists in TrainConfig, every range end and
  choice gives a valid config. Every problem is a one-line ValueError naming the file."""
  try:
    with open(path, encoding="utf-8") as f:
      raw = json.load(f)
  except (OSError, ValueError) as e:
    raise ValueError(f"cannot read tune space {path}: {' '.join(str(e).split())}") from None
  except RecursionError:
    raise ValueError(f"cannot read tune space {path}: JSON nested too deeply") from None
  if not isinstance(raw, dict) or not raw:
    raise ValueError(f"tune space {path} must hold a non-empty JSON object {{config key: distribution}}")
  dims = []
  for key, spec in raw.items():
    try:
      d = _dim(key, spec)
      for v in _values(d):
        C.from_dict(C.nested({key: v}), base).validate()
    except ValueError as e:
      raise ValueError(f"tune space {path}: {' '.join(str(e).split())}") from None
    dims.append(d)
  return tuple(dims)


def _scalar(v) -> bool:
  return v is None or isinstance(v, (bool, int, float, str))


def suggest(trial, dims) -> dict:
  """{config key: value} for one trial from Optuna's suggest_* calls (param names are the config keys)."""
  point = {}
  for d in dims:
    if d.kind == "categorical":
      if all(_scalar(c) for c in d.choices):
        point[d.key] = trial.suggest_categorical(d.key, list(d.choices))
      else:   # Optuna's choices are scalars: offer the JSON texts
        point[d.key] = json.loads(trial.suggest_categorical(d.key, [json.dumps(c) for c in d.choices]))
    elif d.kind == "int":
      point[d.key] = trial.suggest_int(d.key, d.low, d.high, step=d.step, log=d.log)
    else:
      point[d.key] = trial.suggest_float(d.key, d.low, d.high, log=d.log)
  return point


def heldout_means(h: dict) -> dict:
  """{'svr', 'rsr'}: the held-out evaluation's (iteration.heldout) figures averaged over its settings (attack-free
  and each sensor/profile attack, equally weighted)."""
  rows = [v for k, v in h.items() if k[0] != "_"]
  return {m: float(np.mean([r[m] for r in rows])) for m in ("svr", "rsr")}


@dataclasses.dataclass(frozen=True)
class StudySpec:
  """What train.py --tune asks: trials (finished trials the study should hold), batch (trials asked at once),
  storage (an Optuna storage URL), name (the study's), objective (OBJECTIVES), pruner (a PRUNERS name or an Optuna
  pruner object). The pruners and sampler are not kept in the storage: a resumed study gets them from here again."""
  trials: int
  batch: int
  storage: str
  name: str
  objective: str = "svr"
  pruner: object = "median"


def _study(spec: StudySpec, seed: int, log):
  import optuna
  optuna.logging.set_verbosity(optuna.logging.WARNING)
  metrics = OBJECTIVES[spec.objective]
  directions = [d for _, d in metrics]
  pruner = spec.pruner
  if isinstance(pruner, str):   # median: prunes from the second batch on, against the first batch's finished trials
    pruner = {"median": lambda: optuna.pruners.MedianPruner(n_startup_trials=spec.batch),
              "halving": lambda: optuna.pruners.SuccessiveHalvingPruner(),
              "none": lambda: optuna.pruners.NopPruner()}[pruner]()
  # Reseeded by the study's trial count, so a resumed study does not replay the first run's random startup points.
  probe = optuna.create_study(storage=spec.storage, study_name=spec.name, directions=directions, load_if_exists=True)
  if [d.name.lower() for d in probe.directions] != directions:
    raise ValueError(f"study {spec.name!r} in {spec.storage} optimises "
                     f"{[d.name.lower() for d in probe.directions]}; --tune-objective {spec.objective} wants "
                     f"{directions}: use another --study-name")
  sampler = optuna.samplers.TPESampler(seed=seed + len(probe.trials))
  study = optuna.load_study(storage=spec.storage, study_name=spec.name, sampler=sampler, pruner=pruner)
  stale = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,))
  for t in stale:
    study.tell(t.number, state=optuna.trial.TrialState.FAIL, skip_if_finished=True)
    study.enqueue_trial(t.params)
  if stale:
    numbers = ", ".join(str(t.number) for t in stale)
    log(f"[tune] {len(stale)} trial(s) left running by an interrupted process ({numbers}) marked FAIL; their points "
        "are asked again")
  return study


def _finished(study) -> int:
  from optuna.trial import TrialState
  return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED)))


def run_study(base: C.TrainConfig, dims, spec: StudySpec, out: str, *, progress: bool = True, export: bool = False,
              compile_ahead: bool | None = None, log=print) -> dict:
  """Run (or resume) the study until it holds spec.trials finished trials; trial k trains in out/trial_<k>/. Writes
  out/tune.json (every trial) and out/best_config.json (single objective: the best trial's config; svr+rsr: the
  Pareto-optimal trial of lowest SVR, all Pareto trials listed in tune.json). Returns {'best': config dict or None,
  'trials': rows}."""
  from optuna.trial import TrialState
  metrics = [m for m, _ in OBJECTIVES[spec.objective]]
  if base.eval_missions < 1 and metrics != ["return"]:
    raise ValueError(f"--tune-objective {spec.objective} scores the held-out evaluation: eval_missions must be >= 1")
  os.makedirs(out, exist_ok=True)
  study = _study(spec, base.seed, log)
  prune = len(metrics) == 1 and spec.pruner != "none"
  running = []
  try:
    while (done := _finished(study)) < spec.trials:
      asked = [study.ask() for _ in range(min(spec.batch, spec.trials - done))]
      running = list(asked)
      members = []
      for t in asked:
        point = suggest(t, dims)
        try:
          cfg = C.from_dict(C.nested(point), base).validate()
        except ValueError as e:
          t.set_user_attr("error", str(e))
          study.tell(t, state=TrialState.FAIL)
          log(f"[tune] trial {t.number} failed: {e}")
          continue
        t.set_user_attr("config", cfg.to_dict())
        members.append((t, point, cfg))
      if not members:
        raise ValueError("every trial of a batch gave an invalid config (see the lines above)")
      groups = {}
      for m in members:
        groups.setdefault(it.program_config(m[2]), []).append(m)
      log(f"[tune] trials {', '.join(str(t.number) for t, _, _ in members)}: {len(groups)} program(s) "
          f"of {', '.join(str(len(g)) for g in groups.values())} member(s)")
      for grp in groups.values():
        _run_group(study, grp, metrics, prune, out, progress=progress, export=export, compile_ahead=compile_ahead,
                   log=log)
      running = []
      if _finished(study) == done:   # every trial of the batch failed: another batch would fail the same way
        raise ValueError("no trial of the batch finished: " + "; ".join(
            f"trial {t.number}: {study.get_trials(deepcopy=False)[t.number].user_attrs.get('error')}" for t in asked))
  except BaseException:
    mine = {t.number for t in running}   # an interruption (Ctrl-C, an error): this batch's unfinished trials
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):   # FAIL, and are asked again later
      if t.number in mine:
        study.tell(t.number, state=TrialState.FAIL)
        study.enqueue_trial(t.params)
    raise
  return _write_results(study, metrics, out, log)


def _run_group(study, grp, metrics, prune, out, *, progress, export, compile_ahead, log) -> None:
  """Train one program's members (runner.train_sweep) and tell each trial its outcome."""
  from optuna.trial import TrialState
  S = len(grp)
  live = [True] * S
  final = [None] * S
  returns = [float("nan")] * S   # each member's latest finite training return (NaN in a call where no episode ended)
  missions = grp[0][2].eval_missions
  heldout_needed = any(m != "return" for m in metrics)

  def score(s, sg_state):
    vals = {"return": returns[s]}
    if heldout_needed:
      vals.update(heldout_means(it.heldout(grp[s][2], _member(sg_state, s), missions)))
    return vals

  def on_call(step, last_call, sg_state, train_metrics):
    for s, (t, _, _) in enumerate(grp):
      if math.isfinite(train_metrics[s]["return"]):
        returns[s] = train_metrics[s]["return"]
      if not live[s] or not (prune or last_call):
        continue
      vals = score(s, sg_state)
      if last_call:
        final[s] = vals
      if not prune or not math.isfinite(vals[metrics[0]]):   # no return yet: nothing to report at this call
        continue
      t.report(vals[metrics[0]], step)
      if not last_call and t.should_prune():
        live[s] = False
        t.set_user_attr("scores", vals)
        study.tell(t, state=TrialState.PRUNED)
        log(f"[tune] trial {t.number} pruned after host call {step + 1} ({metrics[0]} {vals[metrics[0]]:.4g})")
    return not any(live)

  cfgs = [dataclasses.replace(c, eval_missions=0) for _, _, c in grp]   # on_call evaluates; not again at the end
  names = [f"trial_{t.number}" for t, _, _ in grp]
  for (t, _, _), name in zip(grp, names):   # before training: a trial told PRUNED takes no more attributes
    t.set_user_attr("run_dir", os.path.abspath(os.path.join(out, name)))
    t.set_user_attr("program_members", S)
  runner.train_sweep(cfgs, names, out, progress=progress, export=export, log=log, compile_ahead=compile_ahead,
                     on_call=on_call)
  for s, (t, point, _) in enumerate(grp):
    if not live[s]:
      continue
    vals = final[s]
    values = [vals[m] for m in metrics]
    if not all(math.isfinite(v) for v in values):
      why = ("no training episode ended (a longer budget or a shorter env.max_episode_s gives returns)"
             if "return" in metrics else f"objective not finite ({vals})")
      t.set_user_attr("error", why)
      study.tell(t, state=TrialState.FAIL)
      log(f"[tune] trial {t.number} failed: {why}")
      continue
    t.set_user_attr("scores", vals)
    study.tell(t, values)
    log(f"[tune] trial {t.number} " + " ".join(f"{m} {v:.4g}" for m, v in zip(metrics, values)) + f" {point}")


def _member(tree, s: int):
  import jax
  return jax.tree.map(lambda x: x[s], tree)


def _write_results(study, metrics, out: str, log) -> dict:
  from optuna.trial import TrialState
  trials = study.get_trials(deepcopy=False)
  if len(metrics) == 1:
    done = [t for t in trials if t.state == TrialState.COMPLETE]
    best = [study.best_trial] if done else []
  else:
    best = sorted(study.best_trials, key=lambda t: (t.values[0], -t.values[1]))
  best_numbers = {t.number for t in best}
  rows = [{"number": t.number, "state": t.state.name, "params": t.params,
           "values": dict(zip(metrics, t.values)) if t.values else None,
           "intermediate": {str(k): v for k, v in sorted(t.intermediate_values.items())},
           "scores": t.user_attrs.get("scores"), "run_dir": t.user_attrs.get("run_dir"),
           "program_members": t.user_attrs.get("program_members"), "error": t.user_attrs.get("error"),
           "best": t.number in best_numbers} for t in trials]
  with open(os.path.join(out, "tune.json"), "w") as f:
    json.dump(rows, f, indent=1)
  states = {}
  for r in rows:
    states[r["state"]] = states.get(r["state"], 0) + 1
  log(f"[tune] study {study.study_name}: {', '.join(f'{n} {k.lower()}' for k, n in sorted(states.items()))}; "
      f"{os.path.abspath(os.path.join(out, 'tune.json'))}")
  if not best:
    log("[tune] no trial completed: no best config")
    return {"best": None, "trials": rows}
  cfg = best[0].user_attrs["config"]
  path = os.path.join(out, "best_config.json")
  with open(path, "w") as f:
    json.dump(cfg, f, indent=1)
  log(f"[tune] best trial {best[0].number} ({', '.join(f'{m} {v:.4g}' for m, v in zip(metrics, best[0].values))}): "
      f"{os.path.abspath(path)} (train.py --config reads it)")
  return {"best": cfg, "trials": rows}
