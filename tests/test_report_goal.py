"""The hard suite's goal section (report.hard_goal): per SpecGuard controller, reference and attacked campaign, the
settings' discordant pairs summed into one exact McNemar test, the RSR rule, and a plain verdict."""

from scipy import stats

from specguard_jax import metrics as M
from specguard_jax import report


def _t(b, c, n=500):
  return M.mcnemar_counts(b, c, n)


def _rate(v, half=0.02):
  return {"value": v, "ci": [v - half, v + half], "k": 0, "n": 1000}


def _rep(sg_rsr):
  paired = {
      "attack_free": {"delorean vs specguard_rc": {"svr": _t(0, 50), "critical": _t(0, 50)}},
      # the pair's name in either order: the second setting names DeLorean second, so its b / c are SpecGuard's
      "long/gps/overt": {"delorean vs specguard_rc": {"svr": _t(30, 4), "critical": _t(20, 2)},
                         "no_protection vs specguard_rc": {"svr": _t(0, 0), "critical": _t(0, 0)}},
      "long/gyro/overt": {"specguard_rc vs delorean": {"svr": _t(3, 25), "critical": _t(1, 15)}},
      "redteam/any/overt": {"delorean vs specguard_rc": {"svr": _t(50, 0), "critical": _t(50, 0)}},
  }
  metrics = {c: {} for c in ("no_protection", "delorean", "specguard_rc")}
  table = {k: {"delorean": {"rsr": _rate(0.7)}, "specguard_rc": {"rsr": _rate(sg_rsr)}}
           for k in ("attack_free", "long", "redteam")}
  return {"groups": {"main": {"metrics": metrics, "paired": paired}}}, table


def test_pooled_counts_orientation_and_verdict():
  rep, table = _rep(0.69)
  rows = report.hard_goal(rep, table)
  assert [(r["reference"], r["campaign"]) for r in rows] == [("delorean", "long")]   # not attack-free, not redteam
  r = rows[0]
  # SpecGuard-only violations: 4 + 3 (SVR), 2 + 1 (critical); DeLorean-only: 30 + 25, 20 + 15
  assert (r["svr"]["b"], r["svr"]["c"], r["critical"]["b"], r["critical"]["c"]) == (7, 55, 3, 35)
  assert abs(r["svr"]["p"] - stats.binomtest(7, 62, 0.5).pvalue) < 1e-12
  assert r["beats"] and r["rsr"] == [0.69, 0.7]
  md = "\n".join(report.hard_goal_markdown(rows))
  assert "- specguard_rc beats delorean on every attacked campaign: it wins 1 of 1" in md


def test_lower_rsr_or_no_reference_is_no_win():
  rep, table = _rep(0.5)        # fewer violations by not finishing: RSR 50 % [48, 52] vs 70 %
  rows = report.hard_goal(rep, table)
  assert not rows[0]["beats"]
  assert "specguard_rc does NOT beat delorean" in "\n".join(report.hard_goal_markdown(rows))
  rep["groups"]["main"]["metrics"].pop("delorean")
  assert report.hard_goal(rep, table) == [] and report.hard_goal_markdown([]) == []
