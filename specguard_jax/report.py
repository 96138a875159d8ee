"""evaluate.py's report: metrics per group / controller / setting (specguard_jax.metrics), the paper's tables filled
with ours beside the paper's numbers (report.json, report.md), PNG figures (matplotlib, Agg) and per-mission
records (records/<group>__<controller>.npz)."""

from __future__ import annotations

import collections
import json
import math
import os

import numpy as np

from specguard_jax import metrics as M

# The paper's numbers (CCS 2024, AirSim/PX4; percentages). Ranges where the paper gives only a range.
PAPER = {
    "compliance": {"compliance": 0.0, "binary": 25.0},
    "table5": {"overt": {"no_protection": 100.0, "specguard_pc": 14.8, "specguard_rc": 13.5},
               "stealthy": {"no_protection": 100.0, "specguard_pc": 18.66, "specguard_rc": 14.83}},
    "fig9": {"overt": {"specguard_rc": (13.5, 92.1), "unrocker": (66.0, 46.0), "delorean": (66.0, 46.0),
                       "ssr": ("66.8-79.1", "37.5-46"), "ftc": ("66.8-79.1", "37.5-46"),
                       "pid_piper": ("66.8-79.1", "37.5-46")},
             "stealthy": {"specguard_rc": (14.83, 90.41), "ftc": (90.0, 17.0), "unrocker": (86.0, 17.0),
                          "ssr": (81.0, 35.0), "pid_piper": (70.0, 39.75), "delorean": (69.5, 43.0)}},
    "fig10": {"svr_max": 3.33, "baro_svr": 0.0, "md_range": (3.2, 6.88)},
    "ablation": {"specguard_rc": (13.5, 92.1), "delorean": (60.4, 45.8), "specguard_no_recon": (67.9, "~46")},
    "multi": 24.0,
    "unseen": {"suburban_to_urban": (14.6, 16.7), "urban_to_suburban": (12.1, 14.8)},
    "rover_real": {"svr": 5.0, "rsr": 100.0, "md": 5.88},
    "t2r": "SpecGuard-RC recovers 3x faster than SpecGuard-PC (CDF, Fig. 3b)",
}
CAMPAIGN_ORDER = ("long", "hazard", "designed", "multi", "redteam")
SIM_LINE = ("Our numbers come from our MJX simulator (specguard-jax: MuJoCo MJX physics, our PX4/ArduPilot-like "
            "autopilots, sensors, EKF and attacks), not AirSim (the paper's AirSim/PX4 setup); compare shapes and ratios, not "
            "absolute values.")


def jsonable(x):
  """Plain JSON types (numpy scalars/arrays, tuples, dataclasses' reprs)."""
  if isinstance(x, dict):
    return {str(k): jsonable(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [jsonable(v) for v in x]
  if isinstance(x, (np.bool_, bool)):
    return bool(x)
  if isinstance(x, (np.integer,)):
    return int(x)
  if isinstance(x, (np.floating, float)):
    x = float(x)
    return x if math.isfinite(x) else None
  if isinstance(x, np.ndarray):
    return jsonable(x.tolist())
  if x is None or isinstance(x, (int, str)):
    return x
  return repr(x)


def _profile(name: str):
  return name.split("/")[1] if "/" in name else None


def _single(name: str) -> bool:
  return name.count("/") == 1 and "+" not in name


def _campaign(name: str):
  """'hazard/gps/overt' -> 'hazard' (a campaign setting, evaluation.campaign_settings); else None."""
  parts = name.split("/")
  return parts[0] if len(parts) == 3 else None


def _attack_free(setting: str) -> bool:
  """Attack-free missions: the attack-free setting and the forced false alarms (a zero-bias attack)."""
  return setting == "attack_free" or setting.startswith("false_alarm/")


def build(results: dict, records: dict, meta: dict) -> dict:
  """The report dict: per group/controller/setting metrics, pooled settings, the paper's experiments as views."""
  groups = {}
  for gname, g in results["groups"].items():
    env = g.get("env") or {}
    if not env.get("spec_names"):
      groups[gname] = dict(g, metrics={})
      continue
    dt, names, crit = env["dt"], env["spec_names"], env["critical"]
    settings = g["settings"]
    twin = records.get((gname, "no_protection"))
    # ground truth: the twin's attack-free missions; a group without that setting (false alarms) flies only
    # attack-free missions, so all of its twin's are
    af = settings.index("attack_free") if "attack_free" in settings else None
    gt_all = None if twin is None else (twin if af is None else M.select(twin, twin["setting"] == af))
    t_b = M.baseline_time(gt_all) if gt_all is not None else None
    per = {}
    for (gn, cname), rec in records.items():
      if gn != gname:
        continue
      out = {}
      pools = {}
      for i, s in enumerate(settings):
        r = M.select(rec, rec["setting"] == i)
        tw = M.select(twin, twin["setting"] == i) if twin is not None else None
        out[s] = M.summarize(r, tw, gt_all, attacked=not _attack_free(s), dt=dt, spec_names=names, critical=crit,
                             t_b=t_b)
        if _single(s):
          for key in (f"pooled/{_profile(s)}", "pooled/attacked"):
            pools.setdefault(key, []).append((r, tw, gt_all))
        elif _campaign(s):
          pools.setdefault(f"campaign/{_campaign(s)}", []).append((r, tw, gt_all))
      for key, parts in pools.items():
        r = M.concat([p[0] for p in parts])
        tw = M.concat([p[1] for p in parts]) if twin is not None else None
        gt = M.concat([p[2] for p in parts]) if gt_all is not None else None
        out[key] = M.summarize(r, tw, gt, attacked=True, dt=dt, spec_names=names, critical=crit, t_b=t_b)
        out[key]["settings"] = len(parts)
      per[cname] = out
    groups[gname] = dict(g, metrics=per, t_b=t_b, paired=paired_tests(records, gname, settings, crit))
  rep = {"meta": meta, "not_run": results["not_run"], "skipped_experiments": results["skipped_experiments"],
         "groups": groups, "paper": PAPER}
  rep["totals"] = {"missions": int(sum(r["missions"] for r in results["rollouts"])),
                   "rollouts": len(results["rollouts"]),
                   # compile wall time (on an accelerator the rollouts compile together, overlapped:
                   # evaluation.precompile; on the CPU one by one) and the sum of the per-rollout compile times
                   "compile_s": float(results.get("compile_wall_s",
                                                  sum(r.get("compile_s", 0.0) for r in results["rollouts"]))),
                   "compile_sum_s": float(sum(r.get("compile_s", 0.0) for r in results["rollouts"])),
                   "run_s": float(sum(r.get("run_s", 0.0) for r in results["rollouts"]))}
  rep["experiments"] = experiments(rep)
  rt = redteam_log(results, records)
  if rt:
    rep["redteam"] = rt
  return rep


def _is_redteam(name: str) -> bool:
  return _campaign(name) == "redteam"


def redteam_log(results: dict, records: dict, group: str = "main") -> dict:
  """The red-team campaign's log: {controller: {agent (its dir, whether trained in this run, training seconds and
  per-iteration history), setting, missions: [{mission, world, sensor (the agent's first choice), sensors (all it
  spoofed), onset_s, duration_s, violated, complete, crash, collision}] (sensor None and onset/duration None when the
  agent never attacked; duration_s ends at the episode's end, so a crash during the attack cuts it short), summary:
  {missions, attacked, sensors: {name: missions spoofing it}, combinations: {'gyro+mag': missions}, onset_s /
  duration_s: {median, min, max} over the attacked missions, any_violation, crash}}}; {} when no red-team setting
  was flown."""
  from specguard_jax.types import SENSOR_NAMES
  g = results["groups"].get(group)
  if not g:
    return {}
  names = [s for s in g["settings"] if _is_redteam(s)]
  out = {}
  for (gn, cname), rec in records.items():
    if gn != group or "redteam_sensor" not in rec or not names:
      continue
    i = g["settings"].index(names[0])
    r = M.select(rec, rec["setting"] == i)
    sens = np.asarray(r["redteam_sensor"])
    hit = sens >= 0
    onset = np.where(hit, r["onset"], np.nan)
    dur = np.where(hit, r["attack_end"] - r["onset"], np.nan)
    viol = M.violation(r)
    rows = [{"mission": int(r["mission"][k]), "world": int(r["world"][k]),
             "sensor": SENSOR_NAMES[int(sens[k])] if hit[k] else None,
             "sensors": ([n for j, n in enumerate(SENSOR_NAMES) if r["redteam_mask"][k, j] > 0] if "redteam_mask" in r
                         else [SENSOR_NAMES[int(sens[k])]] if hit[k] else []),   # records without the mask: the first
             "onset_s": float(onset[k]) if hit[k] else None, "duration_s": float(dur[k]) if hit[k] else None,
             "violated": bool(viol[k]), "complete": bool(r["complete"][k]), "crash": bool(r["crash"][k]),
             "collision": bool(r["collision"][k])} for k in range(len(sens))]

    def stats(x):
      x = x[np.isfinite(x)]
      return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max())} if len(x) else None
    counts = collections.Counter(name for m in rows for name in m["sensors"])
    combos = collections.Counter("+".join(m["sensors"]) for m in rows if m["sensors"])
    n = len(rows)
    out[cname] = {"setting": names[0], "agent": (results.get("redteam") or {}).get(cname), "missions": rows,
                  "summary": {"missions": n, "attacked": float(np.mean(hit)) if n else 0.0,
                              "sensors": {k: counts[k] for k in SENSOR_NAMES if counts[k]},
                              "combinations": dict(combos.most_common()),
                              "onset_s": stats(onset), "duration_s": stats(dur),
                              "any_violation": float(np.mean(viol)) if n else 0.0,
                              "crash": float(np.mean(np.asarray(r["crash"]) > 0)) if n else 0.0}}
  return out


def paired_tests(records: dict, group: str, settings, critical) -> dict:
  """{setting (and pooled/<profile>, pooled/attacked): {"A vs B": metrics.paired(...)}} for every pair of the group's
  controllers (in the records' order): McNemar's exact test on the same missions (SVR event over the intended
  missions, any violation and critical-spec violations over all missions)."""
  ctrls = [c for (g, c) in records if g == group]
  twin = records.get((group, "no_protection"))
  rows = {s: np.asarray(records[(group, ctrls[0])]["setting"]) == i for i, s in enumerate(settings)} if ctrls else {}
  for p in ("overt", "stealthy"):
    ids = [i for i, s in enumerate(settings) if _single(s) and _profile(s) == p]
    if ids and ctrls:
      rows[f"pooled/{p}"] = np.isin(records[(group, ctrls[0])]["setting"], ids)
  ids = [i for i, s in enumerate(settings) if _single(s)]
  if ids and ctrls:
    rows["pooled/attacked"] = np.isin(records[(group, ctrls[0])]["setting"], ids)
  out = {}
  for s, mask in rows.items():
    tw = M.select(twin, mask) if twin is not None and s != "attack_free" else None
    out[s] = {f"{a} vs {b}": M.paired(M.select(records[(group, a)], mask), M.select(records[(group, b)], mask), tw,
                                      critical=critical)
              for i, a in enumerate(ctrls) for b in ctrls[i + 1:]}
  return out


def _m(rep, group, ctrl, setting, key="svr"):
  v = rep["groups"].get(group, {}).get("metrics", {}).get(ctrl, {}).get(setting, {})
  if key in ("svr", "svr_all", "rsr", "md", "collision_rate"):
    return v.get(key)
  return v.get(key)


def _pct(x):
  return None if x is None else 100.0 * x


def _svr_cell(rep, group, ctrl, setting):
  """The SVR to quote: no protection's is 100 % by construction (it is its own twin), so it gets its share of attacked
  missions with any violation instead (metrics.summarize 'any_violation')."""
  return _m(rep, group, ctrl, setting, "any_violation" if ctrl == "no_protection" else "svr")


def primary_specguard(rep, group="main"):
  ms = rep["groups"].get(group, {}).get("metrics", {})
  for c in ("specguard_rc", "specguard_pc"):
    if c in ms:
      return c
  return None


def experiments(rep) -> dict:
  """The paper's experiments as views of the metrics (percentages; None = not run)."""
  ex = {}
  main = rep["groups"].get("main", {}).get("metrics", {})
  ctrls = list(main)
  profiles = [p for p in ("overt", "stealthy") if any(f"pooled/{p}" in v for v in main.values())]
  ex["compliance"] = {c: _pct(_m(rep, "main", c, "attack_free", "svr_all")) for c in ctrls}
  ex["table5"] = {p: {c: _pct(_svr_cell(rep, "main", c, f"pooled/{p}")) for c in ("no_protection", "specguard_pc",
                                                                           "specguard_rc")} for p in profiles}
  ex["fig9"] = {p: {c: {"svr": _pct(_svr_cell(rep, "main", c, f"pooled/{p}")),
                        "any_violation": _pct(_m(rep, "main", c, f"pooled/{p}", "any_violation")),
                        "rsr": _pct(_m(rep, "main", c, f"pooled/{p}", "rsr")),
                        "collision": _pct(_m(rep, "main", c, f"pooled/{p}", "collision_rate"))} for c in ctrls}
                for p in profiles}
  sg = primary_specguard(rep)
  if sg:
    sens = [s for s in rep["groups"]["main"]["settings"] if _single(s)]
    ex["fig10"] = {"controller": sg, "per_setting": {s: {"svr": _pct(_m(rep, "main", sg, s)),
                                                         "md": _m(rep, "main", sg, s, "md")} for s in sens}}
  ex["ablation"] = {c: {"svr": _pct(_m(rep, "main", c, "pooled/attacked")),
                        "rsr": _pct(_m(rep, "main", c, "pooled/attacked", "rsr")),
                        "collision": _pct(_m(rep, "main", c, "pooled/attacked", "collision_rate"))}
                    for c in ("specguard_rc", "specguard_pc", "delorean", "specguard_no_recon", "specguard_binary")
                    if c in main}
  multi = [s for s in rep["groups"].get("main", {}).get("settings", []) if "+" in s]
  ex["multi"] = {s: {c: {"svr": _pct(_svr_cell(rep, "main", c, s)), "rsr": _pct(_m(rep, "main", c, s, "rsr"))}
                     for c in ctrls} for s in multi}
  ex["unseen"] = {}
  for g in ("suburban_to_urban", "urban_to_suburban"):
    gm = rep["groups"].get(g, {}).get("metrics", {})
    ex["unseen"][g] = {c: {p: _pct(_svr_cell(rep, g, c, f"pooled/{p}")) for p in profiles} for c in gm}
  gm = rep["groups"].get("rover", {}).get("metrics", {})
  ex["rover"] = {c: {"svr": _pct(_svr_cell(rep, "rover", c, "pooled/attacked")),
                     "rsr": _pct(_m(rep, "rover", c, "pooled/attacked", "rsr")),
                     "md": _m(rep, "rover", c, "pooled/attacked", "md")} for c in gm}
  ex["t2r"] = {c: {p: main[c].get(f"pooled/{p}", {}).get("t2r_stats") for p in profiles} for c in ctrls}
  ex["detection"] = {c: {p: {"detect": main[c].get(f"pooled/{p}", {}).get("detect_rate", {}).get("value"),
                             "delay": main[c].get(f"pooled/{p}", {}).get("detection_delay")} for p in profiles}
                     for c in ctrls}
  ex["shape"] = shape_statements(ex, sg)
  ex["hard"] = hard_table(rep)
  ex["hard_goal"] = hard_goal(rep, ex["hard"])
  return ex


def hard_table(rep, group="main") -> dict:
  """The hard suite's opening table: {campaign: {controller: {svr, critical, rsr, md}}} over the campaign's
  settings pooled ('campaign/<name>'), plus 'attack_free'. Rates as {'value', 'ci', 'k', 'n'} (fractions); md as
  {'mean', 'ci', 'median', 'n'} (%). No protection's SVR is the share of attacked missions with any violation (its
  twin is itself); every other controller's is over the missions no protection violated (metrics.summarize)."""
  ms = rep["groups"].get(group, {}).get("metrics", {})
  keys = sorted({k for v in ms.values() for k in v if k.startswith("campaign/")},
                key=lambda k: (CAMPAIGN_ORDER.index(k[9:]) if k[9:] in CAMPAIGN_ORDER else 99, k))
  out = {}
  for k in (["attack_free"] + keys) if keys else []:
    row = {}
    for c, v in ms.items():
      m = v.get(k)
      if not m:
        continue
      # the red-team attacks differ between controllers (each its own agent): no protection is no twin there
      own = c == "no_protection" or k in ("attack_free", "campaign/redteam")
      svr = m.get("svr_all_rate") if own else m.get("svr_rate")
      row[c] = {"svr": svr, "critical": m.get("critical_rate"), "rsr": m.get("rsr_rate"), "md": m.get("md_stats"),
                "missions": m.get("missions"), "settings": m.get("settings", 1)}
    out[k.replace("campaign/", "")] = row
  return out


def shape_statements(ex, sg) -> list:
  """Plain sentences comparing SpecGuard with every other controller on pooled SVR and RSR, per profile."""
  out = []
  if not sg:
    return ["No SpecGuard run was evaluated: no comparison."]
  for p, rows in ex.get("fig9", {}).items():
    me = rows.get(sg, {})
    if me.get("svr") is None:
      continue
    for c, v in rows.items():
      if c in (sg, "no_protection") or v.get("svr") is None:
        continue
      beats_svr = me["svr"] < v["svr"]
      beats_rsr = (me["rsr"] or 0) > (v["rsr"] or 0)
      r_svr = v["svr"] / me["svr"] if me["svr"] > 0 else math.inf
      r_rsr = me["rsr"] / v["rsr"] if v["rsr"] else math.inf
      verdict = ("beats" if beats_svr and beats_rsr else "does NOT beat")
      out.append(f"{p}: {sg} {verdict} {c}: SVR {me['svr']:.1f} % vs {v['svr']:.1f} % ({r_svr:.2f}x lower; "
                 f"paper ~5x), RSR {me['rsr']:.1f} % vs {v['rsr']:.1f} % ({r_rsr:.2f}x higher; paper ~2x).")
  return out


# ------------------------------------------------------------------------------------------------- markdown


def _f(x, nd=1):
  if x is None:
    return "n/a"
  if isinstance(x, str):
    return x
  return f"{x:.{nd}f}"


def _g(x) -> str:
  """A build record's number: integers as they are, others to 3 significant digits."""
  return str(x) if isinstance(x, int) else f"{x:.3g}"


def builds_line(builds: dict) -> str:
  """The header line of what each trained baseline's cache says of its fit ({"group/controller": build record}):
  its numbers; lists (loss and return curves) and flags stay in report.json (meta.baseline_builds)."""
  return "- trained baselines' builds (numbers; curves in report.json meta.baseline_builds): " + "; ".join(
      f"{k} " + (b["error"] if "error" in b else ", ".join(
          f"{n} {_g(v)}" for n, v in b.items() if isinstance(v, (int, float)) and not isinstance(v, bool)))
      for k, b in builds.items())


def _ci(rate, with_n: bool = True):
  if not rate or rate.get("value") is None:
    return "n/a"
  lo, hi = rate["ci"]
  return f"{100 * rate['value']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]" + (f" (n={rate['n']})" if with_n else "")


def markdown(rep) -> str:
  ex, meta, P = rep["experiments"], rep["meta"], PAPER
  L = ["# SpecGuard evaluation report", "", SIM_LINE, "",
       f"- command: `{meta['command']}`", f"- date {meta['date']}, backend {meta['backend']} ({meta['device']}), "
       f"commit {meta.get('git_commit')}",
       f"- seed {meta['seed']}, {meta['missions_per_setting']} missions per setting and controller, "
       f"{rep['totals']['missions']} missions in all ({rep['totals']['rollouts']} batched rollouts); wall time "
       f"{rep.get('wall_s', 0):.1f} s (compile {rep['totals']['compile_s']:.1f} s, flying "
       f"{rep['totals']['run_s']:.1f} s)",
       "- SVR = observed / intended violations (intended: the same mission flown with no protection violated a spec "
       "or crashed); RSR = completed within 5 m of the last waypoint without crash/collision/stall, over missions "
       "under attack; MD = (T - T_GT) / T_b x 100 over completed missions; definitions in specguard_jax/metrics.py. "
       "All values in %, 95 % Wilson intervals in report.json.",
       "- No protection is its own twin, so its SVR is 100 % by construction: wherever a table quotes an SVR for "
       "no protection it is its share of missions under attack with any violation (column 'any viol.' for every "
       "controller).", ""]
  if meta.get("merged_from"):   # evaluate.py --merge: the parts' own commands
    L[-1:-1] = [f"- merged from {len(meta['merged_from'])} evaluations of the same missions: " + "; ".join(
        f"`{m['command']}` ({m['date']}, {', '.join(m['controllers'])})" for m in meta["merged_from"])]
  if meta.get("recon_modes"):
    L[-1:-1] = ["- state reconstruction (EnvConfig.recon_mode) per controller: " + ", ".join(
        f"{k} {v or 'none'}" for k, v in meta["recon_modes"].items())]
  if meta.get("recovery_rules"):   # the fallback, and a learned policy trained over the rule (a residual on it)
    L[-1:-1] = ["- rule under the alarm (EnvConfig.recovery_rule), where not none: " + ", ".join(
        f"{k} {v}" for k, v in meta["recovery_rules"].items())]
  if meta.get("baseline_builds"):
    L[-1:-1] = [builds_line(meta["baseline_builds"])]
  L += hard_markdown(ex.get("hard"))
  L += hard_goal_markdown(ex.get("hard_goal"))
  L += violation_timing_markdown(rep)
  L += blind_markdown(rep)
  L += redteam_markdown(rep.get("redteam"))
  if rep["not_run"]:
    L += ["## Not run", ""] + [f"- `{k}`: {v}" for k, v in rep["not_run"].items()] + [""]
  if rep["skipped_experiments"]:
    L += ["## Experiments skipped", ""] + [f"- {k}: {v}" for k, v in rep["skipped_experiments"].items()] + [""]
  L += ["## Attack-free compliance (paper Sec. 6.1: compliance reward 0 % SVR, binary ~25 %)", "",
        "| controller | SVR ours | paper |", "|---|---|---|"]
  for c, v in ex["compliance"].items():
    paper = P["compliance"]["binary"] if c == "specguard_binary" else (0.0 if c.startswith("specguard") else None)
    L.append(f"| {c} | {_f(v)} | {_f(paper)} |")
  L += ["", "## Table 5: SVR under overt and stealthy attacks (ours / paper)", "",
        "| attack | no protection (any viol.) | SpecGuard-PC | SpecGuard-RC |", "|---|---|---|---|"]
  for p, row in ex["table5"].items():
    cells = [f"{_f(row[c])} / {_f(P['table5'][p][c])}" for c in ("no_protection", "specguard_pc", "specguard_rc")]
    L.append(f"| {p} | " + " | ".join(cells) + " |")
  L += ["", "## Fig. 9: all controllers (pooled over sensors; ours, paper in brackets)", "",
        "| controller | " + " | ".join(f"{p} SVR | {p} RSR | {p} collisions" for p in ex["fig9"]) + " |",
        "|---|" + "---|---|---|" * len(ex["fig9"])]
  ctrls = sorted({c for rows in ex["fig9"].values() for c in rows})
  for c in ctrls:
    cells = []
    for p, rows in ex["fig9"].items():
      v = rows.get(c, {})
      pp = P["fig9"].get(p, {}).get(c)
      cells += [f"{_f(v.get('svr'))} ({_f(pp[0]) if pp else '-'})", f"{_f(v.get('rsr'))} ({_f(pp[1]) if pp else '-'})",
                _f(v.get("collision"))]
    L.append(f"| {c} | " + " | ".join(cells) + " |")
  L += ["", "Shape against the paper:", ""] + [f"- {s}" for s in ex["shape"]] + [""]
  if "fig10" in ex:
    L += [f"## Fig. 10: {ex['fig10']['controller']} per attacked sensor (paper: SVR <= 3.33 %, baro 0 %, "
          f"MD 3.2-6.88 %)", "", "| setting | SVR | MD |", "|---|---|---|"]
    for s, v in ex["fig10"]["per_setting"].items():
      L.append(f"| {s} | {_f(v['svr'])} | {_f(v['md'])} |")
    L.append("")
  if ex["ablation"]:
    L += ["## Fig. 12: ablations (all attacks pooled; paper overt: SpecGuard 13.5 / 92.1, without the recovery "
          "policy (= DeLorean) 60.4 / 45.8, without state reconstruction 67.9 / ~46)", "",
          "| controller | SVR | RSR | collisions |", "|---|---|---|---|"]
    for c, v in ex["ablation"].items():
      L.append(f"| {c} | {_f(v['svr'])} | {_f(v['rsr'])} | {_f(v['collision'])} |")
    L.append("")
  if ex["multi"]:
    L += [f"## Multi-sensor attacks (paper: SpecGuard {P['multi']} % SVR on GPS + gyroscope)", "",
          "| setting | controller | SVR | RSR |", "|---|---|---|---|"]
    for s, rows in ex["multi"].items():
      for c, v in rows.items():
        L.append(f"| {s} | {c} | {_f(v['svr'])} | {_f(v['rsr'])} |")
    L.append("")
  for g, rows in ex["unseen"].items():
    if not rows:
      continue
    pp = P["unseen"][g]
    L += [f"## Unseen worlds: {g} (paper SVR overt {pp[0]} %, stealthy {pp[1]} %)", "",
          "| controller | " + " | ".join(f"{p} SVR" for p in rep["meta"]["profiles"]) + " |",
          "|---|" + "---|" * len(rep["meta"]["profiles"])]
    for c, v in rows.items():
      L.append(f"| {c} | " + " | ".join(_f(v.get(p)) for p in rep["meta"]["profiles"]) + " |")
    L.append("")
  if ex["rover"]:
    r = P["rover_real"]
    L += [f"## Rover (paper, real Aion rover: SVR {r['svr']} %, RSR {r['rsr']} %, MD {r['md']} %)", "",
          "| controller | SVR | RSR | MD |", "|---|---|---|---|"]
    for c, v in ex["rover"].items():
      L.append(f"| {c} | {_f(v['svr'])} | {_f(v['rsr'])} | {_f(v['md'])} |")
    L.append("")
  L += [f"## Time to recovery and detection ({P['t2r']})", "",
        f"T2R: from detection until every spec held again for {M.RECOVERY_HOLD_S:g} s, over the detected missions "
        "that were non-compliant after detection ('needed recovery').", "",
        "| controller | profile | T2R mean [95 % CI] s | T2R median s | needed recovery | recovered (T2R finite) | "
        "detected | detection delay s |", "|---|---|---|---|---|---|---|---|"]
  main = rep["groups"].get("main", {}).get("metrics", {})
  for c, rows in main.items():
    for p in rep["meta"]["profiles"]:
      v = rows.get(f"pooled/{p}")
      if not v:
        continue
      t = v.get("t2r_stats")
      d = v.get("detection_delay")
      L.append(f"| {c} | {p} | {_f(t['mean']) + ' [' + _f(t['ci'][0]) + ', ' + _f(t['ci'][1]) + ']' if t else 'n/a'}"
               f" | {_f(t['median']) if t else 'n/a'} | {_ci(v.get('t2r_applicable'))}"
               f" | {_ci(v.get('t2r_recovered'))} | {_ci(v.get('detect_rate'))}"
               f" | {_f(d['mean'], 2) if d else 'n/a'} |")
  L += ["", "## Every setting (main group)", "",
        "| controller | setting | missions | SVR [CI] | any viol. [CI] | RSR [CI] | MD % | collisions | critical |",
        "|---|---|---|---|---|---|---|---|---|"]
  for c, rows in main.items():
    for s, v in rows.items():
      L.append(f"| {c} | {s} | {v['missions']} | {_ci(v['svr_rate'])} | {_ci(v.get('any_violation_rate'))} | "
               f"{_ci(v['rsr_rate'])} | {_f(v['md'])} | {_f(_pct(v['collision_rate']))} | "
               f"{_f(_pct(v['critical_rate']['value']))} |")
  L += paired_markdown(rep)
  L += policy_effect_markdown(rep)
  L += false_alarm_markdown(rep)
  if rep.get("figures"):   # the files write() made (none with --no-figures; no trajectories after --merge)
    L += ["", f"Figures: {', '.join(rep['figures'])}.", ""]
  return "\n".join(L)


# The hard suite's goal for a SpecGuard policy: fewer SVR events and fewer critical-spec violations than each
# reference with a paired p below GOAL_ALPHA, on every attacked campaign, while its RSR is no lower.
GOAL_REFERENCES = ("delorean", "fallback")
GOAL_ALPHA = 0.01


def hard_goal(rep, table, group="main") -> list:
  """Per SpecGuard controller, reference (GOAL_REFERENCES present) and attacked campaign of `table` (hard_table; not
  attack_free, not redteam, whose attacks differ per controller): McNemar on the campaign's missions pooled (the
  settings' discordant pairs summed, metrics.mcnemar_counts) for the SVR event and critical violations, both RSRs,
  and whether the SpecGuard controller beats the reference there: fewer of both (p < GOAL_ALPHA) and an RSR whose
  95 % interval reaches the reference's. [] without a SpecGuard controller, a reference or the paired tests."""
  g = rep["groups"].get(group, {})
  paired, ctrls = g.get("paired") or {}, list(g.get("metrics") or {})
  camps = [k for k in (table or {}) if k not in ("attack_free", "redteam")]
  out = []
  for sg in (c for c in ctrls if c.startswith("specguard")):
    for ref in (r for r in GOAL_REFERENCES if r in ctrls):
      for camp in camps:
        sums = {"svr": [0, 0, 0], "critical": [0, 0, 0]}
        for setting, tests in paired.items():
          if setting.split("/")[0] != camp:
            continue
          flip = f"{sg} vs {ref}" not in tests     # the pair named the other way round: swap b and c
          t = tests.get(f"{ref} vs {sg}" if flip else f"{sg} vs {ref}")
          for k, acc in sums.items():
            if t and k in t:
              acc[0] += t[k]["c" if flip else "b"]
              acc[1] += t[k]["b" if flip else "c"]
              acc[2] += t[k]["n"]
        if not sums["svr"][2]:
          continue
        tests = {k: M.mcnemar_counts(*v) for k, v in sums.items()}
        me, them = table[camp][sg]["rsr"], table[camp][ref]["rsr"]
        fewer = all(t["b"] < t["c"] and t["p"] < GOAL_ALPHA for t in tests.values())
        rsr_ok = bool(me and them and me["ci"][1] >= them["value"])
        out.append({"controller": sg, "reference": ref, "campaign": camp, **tests,
                    "rsr": [me and me["value"], them and them["value"]], "beats": bool(fewer and rsr_ok)})
  return out


def hard_goal_markdown(rows) -> list:
  """Lines of the goal's table and one plain sentence per SpecGuard controller (`hard_goal`); [] without rows."""
  if not rows:
    return []
  L = ["## The goal: does SpecGuard beat DeLorean and the fallback?", "",
       f"A SpecGuard controller beats a reference on a campaign when it has fewer SVR events (over the missions no "
       f"protection violated) and fewer critical-spec violations, each by McNemar's exact test on the campaign's "
       f"missions with p < {GOAL_ALPHA}, and its RSR's 95 % interval reaches the reference's RSR. Discordant pairs: "
       f"missions where only SpecGuard violated vs only the reference.", "",
       "| controller | reference | campaign | SVR: discordant, p | critical: discordant, p | RSR % | beats |",
       "|---|---|---|---|---|---|---|"]
  pct = lambda x: "n/a" if x is None else f"{100 * x:.1f}"  # noqa: E731
  for r in rows:
    L.append(f"| {r['controller']} | {r['reference']} | {r['campaign']} | {r['svr']['b']} vs {r['svr']['c']}, "
             f"{r['svr']['p']:.2g} | {r['critical']['b']} vs {r['critical']['c']}, {r['critical']['p']:.2g} | "
             f"{pct(r['rsr'][0])} vs {pct(r['rsr'][1])} | {'yes' if r['beats'] else '**no**'} |")
  L.append("")
  for sg in dict.fromkeys(r["controller"] for r in rows):
    mine = [r for r in rows if r["controller"] == sg]
    won = sum(r["beats"] for r in mine)
    verdict = "beats" if won == len(mine) else "does NOT beat"
    L.append(f"- {sg} {verdict} {' and '.join(dict.fromkeys(r['reference'] for r in mine))} on every attacked "
             f"campaign: it wins {won} of {len(mine)} comparisons.")
  return L + [""]


def hard_markdown(table) -> list:
  """Lines of the hard suite's table (`hard_table`); [] when no campaign was flown."""
  if not table:
    return []
  L = ["## Hard suite: SVR, critical-spec violations, RSR and MD per controller and campaign", "",
       "Campaign rows pool the campaign's settings (evaluation.campaign_settings); % with 95 % intervals (Wilson for "
       "rates, Student t for MD); n = missions. No protection's SVR is the share of its missions with any violation; "
       "the others' is over the missions no protection violated. Attack-free and redteam (each controller against "
       "its own trained attack agent, so no twin): SVR = any violation.", "",
       "| campaign | controller | n | SVR % | critical % | RSR % | MD % |", "|---|---|---|---|---|---|---|"]

  def cell(r):
    if not r or r.get("value") is None:
      return "n/a"
    return f"{100 * r['value']:.1f} [{100 * r['ci'][0]:.1f}, {100 * r['ci'][1]:.1f}]"

  for camp, row in table.items():
    for c, v in row.items():
      md = v.get("md")
      md_s = f"{md['mean']:.1f} [{md['ci'][0]:.1f}, {md['ci'][1]:.1f}]" if md else "n/a"
      L.append(f"| {camp} | {c} | {v['missions']} | {cell(v['svr'])} | {cell(v['critical'])} | {cell(v['rsr'])} | "
               f"{md_s} |")
  return L + [""]


def violation_timing_markdown(rep, group="main") -> list:
  """Lines of the table of where each hard campaign's violations happen against the alarm (metrics.violation_timing,
  over the campaign's settings pooled); [] when no campaign was flown."""
  rows = []
  for c, by_setting in rep["groups"].get(group, {}).get("metrics", {}).items():
    for k in sorted(k for k in by_setting if k.startswith("campaign/")):
      vt = by_setting[k].get("violation_timing")
      if not vt or not vt["alarm_window"]["n"]:
        continue
      cells = " | ".join(_ci(vt[x], with_n=False) for x in ("undetected", "outside", "alarm_window"))
      rows.append(f"| {k[9:]} | {c} | {vt['alarm_window']['n']} | {cells} |")
  if not rows:
    return []
  return ["## Where the violations happen: before the alarm, or while it is up", "",
          "Attacked missions that violated (a spec, a crash or a collision), split: no alarm after the onset "
          "(undetected); an alarm, but every spec compliant from it to the attack's end (the violation came before the "
          "alarm or after the attack: outside); some spec non-compliant between the alarm and the attack's end (alarm "
          "window, up to the attack's end). A reactive (RC) policy is in control only while the alarm is up: it meets "
          "the failures of the alarm-window share; the others it can change only after the attack's end, if at all. "
          "% [95 % interval].", "",
          "| campaign | controller | violating missions | undetected % | outside % | alarm window % |",
          "|---|---|---|---|---|---|"] + rows + [""]


def blind_markdown(rep, group="main") -> list:
  """Lines of the table of the critical violations the estimate never showed (metrics.blind), per hard campaign
  and controller over the campaign's settings pooled; [] when no campaign was flown or records lack 'seen'."""
  rows, specs = [], None
  for c, by_setting in rep["groups"].get(group, {}).get("metrics", {}).items():
    for k in sorted(k for k in by_setting if k.startswith("campaign/")):
      m = by_setting[k]
      if "blind_critical_rate" not in m or not m["blind_critical_rate"]["n"]:
        continue
      specs = specs or list(m["blind_spec"])
      cells = " | ".join(_ci(m["blind_spec"][x], with_n=False) for x in specs)
      rows.append(f"| {k[9:]} | {c} | {m['blind_critical_rate']['n']} | "
                  f"{_ci(m['blind_critical_rate'], with_n=False)} | {cells} |")
  if not rows:
    return []
  return ["## Critical violations the estimate never showed", "",
          "Missions violating a critical spec, and the share of them (blind) where the violated spec's condition "
          "held at every step on the signals computed from the estimate the policy observes (env.believed_signals: "
          "the reconstruction's or the EKF's position and velocity against the same map): the estimate showed the "
          "spec holding throughout, so its spec signals gave no warning; only the alarm, the estimate's uncertainty "
          "or the policy's range ring (true geometry, S1) could. A lower bound (metrics.blind). Per spec: among the "
          "missions violating it. % [95 % interval].", "",
          "| campaign | controller | critical-violating missions | blind % | " + " | ".join(
              f"{x} blind %" for x in specs) + " |", "|---|---|---|---|" + "---|" * len(specs)] + rows + [""]


def redteam_markdown(log) -> list:
  """Lines of the red-team campaign's summary (`redteam_log`); [] when none was flown."""
  if not log:
    return []
  L = ["## Red-team campaign: what each controller's attack agent chose", "",
       "Each controller against its own best-response attack agent (specguard_jax.ppo.redteam; per-mission sensors, "
       "onsets and durations in report.json 'redteam', figures/redteam.png). Sensors: the sets spoofed together, "
       "with their missions; a duration ends at the episode's end, so a crash during the attack cuts it short.", "",
       "| controller | agent | missions | attacked % | sensors | onset s (median) | duration s (median) | "
       "any violation % | crash % |", "|---|---|---|---|---|---|---|---|---|"]
  for c, v in log.items():
    s, a = v["summary"], v.get("agent") or {}
    how = ("trained here" if a.get("trained") else "loaded") + (f" ({a['train_s']:.0f} s)" if a.get("train_s") else "")
    med = lambda x: f"{x['median']:.1f}" if x else "n/a"  # noqa: E731
    sens = ", ".join(f"{k} {n}" for k, n in s["combinations"].items()) or "none"
    L.append(f"| {c} | {how} | {s['missions']} | {100 * s['attacked']:.0f} | {sens} | {med(s['onset_s'])} | "
             f"{med(s['duration_s'])} | {100 * s['any_violation']:.1f} | {100 * s['crash']:.1f} |")
  return L + ["", redteam_verdict(log), ""]


def redteam_verdict(log: dict) -> str:
  """One plain line: the controller that fared best against its own red team, and whether any kept most of its
  missions free of violations (the red team is a best response: what it finds is what a controller leaves open)."""
  rates = {c: v["summary"]["any_violation"] for c, v in log.items()}
  best = min(rates, key=rates.get)
  crashes = [v["summary"]["crash"] for v in log.values()]
  line = (f"Verdict: against its own red team the best controller is {best} with {100 * rates[best]:.1f} % of "
          f"missions violating (worst: {100 * max(rates.values()):.1f} %); crashes "
          f"{100 * min(crashes):.1f}-{100 * max(crashes):.1f} %")
  held = [c for c, r in rates.items() if r < 0.5]
  return line + (". No controller keeps more than half of its missions compliant." if not held else
                 f". Kept most missions compliant: {', '.join(held)}.")


KEY_OPPONENTS = ("no_protection", "delorean")


def _pair(pairs, a, b):
  """The test of a vs b whichever order the report stored it in, as (test, swapped)."""
  if f"{a} vs {b}" in pairs:
    return pairs[f"{a} vs {b}"], False
  return pairs.get(f"{b} vs {a}"), True


def _mc(t, swapped):
  """'b/c p' of one McNemar test, b counted for the row's controller."""
  if not t:
    return "n/a"
  b, c = (t["c"], t["b"]) if swapped else (t["b"], t["c"])
  return f"{b}/{c} p={t['p']:.2g}"


def paired_markdown(rep, group="main") -> list:
  """Each controller against no protection and DeLorean per setting (all pairs in report.json)."""
  paired = rep["groups"].get(group, {}).get("paired") or {}
  ctrls = list(rep["groups"].get(group, {}).get("metrics", {}))
  rows = []
  for s, pairs in paired.items():
    for opp in KEY_OPPONENTS:
      if opp not in ctrls:
        continue
      for c in ctrls:
        if c == opp or (opp == "delorean" and c == "no_protection"):
          continue
        t, sw = _pair(pairs, c, opp)
        if t:
          rows.append(f"| {s} | {c} vs {opp} | {_mc(t.get('svr'), sw)} | {_mc(t['any_violation'], sw)} | "
                      f"{_mc(t['critical'], sw)} |")
  if not rows:
    return []
  return ["", f"## Paired comparisons ({group} group): McNemar's exact test on the same missions", "",
          "b/c = missions where the first controller violated and the second did not / the reverse; p = two-sided "
          "exact p-value (binomial test of b against Bin(b + c, 1/2)). SVR: over the missions whose no-protection "
          "twin violated; any / critical violation: over all missions of the setting.", "",
          "| setting | pair | SVR b/c p | any violation b/c p | critical b/c p |", "|---|---|---|---|---|"] + rows


def false_alarm_markdown(rep) -> list:
  """The false-alarm group (evaluate.py --false-alarms): attack-free missions under a forced alarm, per controller."""
  fa = rep["groups"].get("false_alarm", {}).get("metrics", {})
  if not fa:
    return []
  L = ["", "## Forced false alarms: attack-free missions with the alarm raised (zero-bias attack, oracle detector)", "",
       "What a false alarm costs: the reconstruction drops a good sensor, an RC policy takes control. No protection "
       "flies the same missions without any alarm.", "",
       "| controller | setting | missions | any viol. [CI] | critical % | RSR [CI] | MD % | in control % |",
       "|---|---|---|---|---|---|---|---|"]
  for c, rows in fa.items():
    for s, v in rows.items():
      L.append(f"| {c} | {s} | {v['missions']} | {_ci(v.get('any_violation_rate'))} | "
               f"{_f(_pct(v['critical_rate']['value']))} | {_ci(v['rsr_rate'])} | {_f(v['md'])} | "
               f"{_ci(v.get('control_rate'))} |")
  return L + paired_markdown(rep, group="false_alarm") + policy_effect_markdown(rep, group="false_alarm")


def policy_effect_markdown(rep, group="main") -> list:
  """Per learned controller (a policy whose setpoint is not always zero) and setting: the share of missions in which
  it was in control, and the size of its setpoint over the steps it was (metrics.summarize's action_* stats)."""
  rows = []
  for c, by_setting in rep["groups"].get(group, {}).get("metrics", {}).items():
    for s, v in by_setting.items():
      mean, mx = v.get("action_mean_stats"), v.get("action_max_stats")
      if not mean or (mx and mx["mean"] == 0.0):
        continue
      rows.append(f"| {c} | {s} | {_ci(v['control_rate'])} | {mean['mean']:.2f} [{mean['ci'][0]:.2f}, "
                  f"{mean['ci'][1]:.2f}] | {mx['mean']:.2f} | {mx['n']} |")
  if not rows:
    return []
  return ["", f"## The policy's effect ({group} group)", "",
          "In control % = missions in which the policy's setpoint reached the vehicle at least one step; setpoint size "
          "= the norm of its velocity setpoint (m/s; for a residual policy, the correction) averaged over the steps it "
          "was in control, per mission, then over missions [95 % interval]; max = the mean over missions of the "
          "largest. The paired tests above say whether it changed the outcome.", "",
          "| controller | setting | in control % | setpoint size m/s | max m/s | n |",
          "|---|---|---|---|---|---|"] + rows


# ------------------------------------------------------------------------------------------------- figures


def _pick_traj(rep, trajs, records, sg, prefer=("gps/overt", "gps/stealthy")):
  """(setting, traj slot) of a recorded mission under attack: one that no protection violated and SpecGuard did not
  when there is one."""
  tn, ts = trajs.get(("main", "no_protection")), trajs.get(("main", sg))
  if tn is None or ts is None:
    return None
  settings = rep["groups"]["main"]["settings"]
  cands = [s for s in prefer if s in settings] + [s for s in settings if s != "attack_free" and s not in prefer]
  if not cands:
    return None
  vn, vs = M.violation(records[("main", "no_protection")]), M.violation(records[("main", sg)])
  for s in cands:
    slots = np.where(tn["setting"] == settings.index(s))[0]
    for k in slots:
      row = tn["index"][k]
      if vn[row] and not vs[row]:
        return s, int(k)
  s = cands[0]
  slots = np.where(tn["setting"] == settings.index(s))[0]
  return (s, int(slots[0])) if len(slots) else None


def make_figures(out_dir: str, rep: dict, records: dict, trajs: dict) -> list:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  os.makedirs(out_dir, exist_ok=True)
  written = []

  def save(fig, name):
    path = os.path.join(out_dir, name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)

  ex = rep["experiments"]
  main = rep["groups"].get("main", {}).get("metrics", {})
  sg = primary_specguard(rep) or next((c for c in main if c != "no_protection"), None)
  # comparison bars
  if ex.get("fig9"):
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ctrls = sorted({c for rows in ex["fig9"].values() for c in rows})
    w = 0.8 / max(len(ex["fig9"]), 1)
    for j, (p, rows) in enumerate(ex["fig9"].items()):
      for ax, key in zip(axes, ("svr", "rsr")):
        vals = [rows.get(c, {}).get(key) or 0.0 for c in ctrls]
        ax.bar(np.arange(len(ctrls)) + j * w, vals, w, label=p)
    for ax, key in zip(axes, ("SVR %", "RSR %")):
      ax.set_xticks(np.arange(len(ctrls)) + w / 2, ctrls, rotation=30, ha="right")
      ax.set_ylabel(key)
      ax.set_ylim(0, 105)
      ax.legend()
    axes[0].set_title("Specification violation rate (lower is better)")
    axes[1].set_title("Recovery success rate (higher is better)")
    save(fig, "comparison.png")
  # per-sensor SVR and MD
  if ex.get("fig10"):
    per = ex["fig10"]["per_setting"]
    names = list(per)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].bar(names, [per[s]["svr"] or 0 for s in names])
    axes[0].set_ylabel("SVR %")
    axes[1].bar(names, [per[s]["md"] if per[s]["md"] is not None else 0 for s in names])
    axes[1].set_ylabel("mission delay %")
    for ax in axes:
      ax.tick_params(axis="x", rotation=45)
    axes[0].set_title(f"{ex['fig10']['controller']}: SVR per attacked sensor")
    axes[1].set_title("MD per attacked sensor")
    save(fig, "per_sensor.png")
  # per-spec heat map
  rows, labels, specs = [], [], None
  for c, v in main.items():
    for p in rep["meta"]["profiles"]:
      s = v.get(f"pooled/{p}")
      if s and s.get("spec_rate"):
        specs = list(s["spec_rate"])
        rows.append([100 * (s["spec_rate"][k] or 0) for k in specs])
        labels.append(f"{c} ({p})")
  if rows:
    fig, ax = plt.subplots(figsize=(1.0 + 0.7 * len(specs), 1.0 + 0.45 * len(rows)))
    im = ax.imshow(np.asarray(rows), cmap="Reds", vmin=0, vmax=100, aspect="auto")
    ax.set_xticks(range(len(specs)), specs)
    ax.set_yticks(range(len(labels)), labels)
    for i, r in enumerate(rows):
      for j, x in enumerate(r):
        ax.text(j, i, f"{x:.0f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=ax, label="missions violating the spec %")
    ax.set_title("Violations per specification")
    save(fig, "svr_heatmap.png")
  # T2R CDF
  fig, ax = plt.subplots(figsize=(6, 4))
  any_line = False
  for (g, c), rec in records.items():
    if g != "main":
      continue
    dt = rep["groups"]["main"]["env"]["dt"]
    for p in rep["meta"]["profiles"]:
      settings = rep["groups"]["main"]["settings"]
      ids = [i for i, s in enumerate(settings) if _single(s) and _profile(s) == p]
      r = M.select(rec, np.isin(rec["setting"], ids))
      t = M.t2r(r, dt)
      app = ~np.isnan(t)
      if not app.any():
        continue
      fin = np.sort(t[np.isfinite(t)])
      y = np.arange(1, len(fin) + 1) / app.sum()
      ax.step(np.concatenate([[0.0], fin]), np.concatenate([[0.0], y]), where="post", label=f"{c} ({p})")
      any_line = True
  ax.set_xlabel("time to recovery after detection (s)")
  ax.set_ylabel("CDF (unrecovered missions keep it below 1)")
  ax.set_ylim(0, 1.02)
  ax.set_title("Time to recovery (T2R)")
  if any_line:
    ax.legend(fontsize=7)
  else:
    ax.text(0.5, 0.5, "no detected attacks", ha="center", transform=ax.transAxes)
  save(fig, "t2r_cdf.png")
  # trajectory and altitude/yaw
  pick = _pick_traj(rep, trajs, records, sg) if sg else None
  if pick:
    s, k = pick
    tn, ts = trajs[("main", "no_protection")], trajs[("main", sg)]
    row = tn["index"][k]
    onset, end = records[("main", "no_protection")]["onset"][row], records[("main", "no_protection")]["attack_end"][row]
    fig, ax = plt.subplots(figsize=(6.5, 6))
    wp = tn["waypoints"][k][: int(tn["n_waypoints"][k])]
    ax.plot(wp[:, 0], wp[:, 1], "k--o", ms=4, lw=0.8, label="mission waypoints")
    for tr, lab, col in ((tn, "no protection", "tab:red"), (ts, sg, "tab:green")):
      x = _valid(tr["rows"][:, k])
      ax.plot(x[:, 0], x[:, 1], color=col, label=f"{lab} (true)")
      att = (x[:, 11] >= onset) & (x[:, 11] <= end)
      ax.plot(x[att, 0], x[att, 1], color=col, lw=3, alpha=0.4)
    x = _valid(tn["rows"][:, k])
    ax.plot(x[:, 3], x[:, 4], color="tab:red", ls=":", label="no protection (EKF estimate)")
    ax.set_aspect("equal", "datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Mission under attack ({s}; thick: attack window)")
    ax.legend(fontsize=7)
    save(fig, "trajectory.png")
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=False)
    yaw_pick = None
    settings = rep["groups"]["main"]["settings"]
    for cand in ("gyro/overt", "mag/overt", "gyro/stealthy"):
      if cand in settings:
        slots = np.where(tn["setting"] == settings.index(cand))[0]
        if len(slots):
          yaw_pick = (cand, int(slots[0]))
          break
    panels = [(axes[0], s, k, 8, "altitude (m)")] + ([(axes[1], yaw_pick[0], yaw_pick[1], 6, "yaw (deg)")]
                                                     if yaw_pick else [(axes[1], s, k, 6, "yaw (deg)")])
    for ax, sname, kk, col_i, ylab in panels:
      rr = tn["index"][kk]
      on, en = records[("main", "no_protection")]["onset"][rr], records[("main", "no_protection")]["attack_end"][rr]
      for tr, lab, col in ((tn, "no protection", "tab:red"), (ts, sg, "tab:green")):
        x = _valid(tr["rows"][:, kk])
        y = np.degrees(np.unwrap(x[:, col_i])) if col_i == 6 else x[:, col_i]
        ax.plot(x[:, 11], y, color=col, label=lab)
      ax.axvspan(on, en, color="orange", alpha=0.2, label="attack")
      ax.set_ylabel(ylab)
      ax.set_title(sname)
      ax.legend(fontsize=7)
    axes[1].set_xlabel("time (s)")
    save(fig, "altitude_yaw.png")
  if rep.get("redteam"):
    save(redteam_figure(rep["redteam"], plt), "redteam.png")
  return written


def redteam_figure(log: dict, plt):
  """The red-team agents' choices per controller: missions spoofing each sensor (bars; a two-sensor attack counts for
  both) and each attacked mission's onset vs
  duration (red: a spec violated or a crash, grey: none)."""
  from specguard_jax.types import SENSOR_NAMES
  ctrls = list(log)
  fig, axes = plt.subplots(1, 2, figsize=(11, 4))
  w = 0.8 / max(len(ctrls), 1)
  for j, c in enumerate(ctrls):
    counts = [log[c]["summary"]["sensors"].get(n, 0) for n in SENSOR_NAMES]   # missions spoofing it
    axes[0].bar(np.arange(len(SENSOR_NAMES)) + j * w, counts, w, label=c)
    rows = [m for m in log[c]["missions"] if m["sensor"] is not None]
    for viol in (False, True):
      pts = [(m["onset_s"], m["duration_s"]) for m in rows if m["violated"] == viol]
      if pts:
        x, y = np.asarray(pts).T
        axes[1].scatter(x, y, s=14, marker="os^vDP"[j % 6], color="tab:red" if viol else "tab:gray",
                        alpha=0.7, label=f"{c}, {'violated' if viol else 'no violation'}")
  axes[0].set_xticks(np.arange(len(SENSOR_NAMES)) + w * (len(ctrls) - 1) / 2, SENSOR_NAMES)
  axes[0].set_ylabel("missions")
  axes[0].set_title("Red-team agent: sensors spoofed")
  axes[0].legend(fontsize=7)
  axes[1].set_xlabel("onset (s)")
  axes[1].set_ylabel("duration (s)")
  axes[1].set_title("Red-team agent: onset and duration per mission")
  axes[1].legend(fontsize=7)
  return fig


def _valid(x):
  """Trajectory rows up to the end of the episode (time stops increasing once done)."""
  t = x[:, 11]
  keep = np.concatenate([[True], np.diff(t) > 0])
  return x[keep]


def write(out_dir: str, rep: dict, records: dict, trajs: dict, figures: bool = True) -> None:
  """report.json, report.md, records/*.npz and figures/*.png under out_dir."""
  os.makedirs(os.path.join(out_dir, "records"), exist_ok=True)
  for (g, c), rec in records.items():
    np.savez_compressed(os.path.join(out_dir, "records", f"{g}__{c}.npz"), **rec)
  if figures:
    rep["figures"] = [os.path.relpath(p, out_dir)
                      for p in make_figures(os.path.join(out_dir, "figures"), rep, records, trajs)]
  with open(os.path.join(out_dir, "report.json"), "w") as f:
    json.dump(jsonable(rep), f, indent=1)
  with open(os.path.join(out_dir, "report.md"), "w") as f:
    f.write(markdown(rep))
