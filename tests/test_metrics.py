"""specguard_jax.metrics on constructed per-mission records: the paper's SVR / RSR / MD / T2R definitions."""

import math

import numpy as np
import pytest

from specguard_jax import metrics as M

SPECS = tuple(f"S{i}" for i in range(1, 13))
CRIT = tuple(s in ("S1", "S2", "S12") for s in SPECS)
DT = 0.1


def recs(n, **kw):
  """n clean missions (completed at 100 s, 1 m from the last waypoint, attacked 30-60 s, never alarmed)."""
  r = {"violated": np.zeros((n, len(SPECS)), bool), "complete": np.ones(n, bool), "collision": np.zeros(n, bool),
       "crash": np.zeros(n, bool), "stall": np.zeros(n, bool), "nan": np.zeros(n, bool),
       "attacked": np.ones(n, bool), "t_end": np.full(n, 100.0), "final_dist": np.ones(n),
       "onset": np.full(n, 30.0), "attack_end": np.full(n, 60.0), "first_alarm": np.full(n, M.BIG),
       "det_t": np.full(n, M.BIG), "bad_t": np.full(n, M.BIG), "rec_t": np.full(n, M.BIG),
       "ok_since": np.full(n, 0.1)}
  for k in ("override_s", "action_sum", "action_max"):
    if k in kw:
      r[k] = np.zeros(n)
  if "seen" in kw:
    r["seen"] = np.zeros((n, len(SPECS)), bool)
  for k, v in kw.items():
    r[k] = np.asarray(v, r[k].dtype).reshape(r[k].shape) if np.ndim(v) else np.full(r[k].shape, v, r[k].dtype)
  return r


def summ(r, twin=None, gt=None, attacked=True, **kw):
  return M.summarize(r, twin, gt, attacked=attacked, dt=DT, spec_names=SPECS, critical=CRIT, **kw)


def test_s3_violation_counts_once():
  r = recs(4)
  r["violated"][1, 2] = True   # S3 (minimum altitude) violated in mission 1 only
  s = summ(r, attacked=False)
  assert s["svr"] == pytest.approx(0.25) and s["svr_all"] == pytest.approx(0.25)
  assert s["spec_rate"]["S3"] == pytest.approx(0.25) and sum(s["spec_rate"].values()) == pytest.approx(0.25)
  assert s["critical_rate"]["value"] == 0.0
  r["violated"][1, 0] = True   # + S1 (critical) in the same mission: still one violating mission
  s = summ(r, attacked=False)
  assert s["svr"] == pytest.approx(0.25) and s["critical_rate"]["value"] == pytest.approx(0.25)


def test_rsr_5m_margin_and_failures():
  r = recs(6, final_dist=[4.9, 5.1, 1.0, 1.0, 1.0, 1.0], crash=[0, 0, 1, 0, 0, 0], stall=[0, 0, 0, 1, 0, 0],
           collision=[0, 0, 0, 0, 1, 0], complete=[1, 1, 0, 0, 0, 1])
  assert M.recovered(r).tolist() == [True, False, False, False, False, True]
  s = summ(r)
  assert s["rsr"] == pytest.approx(2 / 6) and s["rsr_rate"]["k"] == 2 and s["rsr_rate"]["n"] == 6
  assert s["collision_rate"] == pytest.approx(1 / 6)
  # a mission the navigator thinks is complete but ends 5.1 m away (spoofed position) is not recovered
  assert not M.recovered(recs(1, final_dist=5.1))[0]


def test_svr_conditions_on_intended_violations():
  twin = recs(10)
  twin["violated"][:4, 2] = True        # the attack meant a violation in missions 0-3 (S3)
  twin["crash"][4] = True               # and in mission 4 (the autopilot alone crashed)
  r = recs(10)
  r["violated"][0, 2] = True            # SpecGuard still violates in mission 0 ...
  r["violated"][7, 5] = True            # ... and in mission 7, whose twin was clean (not an intended violation)
  s = summ(r, twin)
  assert s["intended"] == 5
  assert s["svr"] == pytest.approx(1 / 5) and s["svr_rate"]["k"] == 1 and s["svr_rate"]["n"] == 5
  assert s["svr_all"] == pytest.approx(2 / 10)
  assert s["svr_spec"]["S3"] == pytest.approx(1 / 4) and s["svr_spec"]["S6"] is None
  # no twin: svr falls back to svr_all and says so
  s = summ(r, None)
  assert s["svr"] == pytest.approx(0.2) and "svr_note" in s


def test_mission_delay_known_times():
  gt = recs(3, t_end=[100.0, 120.0, 80.0])       # T_b = (80 + 120) / 2 = 100
  r = recs(3, t_end=[110.0, 126.0, 90.0], complete=[1, 1, 0])
  assert M.baseline_time(gt) == pytest.approx(100.0)
  md, rel = M.mission_delay(r, gt, M.baseline_time(gt))
  assert md[:2] == pytest.approx([10.0, 6.0]) and np.isnan(md[2])
  assert rel[:2] == pytest.approx([10.0, 5.0])
  s = summ(r, recs(3), gt)
  assert s["md"] == pytest.approx(8.0) and s["md_stats"]["n"] == 2 and s["t_b"] == pytest.approx(100.0)


def test_t2r_from_a_constructed_trace():
  # mission 0: detected at 31 s, non-compliant at 33 s, compliant again from 35.1 s for 3 s -> T2R 4.1 s
  # mission 1: detected, compliant throughout after detection -> n/a (nothing to recover from)
  # mission 2: non-compliant after detection and never 3 s compliant again, ended non-compliant -> inf
  # mission 3: never detected -> n/a;  mission 4: recovered but crashed -> inf;  mission 5: attack-free -> n/a
  # mission 6: non-compliant at 40 s, then compliant from 41 s until it completed at 42 s (< 3 s) -> 41 - 38 = 3 s
  r = recs(7, det_t=[31.0, 40.0, 32.0, M.BIG, 33.0, M.BIG, 38.0],
           bad_t=[33.0, M.BIG, 35.0, M.BIG, 34.0, M.BIG, 40.0],
           rec_t=[35.1, M.BIG, M.BIG, M.BIG, 36.0, M.BIG, M.BIG],
           ok_since=[35.1, 0.1, M.BIG, 0.1, 36.0, 0.1, 41.0], t_end=[100.0] * 6 + [42.0],
           crash=[0, 0, 0, 0, 1, 0, 0], complete=[1, 1, 0, 1, 0, 1, 1], attacked=[1, 1, 1, 1, 1, 0, 1])
  t = M.t2r(r, DT)
  assert t[0] == pytest.approx(4.1) and math.isnan(t[1]) and math.isinf(t[2]) and math.isnan(t[3])
  assert math.isinf(t[4]) and math.isnan(t[5]) and t[6] == pytest.approx(3.0)
  s = summ(r)
  assert s["t2r_applicable"]["k"] == 4 and s["t2r_applicable"]["n"] == 5
  assert s["t2r_recovered"]["k"] == 2 and s["t2r_recovered"]["n"] == 4
  assert s["t2r_stats"]["median"] == pytest.approx(3.55)
  assert s["detect_rate"]["k"] == 5 and s["detect_rate"]["n"] == 6
  assert s["detection_delay"]["mean"] == pytest.approx((1 + 10 + 2 + 3 + 8) / 5)


def test_t2r_records_from_a_rollout_step_sequence():
  """The rollout's per-step recurrences (evaluation._rollout) on a scripted compliance trace give the recovery
  instant metrics.t2r expects: first compliant step of the first >= 3 s compliant run after the first bad step."""
  dt, hold = 0.1, int(round(M.RECOVERY_HOLD_S / 0.1))
  det = 1.0
  # compliant until 2.0 s, bad 2.0-2.4 s, compliant 2.5-3.9 s (1.5 s: too short), bad 4.0 s, compliant from 4.1 s
  times = np.round(np.arange(1, 101) * dt, 6)
  ok = ~(((times >= 2.0) & (times <= 2.4)) | (times == 4.0))
  bad_t = rec_t = since = M.BIG
  steps = 0
  for now, o in zip(times, ok):
    if now >= det and not o and bad_t >= M.BIG:
      bad_t = now
    since = min(since, now) if o else M.BIG
    steps = steps + 1 if o else 0
    if bad_t < M.BIG and rec_t >= M.BIG and steps >= hold:
      rec_t = since
  r = recs(1, det_t=det, bad_t=bad_t, rec_t=rec_t, ok_since=since, onset=0.5, attack_end=60.0)
  assert bad_t == pytest.approx(2.0) and rec_t == pytest.approx(4.1)
  assert M.t2r(r, dt)[0] == pytest.approx(3.1)


def test_any_violation_share_is_not_circular_for_no_protection():
  """No protection is its own twin: SVR 100 % by construction; the any-violation share over missions under attack
  is the figure that says how harmful the attacks were."""
  r = recs(8, attacked=[1, 1, 1, 1, 1, 1, 0, 0])   # the last two ended before the attack's onset
  r["violated"][:3, 0] = True
  r["crash"][6] = True                              # a crash in a mission the attack never reached: not counted
  s = summ(r, twin=r)
  assert s["svr"] == 1.0 and s["svr_rate"]["n"] == 4
  assert s["any_violation"] == pytest.approx(3 / 6)
  assert s["any_violation_rate"]["k"] == 3 and s["any_violation_rate"]["n"] == 6
  assert s["svr_all"] == pytest.approx(4 / 8)
  s = summ(r, attacked=False)                       # attack-free: over all missions
  assert s["any_violation"] == pytest.approx(4 / 8)


def test_mcnemar_exact_p_values():
  # b = 10, c = 0: p = 2 * 0.5^10
  a = np.r_[np.ones(10, bool), np.zeros(5, bool), np.ones(3, bool)]
  b = np.r_[np.zeros(10, bool), np.zeros(5, bool), np.ones(3, bool)]
  m = M.mcnemar(a, b)
  assert (m["b"], m["c"], m["n"]) == (10, 0, 18) and m["p"] == pytest.approx(2 * 0.5 ** 10)
  assert M.mcnemar(b, a)["p"] == pytest.approx(2 * 0.5 ** 10) and M.mcnemar(b, a)["c"] == 10
  # b = 3, c = 1: P(X <= 1) + P(X >= 3) for Bin(4, 1/2) = (1 + 4 + 4 + 1) / 16
  m = M.mcnemar([1, 1, 1, 0, 0], [0, 0, 0, 1, 0])
  assert (m["b"], m["c"]) == (3, 1) and m["p"] == pytest.approx(10 / 16)
  # b = c: p = 1; no discordant pair: p = 1
  assert M.mcnemar([1, 0], [0, 1])["p"] == pytest.approx(1.0)
  assert M.mcnemar([1, 0, 0], [1, 0, 0]) == {"b": 0, "c": 0, "n": 3, "p": 1.0}


def test_paired_tests_on_constructed_controllers():
  twin = recs(12)
  twin["violated"][:8, 1] = True          # intended: missions 0-7
  a, b = recs(12), recs(12)
  a["violated"][:6, 1] = True             # A violates 0-5, B violates 0 only; B also violates S12 in mission 10
  b["violated"][0, 1] = True
  b["violated"][10, 11] = True
  p = M.paired(a, b, twin, critical=CRIT)
  assert (p["svr"]["b"], p["svr"]["c"], p["svr"]["n"]) == (5, 0, 8)
  assert (p["any_violation"]["b"], p["any_violation"]["c"], p["any_violation"]["n"]) == (5, 1, 12)
  assert p["svr"]["p"] == pytest.approx(2 * 0.5 ** 5)
  assert (p["critical"]["b"], p["critical"]["c"]) == (5, 1)   # S2 and S12 are critical
  a["mission"], b["mission"] = np.arange(12), np.arange(12)[::-1]
  with pytest.raises(ValueError):
    M.paired(a, b, twin, critical=CRIT)


def test_policy_effect_over_the_steps_in_control():
  """The setpoint's size is averaged over the steps the policy was in control, per mission; missions it never
  controlled count in the in-control share only; a zero residual (DeLorean's) reads 0."""
  r = recs(4, override_s=[0.0, 1.0, 2.0, 0.0], action_sum=[0.0, 20.0, 10.0, 0.0], action_max=[0.0, 3.0, 0.5, 0.0])
  s = summ(r)
  assert s["control_rate"]["k"] == 2 and s["control_rate"]["n"] == 4
  assert s["action_mean_stats"]["mean"] == pytest.approx((20.0 / 10 + 10.0 / 20) / 2)    # 10 and 20 steps of 0.1 s
  assert s["action_max_stats"]["mean"] == pytest.approx(1.75) and s["action_max_stats"]["n"] == 2
  z = summ(recs(2, override_s=[1.0, 1.0], action_sum=0.0, action_max=0.0))
  assert z["action_mean_stats"]["mean"] == 0.0
  assert "action_mean_stats" not in summ(recs(2))     # records of a rollout without the policy's effect


def test_violation_timing_splits_the_violating_attacked_missions_by_the_alarm():
  """Six attacked missions: one clean, one violating and never alarmed, one crashing after an alarm but compliant
  from the alarm to the attack's end (its violation came before the alarm), two non-compliant inside the alarm
  window, one violating but not attacked (left out). Shares over the 4 attacked violators."""
  viol = np.zeros((6, len(SPECS)), bool)
  viol[[1, 3, 4, 5], 8] = True
  r = recs(6, violated=viol, crash=[0, 0, 1, 0, 0, 0], attacked=[1, 1, 1, 1, 1, 0],
           det_t=[35.0, M.BIG, 40.0, 33.0, 36.0, 30.0], bad_t=[M.BIG, M.BIG, M.BIG, 45.0, 36.5, 31.0])
  vt = summ(r)["violation_timing"]
  assert [(vt[k]["k"], vt[k]["n"]) for k in ("undetected", "outside", "alarm_window")] == [(1, 4), (1, 4), (2, 4)]
  assert "violation_timing" not in summ(r, attacked=False)


def test_blind_critical_violations_the_estimate_never_showed():
  """Four missions: S2 violated and never seen on the estimate (blind), S2 violated and seen, S12 violated and
  unseen plus S1 violated and seen (blind: one critical spec unseen), S4 violated unseen (not critical: not blind).
  blind_critical_rate counts over the 3 critical violators; blind_spec per spec over its violators."""
  viol = np.zeros((4, len(SPECS)), bool)
  seen = np.zeros((4, len(SPECS)), bool)
  viol[0, 1] = True
  viol[1, 1] = seen[1, 1] = True
  viol[2, 11] = viol[2, 0] = seen[2, 0] = True
  viol[3, 3] = True
  s = summ(recs(4, violated=viol, seen=seen))
  assert (s["blind_critical_rate"]["k"], s["blind_critical_rate"]["n"]) == (2, 3)
  assert [(s["blind_spec"][x]["k"], s["blind_spec"][x]["n"]) for x in ("S1", "S2", "S12")] == [(0, 1), (1, 2), (1, 1)]
  assert list(s["blind_spec"]) == ["S1", "S2", "S12"]
  assert M.blind(recs(4, violated=viol, seen=seen), CRIT).sum() == 2
  assert "blind_critical_rate" not in summ(recs(4, violated=viol))   # records without 'seen'


def test_confidence_intervals_sane():
  lo, hi = M.wilson(0, 100)
  assert lo == 0.0 and 0.0 < hi < 0.05
  lo, hi = M.wilson(100, 100)
  assert hi == 1.0 and 0.95 < lo < 1.0
  lo, hi = M.wilson(50, 100)
  assert lo < 0.5 < hi and hi - lo == pytest.approx(0.19, abs=0.01)
  assert all(math.isnan(x) for x in M.wilson(0, 0))
  m, lo, hi = M.mean_ci([1.0, 2.0, 3.0, 4.0])
  assert m == 2.5 and lo < m < hi and hi - m == pytest.approx(2.0540, abs=1e-3)   # t(0.975, 3) * s / sqrt(4)
  m, lo, hi = M.mean_ci(np.random.default_rng(0).normal(size=1000))   # ~ +-1.96 / sqrt(1000)
  assert lo < 0.0 < hi and hi - lo == pytest.approx(2 * 1.96 / math.sqrt(1000), rel=0.1)
