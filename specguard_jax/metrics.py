"""The paper's evaluation metrics (Sec. 5.4) on per-mission records (specguard_jax.evaluation.rollout), pure numpy.

Records are dicts of arrays with one row per mission (keys as evaluation.rollout; tests build them by hand). The
"twin" of a mission is the same mission (plan, world, attack schedule, sensor-noise seed) flown by the autopilot
alone (no protection); "gt" is that mission flown by the autopilot alone without the attack.

Definitions (what we chose where the paper leaves room):
  violation       any spec's whole-episode robustness < 0, or a crash / collision / NaN end (a mission that ends
                  in the ground has failed its specs even if the monitor had no time to see it).
  svr             the paper's SVR = observed / intended violations. Intended: the attack was meant to cause a
                  violation, operationalised as "the no-protection twin had a violation". svr = share of violating
                  missions among those whose twin violated. Attack-free settings count any violation over all
                  missions (svr = svr_all). svr_all = share of violating missions over all missions.
  svr_spec[k]     per-spec SVR: among missions whose twin violated spec k, the share where spec k was violated too
                  (None where no twin violated k). spec_rate[k]: share of all missions violating spec k.
  critical_rate   share of missions violating any critical spec of the table (S1, S2, S12 by default).
  blind           a violated critical spec whose step condition never failed, at any step, on the signals
                  computed from the estimate the policy observes (record 'seen', env.believed_signals): that
                  estimate showed the spec holding throughout (its margin may still have shrunk). A lower bound on
                  the violations the estimate missed (a spec seen failing once, anywhere, is not blind).
                  blind_critical_rate: the share of the missions violating a critical spec with such a violation;
                  blind_spec[k]: among the missions violating critical spec k, the share blind. A controller can
                  still avoid them through what else it sees (the alarm, the estimate's uncertainty, the policy's
                  range ring of the true geometry for S1), not through the spec signals of its estimate.
  rsr             recovered / missions: recovered = nav completed the mission AND the true final position is within
                  5 m of the last waypoint (horizontal for landing missions and the rover) AND no crash, collision,
                  stall or NaN. Over all missions of an attacked setting (missions under attack); for attack-free
                  settings the same formula is the success rate.
  md              mission delay, per mission (T_SG - T_GT) / T_b x 100, over missions completed by both the
                  controller and its gt twin; T_GT = the gt twin's completion time; T_b = (T_min + T_max) / 2 of
                  the completion times of all completed gt twins of the evaluation (the paper's "average of the
                  minimum and maximum mission completion times in attack free missions"). md_rel: the same with
                  T_b = T_GT of each mission (a per-mission relative delay, for reference).
  any_violation   share of missions under attack (the attack became active before the mission ended) with any
                  violation; attack-free settings: over all missions. No protection's SVR is 100 % by construction
                  (it is its own twin): this is the figure to quote for it (and it is defined for every controller).
  t2r             time to recovery (s), over the attacked missions whose attack was detected (first alarm at or after
                  the onset, t_d) AND that were non-compliant after detection (some spec's instantaneous compliance
                  failed at a step in [t_d, attack end]: the first such step is bad_t); the others have nothing to
                  recover from (t2r_applicable says how many there were). Recovery is the first instant after bad_t
                  from which every spec stayed instantaneously compliant for RECOVERY_HOLD_S s (rec_t: the first
                  compliant step of that run), or from which the mission stayed compliant until it completed;
                  T2R = t_r - t_d. A mission that never got back (non-compliant run to its end, or a crash /
                  collision / NaN end) never recovered (T2R = inf: the CDF stays below 1).
  paired tests    controllers fly the same missions (evaluation.py), so two controllers on one setting are compared
                  per mission: McNemar's exact test on the discordant pairs (b: A violated and B did not, c: the
                  reverse), two-sided binomial test of b against Bin(b + c, 1/2); on the SVR's event (any violation,
                  over the missions whose twin violated), on any violation over all missions, and on critical-spec
                  violations over all missions.
  detection       detect_rate: attacked missions with an alarm at or after the onset; delay = t_d - onset (s);
                  false_alarm_rate: an alarm before the onset (attack-free: any alarm).
Confidence intervals: Wilson score intervals (95 %) for proportions, Student-t intervals (95 %) for means.
"""

from __future__ import annotations

import math

import numpy as np

RSR_RADIUS_M = 5.0
RECOVERY_HOLD_S = 3.0   # s: how long every spec must hold again for a recovery to count (T2R); the specs' own grace
                        # (SG_ACCEL_TIME, 3 s) for the speed bounds, so a recovery is not a momentary pass
BIG = 1e9
Z95 = 1.959963984540054


def select(rec: dict, mask) -> dict:
  """Rows of a record dict where mask is True."""
  mask = np.asarray(mask, bool)
  return {k: np.asarray(v)[mask] for k, v in rec.items()}


def concat(recs) -> dict:
  recs = list(recs)
  return {k: np.concatenate([np.asarray(r[k]) for r in recs], 0) for k in recs[0]}


def _b(r, k):
  return np.asarray(r[k], bool)


def violation(r) -> np.ndarray:
  """[n] bool: any spec violated, or a crash / collision / NaN end."""
  v = np.any(_b(r, "violated"), axis=-1)
  for k in ("crash", "collision", "nan"):
    if k in r:
      v = v | _b(r, k)
  return v


def recovered(r, radius: float = RSR_RADIUS_M) -> np.ndarray:
  """[n] bool: completed, final true position within `radius` m of the last waypoint, no crash/collision/stall/NaN."""
  ok = _b(r, "complete") & (np.asarray(r["final_dist"], float) <= radius)
  for k in ("crash", "collision", "stall", "nan"):
    if k in r:
      ok = ok & ~_b(r, k)
  return ok


def wilson(k, n, z: float = Z95) -> tuple:
  """Wilson score interval (lo, hi) of k successes in n trials; (nan, nan) when n == 0."""
  k, n = float(k), float(n)
  if n <= 0:
    return (math.nan, math.nan)
  p = k / n
  den = 1.0 + z * z / n
  c = (p + z * z / (2 * n)) / den
  h = z * math.sqrt(max(p * (1 - p) / n + z * z / (4 * n * n), 0.0)) / den
  lo, hi = max(0.0, c - h), min(1.0, c + h)
  return (0.0 if k == 0 else lo, 1.0 if k == n else hi)   # exact ends (no rounding past p)


def mean_ci(x, conf: float = 0.95) -> tuple:
  """(mean, lo, hi) with a Student-t interval; nan for no data, (m, m, m) for one value."""
  x = np.asarray(x, float)
  x = x[np.isfinite(x)]
  if len(x) == 0:
    return (math.nan, math.nan, math.nan)
  m = float(np.mean(x))
  if len(x) == 1:
    return (m, m, m)
  from scipy import stats
  h = float(stats.t.ppf(0.5 + conf / 2, len(x) - 1) * np.std(x, ddof=1) / math.sqrt(len(x)))
  return (m, m - h, m + h)


def rate(mask, among=None) -> dict:
  """{'value', 'ci', 'k', 'n'} of a boolean [n] (restricted to `among`)."""
  mask = np.asarray(mask, bool)
  if among is not None:
    mask = mask[np.asarray(among, bool)]
  k, n = int(mask.sum()), int(mask.size)
  return {"value": (k / n) if n else None, "ci": list(wilson(k, n)) if n else None, "k": k, "n": n}


def baseline_time(gt) -> float:
  """T_b = (T_min + T_max) / 2 over the completed attack-free (gt) runs; nan when none completed."""
  t = np.asarray(gt["t_end"], float)[_b(gt, "complete")]
  return float((t.min() + t.max()) / 2) if len(t) else math.nan


def mission_delay(r, gt, t_b: float) -> tuple:
  """(md [n] %, md_rel [n] %): nan where the mission or its gt twin did not complete."""
  both = _b(r, "complete") & _b(gt, "complete")
  d = np.asarray(r["t_end"], float) - np.asarray(gt["t_end"], float)
  md = np.where(both, d / t_b * 100.0, np.nan) if np.isfinite(t_b) and t_b > 0 else np.full(d.shape, np.nan)
  t_gt = np.asarray(gt["t_end"], float)
  rel = np.where(both & (t_gt > 0), d / np.maximum(t_gt, 1e-9) * 100.0, np.nan)
  return md, rel


def critical_violation(r, critical) -> np.ndarray:
  """[n] bool: a critical spec (`critical` [S] bool) violated."""
  crit = np.asarray(critical, bool)
  v = _b(r, "violated")
  return np.any(v[:, crit], -1) if crit.any() else np.zeros(v.shape[0], bool)


def blind(r, critical) -> np.ndarray:
  """[n, S] bool: spec k critical and violated, its condition never failed on the estimate's signals (record
  'seen' [n, S], evaluation.rollout)."""
  crit = np.asarray(critical, bool)
  return _b(r, "violated") & ~_b(r, "seen") & crit[None, :]


def t2r(r, dt: float) -> np.ndarray:
  """[n] time to recovery (s): nan where not applicable (not attacked, never detected, or compliant throughout after
  detection), inf where it never recovered (see module docstring). Reads det_t, bad_t, rec_t, ok_since (the first
  step of the compliant run at the mission's end, BIG when its last step was non-compliant) and the end flags."""
  del dt   # the records hold step times: the recovery instant is the first compliant step of the run
  det = np.asarray(r["det_t"], float)
  bad = np.asarray(r["bad_t"], float)
  applicable = _b(r, "attacked") & (det < BIG / 2) & (bad < BIG / 2)
  rec_t = np.asarray(r["rec_t"], float)
  since = np.asarray(r["ok_since"], float)
  ended_ok = _b(r, "complete") & (since < BIG / 2) & (since > bad)
  t_r = np.where(rec_t < BIG / 2, rec_t, np.where(ended_ok, since, np.inf))
  failed = np.zeros(det.shape, bool)
  for k in ("crash", "collision", "nan"):
    if k in r:
      failed = failed | _b(r, k)
  val = np.where(failed, np.inf, np.maximum(t_r - det, 0.0))
  return np.where(applicable, val, np.nan)


def violation_timing(r) -> dict:
  """Where the violations of attacked missions happen against the alarm, each a rate among the attacked missions
  that violated (violation(): a spec, a crash or a collision):
    undetected    no alarm at or after the attack's onset;
    outside       an alarm, but every spec was compliant from it to the attack's end (or the episode's): the
                  violation happened before the alarm or after the attack;
    alarm_window  some spec non-compliant between the alarm and the attack's end (record bad_t, over the specs that
                  carry a reward): where a reactive (RC) policy, in control while the alarm is up, meets the
                  failure; outside this window it can act only on what follows the attack's end."""
  viol = violation(r) & _b(r, "attacked")
  detected = np.asarray(r["det_t"], float) < BIG / 2
  window = detected & (np.asarray(r["bad_t"], float) < BIG / 2)
  return {"undetected": rate(viol & ~detected, viol), "outside": rate(viol & detected & ~window, viol),
          "alarm_window": rate(viol & window, viol)}


def mcnemar(a, b) -> dict:
  """McNemar's exact test of two paired boolean outcomes a, b [n] (e.g. 'violated' for two controllers on the same
  missions): {'b': a and not b, 'c': b and not a, 'n': pairs, 'p': two-sided exact p-value}. Conditional on the
  b + c discordant pairs, b ~ Bin(b + c, 1/2) under the null of equal rates; p = 1 with no discordant pair.
  scipy comes with jax (one of its requirements; mean_ci uses it too)."""
  a, b_ = np.asarray(a, bool), np.asarray(b, bool)
  return mcnemar_counts(int(np.sum(a & ~b_)), int(np.sum(~a & b_)), int(a.size))


def mcnemar_counts(b: int, c: int, n: int) -> dict:
  """`mcnemar`'s dict from its counts: b pairs where only A has the event, c where only B has it, n pairs. Summing
  b and c over disjoint sets of missions (the settings of a campaign) gives the test of the pooled missions."""
  from scipy import stats
  p = float(stats.binomtest(b, b + c, 0.5).pvalue) if b + c else 1.0
  return {"b": int(b), "c": int(c), "n": int(n), "p": p}


def paired(ra, rb, twin=None, *, critical) -> dict:
  """McNemar tests of controller A (records ra) against B (rb) on the same missions in the same order:
  'any_violation' and 'critical' over all missions, 'svr' over the missions whose no-protection twin violated (the
  SVR's denominator; absent without a twin)."""
  for k in ("setting", "mission"):
    if k in ra and k in rb and not np.array_equal(np.asarray(ra[k]), np.asarray(rb[k])):
      raise ValueError(f"records are not paired: their {k!r} columns differ")
  va, vb = violation(ra), violation(rb)
  out = {"any_violation": mcnemar(va, vb),
         "critical": mcnemar(critical_violation(ra, critical), critical_violation(rb, critical))}
  if twin is not None:
    intended = violation(twin)
    out["svr"] = mcnemar(va[intended], vb[intended])
  return out


def _stats(x) -> dict | None:
  x = np.asarray(x, float)
  x = x[np.isfinite(x)]
  if not len(x):
    return None
  m, lo, hi = mean_ci(x)
  return {"mean": m, "ci": [lo, hi], "median": float(np.median(x)), "n": int(len(x))}


def summarize(r, twin=None, gt=None, *, attacked: bool, dt: float, spec_names, critical, t_b: float | None = None,
              per_spec: bool = True) -> dict:
  """Metrics of one controller on one (possibly pooled) setting. twin: the no-protection records of the same
  missions in the same order (None: svr falls back to svr_all and is flagged); gt: their attack-free no-protection
  records (None: no md); t_b: the mission-delay baseline (default baseline_time(gt)). Rates come as
  {'value', 'ci', 'k', 'n'}; the top-level svr/rsr/md/collision_rate are plain numbers (None when undefined)."""
  n = len(np.asarray(r["complete"]))
  viol = violation(r)
  out = {"missions": n, "attacked": attacked}
  out["svr_all_rate"] = rate(viol)
  if attacked and twin is not None:
    intended = violation(twin)
    out["svr_rate"] = rate(viol, intended)
    out["intended"] = int(intended.sum())
  else:
    out["svr_rate"] = dict(out["svr_all_rate"])
    out["intended"] = n if not attacked else None
    if attacked:
      out["svr_note"] = "no no-protection twin: svr = svr_all"
  out["rsr_rate"] = rate(recovered(r))
  out["collision_rate_ci"] = rate(_b(r, "collision"))
  out["crash_rate"] = rate(_b(r, "crash"))
  out["stall_rate"] = rate(_b(r, "stall"))
  out["any_violation_rate"] = rate(viol, _b(r, "attacked")) if attacked else dict(out["svr_all_rate"])
  out["critical_rate"] = rate(critical_violation(r, critical))
  if "seen" in r and np.any(critical):
    bl, v = blind(r, critical), _b(r, "violated")
    out["blind_critical_rate"] = rate(np.any(bl, -1), critical_violation(r, critical))
    out["blind_spec"] = {s: rate(bl[:, i], v[:, i]) for i, s in enumerate(spec_names) if critical[i]}
  if per_spec:
    v = _b(r, "violated")
    out["spec_rate"] = {s: float(np.mean(v[:, i])) if n else None for i, s in enumerate(spec_names)}
    if attacked and twin is not None:
      tv = _b(twin, "violated")
      out["svr_spec"] = {s: (float(np.mean(v[tv[:, i], i])) if tv[:, i].any() else None)
                         for i, s in enumerate(spec_names)}
  if gt is not None:
    tb = baseline_time(gt) if t_b is None else t_b
    md, rel = mission_delay(r, gt, tb)
    out["md_stats"], out["md_rel_stats"], out["t_b"] = _stats(md), _stats(rel), tb
  t = t2r(r, dt)
  app = np.isfinite(t) | np.isinf(t)
  if attacked:
    detected_attacked = _b(r, "attacked") & (np.asarray(r["det_t"], float) < BIG / 2)
    out["t2r_applicable"] = rate(app, detected_attacked)
    out["t2r_recovered"] = rate(np.isfinite(t), app) if app.any() else None
    out["t2r_stats"] = _stats(t)
    fin = np.sort(t[np.isfinite(t)])
    out["t2r_quantiles"] = ({f"p{q}": float(np.percentile(fin, q)) for q in (10, 25, 50, 75, 90)}
                            if len(fin) else None)
    det = np.asarray(r["det_t"], float)
    detected = det < BIG / 2
    out["detect_rate"] = rate(detected, _b(r, "attacked"))
    out["detection_delay"] = _stats(np.where(detected & _b(r, "attacked"), det - np.asarray(r["onset"]), np.nan))
    out["false_alarm_rate"] = rate(np.asarray(r["first_alarm"], float) < np.asarray(r["onset"], float))
    out["violation_timing"] = violation_timing(r)
  else:
    out["false_alarm_rate"] = rate(np.asarray(r["first_alarm"], float) < BIG / 2)
  if "action_sum" in r:   # the policy's effect: its setpoint's size over the steps it was in control
    steps = np.asarray(r["override_s"], float) / dt
    ctl = steps > 0.5
    out["control_rate"] = rate(ctl)
    out["action_mean_stats"] = _stats(np.where(ctl, np.asarray(r["action_sum"], float) / np.maximum(steps, 1.0),
                                               np.nan))
    out["action_max_stats"] = _stats(np.where(ctl, np.asarray(r["action_max"], float), np.nan))
  out["svr"] = out["svr_rate"]["value"]
  out["svr_all"] = out["svr_all_rate"]["value"]
  out["any_violation"] = out["any_violation_rate"]["value"]
  out["rsr"] = out["rsr_rate"]["value"]
  out["collision_rate"] = out["collision_rate_ci"]["value"]
  out["md"] = out["md_stats"]["mean"] if out.get("md_stats") else None
  return out
