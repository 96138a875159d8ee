"""Spec tables, parameters, spec/params files, compiled evaluator and online spec monitor."""

import json

import jax
import numpy as np
import pytest

from specguard_jax import specs, stl
from specguard_jax.signals import SIGNAL_NAMES

DT = 0.1


def nominal_trace(t=600):
  """A plausible compliant drone mission at dt = 0.1 s: take-off, 3 cruise legs, loiter, landing. {name: [T]}."""
  s = {n: np.zeros(t, np.float32) for n in SIGNAL_NAMES}
  k = np.arange(t)
  to, cr, lo = 70, 470, 520  # phase starts: cruise, loiter, landing
  s["in_takeoff"][:to] = 1
  s["in_cruise"][to:cr] = 1
  s["in_loiter"][cr:lo] = 1
  s["in_landing"][lo:] = 1
  vz = np.where(k < to, np.minimum(k * DT, 1.0) * 2.5, 0.0)
  vz[lo:] = -0.4
  s["speed_z"] = vz.astype(np.float32)
  s["descent_speed"] = np.maximum(0, -vz).astype(np.float32)
  s["altitude"] = (0.5 + np.cumsum(vz) * DT).astype(np.float32)
  leg = ((k - to) % 125).astype(np.float32)  # 12.5 s legs of 100 m at 8 m/s
  s["dist_wp"] = np.where(s["in_cruise"] > 0, 100 - leg * 0.8, 3.0).astype(np.float32)
  speed = np.where(s["dist_wp"] < 8, 3.0, 8.0)
  speed = np.where(leg < 10, 3.0 + leg * 0.5, speed)  # accelerating out of each turn
  s["speed_xy"] = np.where(s["in_cruise"] > 0, speed, 0.5).astype(np.float32)
  s["wp_slack"] = np.where(s["in_cruise"] > 0, 20 - leg * 0.1, 5).astype(np.float32)
  s["dist_final"] = np.maximum(0, 300 - np.maximum(k - to, 0) * 0.8).astype(np.float32)
  s["path_deviation"][:] = 1.0
  s["obstacle_distance"][:] = 30.0
  s["fence_margin"][:] = 8.0
  s["fence_h"][:] = 20.0
  s["fence_v"][:] = 8.0
  s["loiter_deviation"][cr:lo] = 2.0
  s["time"] = (k * DT).astype(np.float32)
  return s


def test_tables_shape_names_and_flags():
  d, r = specs.drone_specs(), specs.rover_specs()
  assert d.names == tuple(f"S{i}" for i in range(1, 13))
  assert r.names == ("S1", "S2", "S5", "S6", "S7", "S8", "S12")
  assert [s.name for s in d.specs if s.critical] == ["S1", "S2", "S12"]
  assert [s.name for s in r.specs if s.critical] == ["S1", "S2", "S12"]
  for table in (d, r):
    for name in table.names:
      assert set(stl.signals_of(table.formula(name))) <= set(SIGNAL_NAMES)
  assert hash(d) == hash(specs.drone_specs())  # usable as a static jit argument
  assert "S12" in d.describe()


def test_nominal_mission_satisfies_all_and_single_violations_are_caught():
  ev = specs.compile_specs(specs.drone_specs(), DT)
  sig = nominal_trace()
  rob, viol = ev(sig)
  assert rob.shape == (12,) and not np.any(viol), dict(zip(ev.names, np.asarray(rob)))
  cases = {  # (signal, index slice, value) -> the only violated spec
      "S1": ("obstacle_distance", slice(200, 205), 4.0), "S2": ("path_deviation", slice(300, 301), 10.5),
      "S3": ("altitude", slice(200, 230), 9.0), "S4": ("altitude", slice(200, 230), 21.0),
      "S5": ("wp_slack", slice(300, 310), -1.0), "S7": ("speed_xy", slice(150, 200), 4.0),
      "S8": ("speed_xy", slice(300, 305), 13.0), "S9": ("descent_speed", slice(550, 560), 0.8),
      "S10": ("speed_z", slice(10, 70), 1.5), "S11": ("loiter_deviation", slice(480, 490), 9.0),
      "S12": ("fence_margin", slice(100, 101), 0.5),
  }
  for spec, (name, sl, value) in cases.items():
    bad = {k: v.copy() for k, v in sig.items()}
    bad[name][sl] = value
    _, viol = ev(bad)
    expected = {spec} | ({"S6"} if spec == "S1" else set())
    assert {n for n, v in zip(ev.names, np.asarray(viol)) if v} == expected, spec


def test_phase_guards():
  ev = specs.compile_specs(specs.drone_specs(), DT)
  sig = nominal_trace()
  i = ev.names.index
  # low altitude during take-off/landing and zero speed in loiter are not violations (checked by the nominal trace);
  # a 2 s slow-down far from a waypoint is tolerated by the 3 s acceleration grace, a 5 s one is not
  for dur, violated in ((20, False), (50, True)):
    bad = {k: v.copy() for k, v in sig.items()}
    bad["speed_xy"][150:150 + dur] = 4.0
    assert bool(ev(bad)[1][i("S7")]) == violated
  # S3's robustness is the altitude margin while the guard is on
  rob, _ = ev(sig)
  assert np.isclose(rob[i("S3")], sig["altitude"][70:520].min() - 10.0, atol=1e-4)
  assert np.isclose(rob[i("S1")], 30.0 - 5.0)


def test_online_spec_monitor_equals_offline():
  ev = specs.compile_specs(specs.drone_specs(), DT)
  base = nominal_trace(300)
  rng = np.random.default_rng(0)
  batch = {k: np.stack([v, v + rng.normal(0, 1.5, v.shape).astype(np.float32)]) for k, v in base.items()}
  state = ev.monitor_init((2,))

  def step(s, x_t):
    s, rob, viol = ev.monitor_update(s, x_t)
    return s, rob

  _, online = jax.jit(lambda s, xs: jax.lax.scan(step, s, xs))(state, {k: v.T for k, v in batch.items()})
  rob, viol = ev(batch)
  np.testing.assert_allclose(online[-1], rob, atol=1e-5)
  assert np.any(np.asarray(viol)[1])  # the noisy copy violates something
  rob100, _ = ev({k: v[:, :100] for k, v in batch.items()})
  np.testing.assert_allclose(online[99], rob100, atol=1e-5)


def test_overrides_and_bad_params():
  sig = nominal_trace()
  sig["obstacle_distance"][100] = 6.0
  assert not specs.compile_specs(specs.drone_specs(), DT)(sig)[1][0]
  assert specs.compile_specs(specs.drone_specs({"CP_DIST": 7.0}), DT)(sig)[1][0]
  assert specs.with_params(specs.rover_specs(), {"AVOID_MARGIN": 2}).params["AVOID_MARGIN"] == 2.0
  for bad, msg in (({"CP_DIST_X": 1.0}, "unknown parameter 'CP_DIST_X'"), ({"CP_DIST": "abc"}, "not a number"),
                   ({"CP_DIST": float("nan")}, "not finite"), ({"CP_DIST": -1}, "outside")):
    with pytest.raises(specs.SpecError, match=msg) as e:
      specs.drone_specs(bad)
    assert "\n" not in str(e.value)


def test_load_params_files(tmp_path):
  px4 = tmp_path / "drone.params"
  px4.write_text("# Onboard parameters for Vehicle 1\n#\n# Vehicle-Id Component-Id Name Value Type\n"
                 "1\t1\tCP_DIST\t6.5\t9\n1\t1\tMPC_XY_VEL_MAX\t10.000000000000000000\t9\n1\t1\tMPC_Z_P\t1.0\t9\n")
  got = specs.load_params_file(str(px4))
  assert got == {"CP_DIST": 6.5, "MPC_XY_VEL_MAX": 10.0}
  assert specs.drone_specs(got).params["CP_DIST"] == 6.5
  apm = tmp_path / "rover.parm"
  apm.write_text("AVOID_MARGIN,4\nWPNAV_RADIUS 300  # cm\nFENCE_MARGIN\t2\nATC_STR_RAT_P,0.2\n")
  assert specs.load_params_file(str(apm)) == {"AVOID_MARGIN": 4.0, "WPNAV_RADIUS": 3.0, "FENCE_MARGIN": 2.0}
  bad = tmp_path / "bad.parm"
  bad.write_text("AVOID_MARGIN,4\nthis line is wrong\n")
  with pytest.raises(specs.SpecError, match="bad.parm:2"):
    specs.load_params_file(str(bad))
  bad.write_text("AVOID_MARGIN,four\n")
  with pytest.raises(specs.SpecError, match="AVOID_MARGIN.*not a number"):
    specs.load_params_file(str(bad))


def test_add_spec_in_text_and_errors():
  t = specs.add_spec(specs.drone_specs(), "S13", "always((in_cruise > 0.5) -> (altitude < SG_MAX_ALT))",
                     params={"SG_MAX_ALT": 18.0}, critical=True)
  s = t["S13"]
  assert (s.family, s.reward_signals, t.threshold(s), s.critical) == ("keep_below", ("altitude",), 18.0, True)
  assert s.reward_guard
  assert specs.compile_specs(t, DT)(nominal_trace())[0].shape == (13,)
  with pytest.raises(specs.SpecError, match="S14.*position"):
    specs.add_spec(t, "S14", "always(altitude > )")
  with pytest.raises(specs.SpecError, match="S14.*unknown signal 'altitud'"):
    specs.add_spec(t, "S14", "always(altitud > 3)")
  with pytest.raises(specs.SpecError, match="duplicate"):
    specs.add_spec(t, "S13", "always(altitude > 3)")
  with pytest.raises(specs.SpecError, match="inverted"):
    specs.add_spec(t, "S14", "always[3s, 1s](altitude > 3)")
  with pytest.raises(specs.SpecError, match="family"):
    specs.add_spec(t, "S14", "always(altitude > 3)", family="sigmoidish", reward_signals=["altitude"])
  u = specs.add_spec(t, "S14", "eventually[0s, 60s](dist_final < 2)")  # monitored only: no shaped reward
  assert u["S14"].family == "none"


def test_spec_files(tmp_path):
  txt = tmp_path / "extra.specs"
  txt.write_text("# extra specs\nparam SG_MAX_CLIMB = 3\nspec C1: always(speed_z < SG_MAX_CLIMB)\n"
                 "spec C2 critical: always((in_landing > 0.5) -> (altitude < 30))\n")
  t = specs.load_spec_file(str(txt), specs.drone_specs())
  assert t.names[-2:] == ("C1", "C2") and t["C2"].critical and t.params["SG_MAX_CLIMB"] == 3.0
  js = tmp_path / "extra.json"
  js.write_text(json.dumps({"params": {"SG_V": 4}, "specs": [
      {"name": "J1", "stl": "always(speed_xy < SG_V)", "family": "keep_below", "k": 2.0,
       "reward_signals": ["speed_xy"], "reward_threshold": "SG_V"}]}))
  t = specs.load_spec_file(str(js))
  assert t.names == ("J1",) and t["J1"].k == 2.0
  txt.write_text("spec C1 always(speed_z < 3)\n")
  with pytest.raises(specs.SpecError, match="extra.specs:1"):
    specs.load_spec_file(str(txt))
