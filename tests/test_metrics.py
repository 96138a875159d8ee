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
       "det_t": np.full(n, M.BIG), "last_bad": np.full(n, -M.BIG), "end_ok": np.ones(n, bool)}
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
  # mission 0: detected at 31 s, last non-compliant step 35 s -> recovered at 35.1 s: T2R 4.1 s
  # mission 1: detected, compliant throughout -> 0 s;  mission 2: still violating at the attack's end -> inf
  # mission 3: never detected -> n/a;  mission 4: detected but crashed -> inf;  mission 5: attack-free -> n/a
  r = recs(6, det_t=[31.0, 40.0, 32.0, M.BIG, 33.0, M.BIG], last_bad=[35.0, -M.BIG, 60.0, -M.BIG, 34.0, -M.BIG],
           end_ok=[1, 1, 0, 1, 1, 1], crash=[0, 0, 0, 0, 1, 0], attacked=[1, 1, 1, 1, 1, 0])
  t = M.t2r(r, DT)
  assert t[0] == pytest.approx(4.1) and t[1] == 0.0 and math.isinf(t[2]) and math.isnan(t[3])
  assert math.isinf(t[4]) and math.isnan(t[5])
  s = summ(r)
  assert s["t2r_recovered"]["k"] == 2 and s["t2r_recovered"]["n"] == 4
  assert s["t2r_stats"]["median"] == pytest.approx(2.05)
  assert s["detect_rate"]["k"] == 4 and s["detect_rate"]["n"] == 5
  assert s["detection_delay"]["mean"] == pytest.approx((1 + 10 + 2 + 3) / 4)


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
