"""evaluate.py end to end on the CPU: a tiny real run (2 controllers sharing one compiled rollout x 3 settings x 3
short missions) writes report.json / report.md / figures with sane values; bad flags are one-line errors (exit 2)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import evaluate as evaluate_cli
from specguard_jax import controllers as C
from specguard_jax import evaluation as E

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MISSIONS = 3


def _autopilot_copy(ctx):
  """The autopilot alone under another name: same env config and policy as no_protection, so it shares the compiled
  rollout and must reproduce its twin exactly (SVR over intended violations = 100 %, zero mission delay)."""
  c = C.build("no_protection", ctx)
  return C.Controller("autopilot_copy", c.env_overrides, c.policy, c.params, "test: the autopilot again")


def _code_mappings() -> int:
  """This process's memory mappings (Linux); XLA:CPU maps each compiled executable's code into thousands of them."""
  with open("/proc/self/maps") as f:
    return sum(1 for _ in f)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
  C.register("autopilot_copy", _autopilot_copy)
  out = str(tmp_path_factory.mktemp("eval"))
  maps, held = _code_mappings(), E.cached_rollouts()
  rc = evaluate_cli.main(["--controllers", "no_protection,autopilot_copy", "--sensors", "gps,gyro",
                          "--profiles", "overt", "--missions", str(MISSIONS), "--mission-s", "30,40", "--max-s", "90",
                          "--false-alarms", "gps", "--out", out, "--no-progress"])
  assert rc == 0
  # On the CPU each rollout is compiled for its flight and freed after it (the copy reuses its twin's executable):
  # kept, the 23 rollouts of --suite paper exceeded the kernel's 65,530 mappings and crashed. Here the three compiled
  # rollouts, kept, add ~2,100 mappings; freed, ~200.
  assert E.cached_rollouts() == held
  assert _code_mappings() - maps < 1000, "the flown rollouts' executables are still mapped"
  with open(os.path.join(out, "report.json")) as f:
    rep = json.load(f)
  yield out, rep
  C._REGISTRY.pop("autopilot_copy", None)
  E.clear_cache()


def test_report_names_the_rule_a_controller_flies_over(report):
  """A run trained over the fallback rule is flown over it; the report's header says so (none: no line)."""
  from specguard_jax import report as R
  _, rep = report
  assert "recovery_rule" not in R.markdown(rep)
  rep = dict(rep, meta=dict(rep["meta"], recovery_rules={"main/specguard_rc": "fallback"}))
  line = "- rule under the alarm (EnvConfig.recovery_rule), where not none: main/specguard_rc fallback"
  assert line in R.markdown(rep)


def test_report_files_and_keys(report):
  out, rep = report
  for name in ("report.json", "report.md", "records/main__no_protection.npz", "records/main__autopilot_copy.npz"):
    assert os.path.isfile(os.path.join(out, name)), name
  for fig in ("comparison.png", "svr_heatmap.png", "t2r_cdf.png"):
    path = os.path.join(out, "figures", fig)
    assert os.path.getsize(path) > 5000, fig
  g = rep["groups"]["main"]
  assert g["settings"] == ["attack_free", "gps/overt", "gyro/overt"]
  assert g["controllers"]["no_protection"]["recovery_rule"] == "none" and rep["meta"]["recovery_rules"] == {}
  for c in ("no_protection", "autopilot_copy"):
    for s in g["settings"] + ["pooled/overt", "pooled/attacked"]:
      m = g["metrics"][c][s]
      for k in ("svr", "svr_all", "rsr", "md", "collision_rate", "missions", "svr_rate", "rsr_rate"):
        assert k in m, (c, s, k)
      assert m["missions"] == (MISSIONS if s in g["settings"] else MISSIONS * (2 if s.startswith("pooled") else 1))
      for k in ("svr_all", "rsr", "collision_rate"):
        assert 0.0 <= m[k] <= 1.0
      lo, hi = m["rsr_rate"]["ci"]
      assert lo <= m["rsr"] <= hi
  assert rep["totals"]["missions"] == 2 * (3 + 1) * MISSIONS and rep["wall_s"] > 0   # + the false-alarm group
  md = open(os.path.join(out, "report.md")).read()
  assert "not AirSim" in md and "Table 5" in md and "autopilot_copy" in md


def test_forced_false_alarms_group(report):
  """--false-alarms: attack-free missions with the alarm raised; the autopilot copy has no reconstruction and no
  policy, so the alarm changes nothing and it flies exactly its twin's missions (the report's ground truth for a
  group without an 'attack_free' setting is the twin's own missions)."""
  out, rep = report
  g = rep["groups"]["false_alarm"]
  assert g["settings"] == ["false_alarm/gps"]
  a = np.load(os.path.join(out, "records/false_alarm__no_protection.npz"))
  b = np.load(os.path.join(out, "records/false_alarm__autopilot_copy.npz"))
  np.testing.assert_array_equal(a["violated"], b["violated"])
  for c in ("no_protection", "autopilot_copy"):
    m = g["metrics"][c]["false_alarm/gps"]
    assert m["missions"] == MISSIONS and m["md"] == 0.0
  m0, m1 = (g["metrics"][c]["false_alarm/gps"] for c in ("no_protection", "autopilot_copy"))
  assert m0["any_violation_rate"] == m1["any_violation_rate"] and m0["rsr"] == m1["rsr"]
  md = open(os.path.join(out, "report.md")).read()
  assert "## Forced false alarms" in md


def test_twin_reproduces_itself(report):
  """Same missions, same controller: identical records, 100 % of intended violations observed, zero delay."""
  out, rep = report
  a = np.load(os.path.join(out, "records/main__no_protection.npz"))
  b = np.load(os.path.join(out, "records/main__autopilot_copy.npz"))
  for k in ("violated", "t_end", "final_dist", "complete"):
    np.testing.assert_array_equal(a[k], b[k])
  # paired missions: every setting flies missions 0..n-1 with the same plan (attack-free vs attacked twins)
  assert (a["mission"] == np.tile(np.arange(MISSIONS), 3)).all()
  assert not a["attacked"][:MISSIONS].any() and a["onset"][MISSIONS:].max() < 40.0
  ms = rep["groups"]["main"]["metrics"]
  for s, m in ms["autopilot_copy"].items():
    if m["attacked"] and m["intended"]:
      assert m["svr"] == 1.0
    assert m["md"] == ms["no_protection"][s]["md"] and m["rsr"] == ms["no_protection"][s]["rsr"]
  assert ms["autopilot_copy"]["attack_free"]["md"] == 0.0   # T_SG = T_GT: its own ground truth
  # paired tests: the same controller twice has no discordant mission (p = 1), on every setting and pool
  pairs = rep["groups"]["main"]["paired"]
  assert set(pairs) == set(rep["groups"]["main"]["settings"]) | {"pooled/overt", "pooled/attacked"}
  for s, tests in pairs.items():
    for k in ("any_violation", "critical") + (("svr",) if s != "attack_free" else ()):
      t = tests["no_protection vs autopilot_copy"][k]
      assert (t["b"], t["c"], t["p"]) == (0, 0, 1.0), (s, k)
    assert 0.0 <= ms["no_protection"][s]["any_violation"] <= 1.0
  assert "McNemar" in open(os.path.join(out, "report.md")).read()


def _cli(*args):
  p = subprocess.run([sys.executable, os.path.join(ROOT, "evaluate.py"), *args], capture_output=True, text=True,
                     cwd=ROOT, env=dict(os.environ, JAX_PLATFORMS="cpu"), timeout=120)
  return p.returncode, p.stderr.strip()


@pytest.mark.parametrize("args,needle", [
    (("--controllers", "nope"), "unknown controller"),
    (("--sensors", "lidar"), "unknown sensor"),
    (("--profiles", "loud"), "unknown or no profile"),
    (("--run", "/nonexistent/run"), "no such directory"),
    (("--missions", "0"), "--missions must be >= 1"),
    (("--mission-s", "abc"), "--mission-s takes"),
    (("--bogus",), "unrecognized arguments"),
])
def test_bad_flags_one_line(args, needle):
  rc, err = _cli(*args)
  assert rc == 2 and len(err.splitlines()) == 1 and needle in err, err


def _part(src, dst, keep):
  """A copy of the evaluation in `src` holding only the controllers in `keep` (report.json and records), as if an
  evaluate.py job had flown only those."""
  import shutil
  with open(os.path.join(src, "report.json")) as f:
    rep = json.load(f)
  os.makedirs(os.path.join(dst, "records"))
  for g, grp in rep["groups"].items():
    grp["controllers"] = {c: v for c, v in grp["controllers"].items() if c in keep}
    for c in grp["controllers"]:
      shutil.copy(os.path.join(src, "records", f"{g}__{c}.npz"), os.path.join(dst, "records"))
  with open(os.path.join(dst, "report.json"), "w") as f:
    json.dump(rep, f)
  return str(dst)


def test_merge_of_parts_equals_the_whole(report, tmp_path):
  """evaluate.py --merge: two parts (no protection alone; no protection + the copy) give the report of the one job
  that flew both: the same metrics and paired tests; parts of other missions or a twin that flew differently are
  refused in one line."""
  out, rep = report
  a = _part(out, tmp_path / "a", {"no_protection"})
  b = _part(out, tmp_path / "b", {"no_protection", "autopilot_copy"})
  merged = str(tmp_path / "merged")
  assert evaluate_cli.main(["--merge", a, b, "--out", merged, "--no-figures"]) == 0
  with open(os.path.join(merged, "report.json")) as f:
    m = json.load(f)
  for g in ("main", "false_alarm"):
    assert list(m["groups"][g]["controllers"]) == ["no_protection", "autopilot_copy"]
    assert m["groups"][g]["metrics"] == rep["groups"][g]["metrics"]
    assert m["groups"][g]["paired"] == rep["groups"][g]["paired"]
  assert m["totals"]["missions"] == rep["totals"]["missions"]
  assert [p["controllers"] for p in m["meta"]["merged_from"]] == [["no_protection"],
                                                                   ["autopilot_copy", "no_protection"]]
  assert "merged from 2 evaluations" in open(os.path.join(merged, "report.md")).read()
  # a part of other missions (another seed) is refused
  c = _part(out, tmp_path / "c", {"no_protection"})
  with open(os.path.join(c, "report.json")) as f:
    r = json.load(f)
  r["meta"]["seed"] += 1
  with open(os.path.join(c, "report.json"), "w") as f:
    json.dump(r, f)
  rc, err = _cli("--merge", c, b, "--out", str(tmp_path / "m2"))
  assert rc == 2 and len(err.splitlines()) == 1 and "differ in seed" in err, err
  # the twin flown differently in two parts (pairing broken) is refused
  d = _part(out, tmp_path / "d", {"no_protection"})
  path = os.path.join(d, "records", "main__no_protection.npz")
  z = dict(np.load(path))
  z["violated"] = ~z["violated"]
  np.savez(path, **z)
  rc, err = _cli("--merge", d, b, "--out", str(tmp_path / "m3"))
  assert rc == 2 and "main/no_protection flew differently" in err, err
  rc, err = _cli("--merge", a, b, "--out", str(tmp_path / "m4"), "--seed", "3")
  assert rc == 2 and "--merge takes only --out" in err, err


def test_tagged_runs_fly_beside_the_others(tmp_path):
  """--runs specguard_rc_<tag>=DIR (another seed) is flown in the main group under its role's name, and with the
  oracle's forced alarm in the false-alarm group; an unknown role is a one-line error."""
  for name, variant in (("rc", "rc"), ("s1", "rc")):
    (tmp_path / name).mkdir()
    (tmp_path / name / "config.json").write_text(json.dumps({"variant": variant}))
  args = evaluate_cli.parse_args(["--run", str(tmp_path / "rc"), "--runs", f"specguard_rc_s1={tmp_path}/s1",
                                  "--controllers", "no_protection,specguard_rc", "--false-alarms", "gps"])
  p = evaluate_cli.plan(args)
  main = p["groups"]["main"]["controllers"]
  assert main[-1] == ("run", "specguard_rc_s1", f"{tmp_path}/s1", ()) and "specguard_rc" in main
  fa = p["groups"]["false_alarm"]["controllers"]
  assert fa[-1] == ("run", "specguard_rc_s1", f"{tmp_path}/s1", evaluate_cli.FORCED_ALARM)
  rc, err = _cli("--runs", f"seed1={tmp_path}/s1")
  assert rc == 2 and "unknown run role 'seed1'" in err, err
