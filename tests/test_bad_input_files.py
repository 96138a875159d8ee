"""Bad input never crashes, hangs or passes silently: STL text, mission files (.plan, QGC WPL) and parameter files
(.params, .parm).

Table-driven cases end in the project's own one-line errors (stl.STLError, specs.SpecError, MissionFileError) or a
warning; property tests (hypothesis, seeded) feed random text to the STL parser and random bytes and mutated valid
files to the mission and parameter loaders: they parse or raise those errors, never anything else."""

import json
import pathlib
import warnings

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from envs import mission_files as mf
from envs.mission_files import MissionFileError, MissionFileWarning
from specguard_jax import specs, stl
from specguard_jax.specs import ParamFileWarning, SpecError

DATA = pathlib.Path(__file__).resolve().parents[1] / "envs" / "data"
PLAN = (DATA / "drone_inspection.plan").read_text()
WPL = (DATA / "drone_patrol.waypoints").read_text()
ROVER_WPL = (DATA / "rover_loop.waypoints").read_text()
PROPERTY = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


def _one_line(err):
  assert "\n" not in str(err.value), str(err.value)
  return str(err.value)


# ---------------------------------------------------------------------------------------------------------- STL text

STL_BAD = [
    # (case, text, params, error, message pattern)
    ("300 nested parens", "(" * 300 + "x > 0" + ")" * 300, None, stl.FormulaSizeError,
     "position 112: text nests more than 112 levels"),
    ("5000 nested parens", "(" * 5000 + "x > 0" + ")" * 5000, None, stl.FormulaSizeError, "112 levels"),
    ("500 nots", "not " * 500 + "x > 0", None, stl.FormulaSizeError, "position 448: text nests"),
    ("300 implications", "x > 0 -> " * 300 + "x > 0", None, stl.FormulaSizeError, "tree nests more than 32 levels"),
    ("300-term until chain", " until ".join(["x > 0"] * 300), None, stl.FormulaSizeError,
     r"position \d+: formula tree"),
    ("100 nots", "not " * 100 + "x > 0", None, stl.FormulaSizeError, "tree nests more than 32 levels"),
    ("2000 unary minus", "- " * 2000 + "x > 0", None, stl.FormulaSizeError, "position 224: text nests"),
    ("300 arithmetic parens", "(" * 300 + "x + 1" + ")" * 300 + " > 0", None, stl.FormulaSizeError, "112 levels"),
    ("5000-term and chain", " and ".join(["x > 0"] * 5000), None, stl.FormulaSizeError, "4096 nodes"),
    ("1 MB text", "x > 0 and " * 100_000 + "x > 0", None, stl.FormulaSizeError, "200000"),
    ("always[0,1e12]", "always[0,1e12](x > 0)", None, stl.IntervalError, r"'\[0,1e12\]' at position 6.*4 TB.*1000"),
    ("always[0,1e9]", "always[0,1e9](x > 0)", None, stl.IntervalError, r"1,000,000,000 steps.*4 GB"),
    ("until[0,1e9]", "x > 0 until[0,1e9] y > 0", None, stl.IntervalError, "4 GB"),
    ("1500-step window", "eventually[0,1.5e3](x > 0)", None, stl.IntervalError, "1,500 steps"),
    ("nested 900 + 900 steps", "always[0,900](eventually[0,900](x > 0))", None, stl.IntervalError,
     "nested windows.*1,800 steps"),
    ("constant 1e999", "x > 1e999", None, stl.STLSyntaxError, "position 4.*'1e999' is not a finite"),
    ("400-digit constant", "x > " + "9" * 400, None, stl.STLSyntaxError, "position 4.*not a finite"),
    ("constant inf", "x > inf", None, stl.STLSyntaxError, "position 4.*'inf' is not a finite"),
    ("constant -Infinity", "x > -Infinity", None, stl.STLSyntaxError, "position 5.*'Infinity'"),
    ("constant nan", "x < nan", None, stl.STLSyntaxError, "position 4.*'nan'"),
    ("coefficient overflow", "1e300 * 1e300 * x > 0", None, stl.STLSyntaxError, "position 0.*overflow"),
    ("division overflow", "x / 1e-320 > 0", None, stl.STLSyntaxError, "overflow"),
    ("offset overflow", "x > 1e308 + 1e308", None, stl.STLSyntaxError, "overflow"),
    ("bound 1e999", "always[0,1e999](x > 0)", None, stl.STLSyntaxError, "not a finite"),
    ("parameter nan", "x > A", {"A": float("nan")}, stl.STLError, "'A'.*not a finite"),
    ("parameter text", "x > A", {"A": "abc"}, stl.STLError, "'A'.*'abc' is not a number"),
    ("parameter None", "x > A", {"A": None}, stl.STLError, "'A'.*not a number"),
    ("1000 unbalanced parens", "(x > 0 and " * 1000, None, stl.STLSyntaxError, "unbalanced"),
    ("NUL character", "x > 0\x00", None, stl.STLSyntaxError, "position 5"),
]


@pytest.mark.parametrize("text, params, err, pattern", [c[1:] for c in STL_BAD], ids=[c[0] for c in STL_BAD])
def test_bad_stl_is_refused_at_parse_time(text, params, err, pattern):
  with pytest.raises(err, match=pattern) as e:
    stl.parse(text, params=params)
  _one_line(e)


@pytest.mark.parametrize("text, params, pattern", [
    ("always[0s, 1e6s](x > 0)", None, r"\[0s,1000000s\] of always.*10,000,000 steps at dt=0.1 s.*40 MB"),
    ("always[0, T s](x > 0)", {"T": 1e6}, "10,000,000 steps at dt=0.1 s"),
    ("eventually[0s, 60s](always[0s, 60s](x > 0))", None, "nested windows.*1,200 steps at dt=0.1 s"),
])
def test_second_windows_are_checked_with_dt(text, params, pattern):
  f = stl.parse(text, params=params)   # seconds: the step count needs dt
  for use in (lambda: stl.to_steps(f, 0.1), lambda: stl.OnlineMonitor.create(f, 0.1),
              lambda: stl.robustness(f, {"x": np.zeros(4)}, dt=0.1)):
    with pytest.raises(stl.IntervalError, match=pattern) as e:
      use()
    _one_line(e)


def test_formulas_built_in_python_are_checked_too():
  deep = stl.parse("x > 0")
  for _ in range(1000):
    deep = stl.Not(deep)
  with pytest.raises(stl.FormulaSizeError, match="more than 32 levels"):
    stl.robustness(deep, {"x": np.zeros(3)})
  long = stl.Always(stl.parse("x > 0"), stl.Interval(0, 5000))
  with pytest.raises(stl.IntervalError, match="5,000 steps"):
    stl.OnlineMonitor(long).init(())
  with pytest.raises(stl.IntervalError, match="5,000 steps"):
    stl.robustness(long, {"x": np.zeros(3)})


def _later_uses(f, dt=0.1):
  """Every later use of a parsed formula: str / hash, offline robustness (eager and jitted), the online monitor."""
  assert stl.parse(str(f)) == f and hash(f) == hash(stl.parse(str(f)))
  names = stl.signals_of(f)
  sig = {n: jnp.linspace(-1.0, 1.0, 6) * (k + 1) for k, n in enumerate(names)}
  rob = stl.robustness(f, sig, dt=dt)
  np.testing.assert_array_equal(rob, jax.jit(lambda s: stl.robustness(f, s, dt=dt))(sig))
  mon = stl.OnlineMonitor.create(f, dt)
  state = mon.init(())
  for t in range(6):
    state, val = mon.update(state, {n: v[t] for n, v in sig.items()})
  np.testing.assert_allclose(val, stl.robustness(f, sig, dt=dt)[0], atol=1e-5)
  return rob


def test_formulas_at_the_limits_work_at_every_later_use():
  # MAX_DEPTH levels: 99 nots over a predicate
  f = stl.parse("not " * (stl.MAX_DEPTH - 1) + "x > 0.5")
  np.testing.assert_allclose(_later_uses(f), -(np.linspace(-1, 1, 6) - 0.5), atol=1e-6)
  # a 1,000-term and chain is a balanced tree (depth 11), equal to the min over its terms
  terms = [f"x{k % 7} > {k / 1000}" for k in range(1000)]
  f = stl.parse(" and ".join(terms))
  assert isinstance(f, stl.And) and stl.ast.check_size(f) is f
  rob = _later_uses(f)
  sig = {f"x{k}": np.linspace(-1.0, 1.0, 6) * (k + 1) for k in range(7)}
  np.testing.assert_allclose(rob, np.min([sig[f"x{k % 7}"] - k / 1000 for k in range(1000)], axis=0), atol=1e-5)
  # the deepest text: MAX_DEPTH - 1 nested temporal operators (three levels each when printed) over a predicate whose
  # arithmetic nests 12 levels (printed canonically); str() parses back to the same formula
  text = "always[0,1](" * (stl.MAX_DEPTH - 1) + "(" * 12 + "x + 1" + ")" * 12 + " > 0" + ")" * (stl.MAX_DEPTH - 1)
  f = stl.parse(text)
  assert stl.parse(str(f)) == f and stl.ast.window_span(stl.to_steps(f)) == stl.MAX_DEPTH - 1
  # a window of MAX_WINDOW_STEPS steps
  f = stl.parse(f"always[0,{stl.MAX_WINDOW_STEPS}](x > 0)")
  assert stl.OnlineMonitor.create(f).init(()).window == {} and stl.ast.window_span(f) == stl.MAX_WINDOW_STEPS


def test_long_chain_spec_compiles_and_monitors():
  table = specs.add_spec(specs.drone_specs(), "S13", "always(" + " and ".join(["altitude > 1"] * 1000) + ")")
  ev = specs.compile_specs(table, 0.1)
  _, rob, _ = ev.monitor_update(ev.monitor_init(()), {n: jnp.float32(5.0) for n in ev.signals})
  assert rob.shape == (13,) and float(rob[-1]) == 4.0


@pytest.mark.parametrize("build, err, pattern", [
    (lambda: specs.drone_specs({"SG_ACCEL_TIME": 1e6}), SpecError,
     r"spec S7: .*10,000,000 steps at dt=0.1 s.*\(its parameters: .*SG_ACCEL_TIME=1e\+06"),
    (lambda: specs.rover_specs({"SG_ACCEL_TIME": 1e3}), SpecError, "spec S7: .*10,000 steps"),
    (lambda: specs.drone_specs({"MPC_XY_VEL_MIN": 20.0}), SpecError,
     "MPC_XY_VEL_MIN = 20 m/s must be below MPC_XY_VEL_MAX = 12 m/s"),
    (lambda: specs.drone_specs({"NAV_MIN_LTR_ALT": 20.0}), SpecError,
     "NAV_MIN_LTR_ALT = 20 m must be below MIS_TAKEOFF_ALT = 20 m"),
    (lambda: specs.with_params(specs.rover_specs(), {"CRUISE_SPEED_MIN": 13}), SpecError,
     "CRUISE_SPEED_MIN = 13 m/s must be below CRUISE_SPEED_MAX = 12"),
    (lambda: specs.add_spec(specs.drone_specs(), "S13", "not " * 500 + "(altitude > 1)"), SpecError,
     "spec S13 .*112 levels"),
    (lambda: specs.add_spec(specs.drone_specs(), "S13", "always(altitude > CP_DIST)", params={"CP_DIST": -1}),
     SpecError, "CP_DIST: value -1.0 m is outside.*disabled"),
], ids=["SG_ACCEL_TIME=1e6", "rover SG_ACCEL_TIME=1e3", "min speed above max", "min altitude = max",
        "rover min speed above max", "spec of 500 nots", "add_spec CP_DIST=-1"])
def test_bad_spec_tables_are_refused_before_tracing(build, err, pattern):
  with pytest.raises(err, match=pattern) as e:
    specs.compile_specs(build(), 0.1)
  _one_line(e)


@pytest.mark.parametrize("name, text, pattern", [
    ("s.specs", "param CP_DIST = -1\nspec S13: always(altitude > CP_DIST)\n", r"CP_DIST \(.*s.specs:1\).*outside"),
    ("s.json", json.dumps({"params": {"CP_DIST": -1}, "specs": []}), "CP_DIST.*outside"),
    ("s.json", "[1, 2]", "expected a JSON object"),
    ("s.json", json.dumps({"specs": [1]}), "spec #0 is a JSON int"),
    ("s.json", json.dumps({"specs": [{"name": "S13", "stl": "always(altitude > 1)", "k": "abc"}]}), "spec S13"),
    ("s.json", '{"a":' * 100_000 + "1" + "}" * 100_000, "unreadable JSON"),
    ("s.specs", b"spec S13: always(altitude > 1) # H\xf6he\nspec S14: always(altitud\xe9 > 1)\n", "s.specs:2"),
])
def test_bad_spec_files(tmp_path, name, text, pattern):
  p = tmp_path / name
  p.write_bytes(text if isinstance(text, bytes) else text.encode())
  with pytest.raises(SpecError, match=pattern) as e:
    specs.load_spec_file(str(p), specs.drone_specs())
  _one_line(e)


# --------------------------------------------------------------------------------------------------- parameter files

PX4_OK = "# Onboard parameters for Vehicle 1\n1\t1\tCP_DIST\t6.5\t9\n1\t1\tMPC_XY_VEL_MAX\t10.0\t9\n"
PARM_OK = "AVOID_MARGIN,4\nWPNAV_RADIUS 300  # cm\nFENCE_MARGIN\t2\n"

PARAMS_BAD = [
    # (case, contents, format, message pattern)
    ("garbage line", "CP_DIST,5\nhello world again\n", "parm", "p:2: cannot parse 'hello world again'"),
    ("word value", "CP_DIST,5\nFOO bar\n", "parm", r"FOO \(p:2\): value 'bar' is not a number"),
    ("bad name", "5,5\n", "parm", "p:1: '5' is not a parameter name"),
    ("PX4 line in .parm", "1\t1\tCP_DIST\t5\t9\n", "parm", "p:1: cannot parse"),
    ("PX4 type column", "1\t1\tCP_DIST\t5\txyz\n", "params", "p:1: .*integer SYS, COMP and TYPE"),
    ("binary", bytes(range(256)), "parm", "p:1: non-ASCII or control character"),
    ("Latin-1 in a name", "CP_D\xcfST,5\n".encode("latin-1"), "parm", "p:1: non-ASCII"),
    ("duplicate", "CP_DIST,5\nFOO,1\nCP_DIST,7\n", "parm", "p:3: CP_DIST is set twice: 5 on line 1 and 7 on line 3"),
    ("duplicate unknown", "FOO,1\nFOO,1\n", "parm", "FOO is set twice"),
    ("PX4 -1 disabled", "1\t1\tCP_DIST\t-1\t9\n", "params", r"CP_DIST \(p:1\): value -1.0 m is outside.*disabled"),
    ("ArduPilot -1", "AVOID_MARGIN,-1\n", "parm", r"AVOID_MARGIN \(p:1\).*outside"),
    ("cm scale -1", "WPNAV_RADIUS,-1\n", "parm", "WPNAV_RADIUS.*outside"),
    ("nan", "CP_DIST,nan\n", "parm", "not finite"),
    ("1e999", "CP_DIST,1e999\n", "parm", "not finite"),
    ("unknown inf", "FOO,inf\n", "parm", r"FOO \(p:1\).*not finite"),
    ("min speed above max", "1\t1\tMPC_XY_VEL_MIN\t15\t9\n1\t1\tMPC_XY_VEL_MAX\t12\t9\n", "params",
     r"p: contradictory parameters: MPC_XY_VEL_MIN = 15 m/s \(line 1\) must be below MPC_XY_VEL_MAX = 12 m/s "
     r"\(line 2\)"),
    ("rover min above max", "CRUISE_SPEED_MIN,9\nCRUISE_SPEED_MAX,8\n", "parm", "CRUISE_SPEED_MIN = 9 m/s"),
]


@pytest.mark.parametrize("data, fmt, pattern", [c[1:] for c in PARAMS_BAD], ids=[c[0] for c in PARAMS_BAD])
def test_bad_parameter_files(data, fmt, pattern):
  with pytest.raises(SpecError, match=pattern) as e:
    specs.loads_params(data, fmt, name="p")
  _one_line(e)


def test_parameter_file_encodings_and_unknown_names(tmp_path):
  p = tmp_path / "drone.params"
  p.write_bytes(b"\xef\xbb\xbf" + "# H\xf6he\n".encode("latin-1") + PX4_OK.encode() + b"1\t1\tMPC_Z_P\t1.0\t9\n"
                + b"1\t1\tSYS_AUTOSTART\t4001\t6\n")
  with pytest.warns(ParamFileWarning, match=r"ignored 2 parameter\(s\) the specs do not use: MPC_Z_P, SYS_AUTOSTART"):
    assert specs.load_params_file(str(p)) == {"CP_DIST": 6.5, "MPC_XY_VEL_MAX": 10.0}
  many = "".join(f"X{k},1\n" for k in range(30))
  with pytest.warns(ParamFileWarning, match="ignored 30 .*X19 and 10 more") as w:
    specs.loads_params(many, "parm")
  assert len(w) == 1
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert specs.loads_params("\ufeff" + PARM_OK, "parm") == {"AVOID_MARGIN": 4.0, "WPNAV_RADIUS": 3.0,
                                                             "FENCE_MARGIN": 2.0}
  with pytest.raises(SpecError, match="cannot read parameter file"):
    specs.load_params_file(str(tmp_path))


# ------------------------------------------------------------------------------------------------------ mission files


def _plan(edit):
  doc = json.loads(PLAN)
  edit(doc)
  return json.dumps(doc)


def _param(k, j, v):
  return lambda doc: doc["mission"]["items"][k]["params"].__setitem__(j, v)


def _home(v):
  return lambda doc: doc["mission"].__setitem__("plannedHomePosition", v)


def _wpl(*cells, text=WPL):
  rows = [r.split("\t") for r in text.splitlines()]
  for line, col, value in cells:
    rows[line][col] = value
  return "\n".join("\t".join(r) for r in rows) + "\n"


MISSIONS_BAD = [
    # (case, contents, format, vehicle, message pattern); WPL rows: 1 home, 2 take-off, 3-5 waypoints (5: AMSL)
    ("latitude 95", _plan(_param(2, 4, 95.0)), "plan", "drone", r"item 3: NAV_WAYPOINT lat 95.0.*\[-90, 90\]"),
    ("longitude 200", _plan(_param(2, 5, 200.0)), "plan", "drone", "lon 200.0 is outside"),
    ("1000 km away", _plan(_param(2, 4, 58.26)), "plan", "drone", "1001.8 km from home .at most 10 km"),
    ("12 km away", _plan(_param(2, 4, 49.37)), "plan", "drone", "12.2 km from home"),
    ("home latitude 91", _plan(_home([91.0, 1.0, 10])), "plan", "drone", "home position lat 91.0"),
    ("home altitude 1e5", _plan(_home([49.26, -123.2, 1e5])), "plan", "drone", "home altitude 100000.0 m AMSL"),
    ("NaN latitude", _plan(_param(2, 4, float("nan"))), "plan", "drone", r"item 3: param 5 \(latitude\) is NaN"),
    ("Infinity altitude", _plan(_param(2, 6, float("inf"))), "plan", "drone", r"param 7 \(altitude\) is Infinity"),
    ("-Infinity home", _plan(_home([49.26, float("-inf"), 0])), "plan", "drone",
     r"plannedHomePosition\[1\] \(longitude\) is -Infinity"),
    ("1e400 altitude", PLAN.replace("15\n", "1e400\n", 1), "plan", "drone", r"item 1: param 7 \(altitude\) is not fin"),
    ("huge integer", _plan(_param(2, 0, 10 ** 400)), "plan", "drone", "item 3: param 1 is not finite"),
    ("5000-digit integer", PLAN.replace('"version": 1', '"version": ' + "9" * 5000, 1), "plan", "drone",
     "unreadable JSON"),
    ("boolean altitude", _plan(_param(2, 6, True)), "plan", "drone", r"param 7 is not a number \(altitude\): boolean"),
    ("boolean home", _plan(_home([True, 1.0, 5])), "plan", "drone", r"plannedHomePosition\[0\] is not a number"),
    ("boolean command", _plan(lambda d: d["mission"]["items"][2].__setitem__("command", True)), "plan", "drone",
     "item 3: 'command' and 'frame' must be integers"),
    ("deep JSON object", '{"a":' * 100_000 + "1" + "}" * 100_000, "plan", "drone", "nested too deeply"),
    ("deep JSON list", "[" * 100_000 + "]" * 100_000, "plan", "drone", "nested too deeply"),
    ("JSON list", "[1, 2, 3]", "plan", "drone", "not a .plan object: the top level is a JSON list"),
    ("below ground, relative", _plan(_param(2, 6, -5.0)), "plan", "drone",
     "item 3: NAV_WAYPOINT altitude -5.00 m above home is not above the ground"),
    ("below ground, AMSL", _wpl((5, 10, "20.0")), "wpl", "drone",
     r"line 6: NAV_WAYPOINT altitude -60.00 m above home \(frame 0: 20 m AMSL, home at 80 m\)"),
    ("take-off at 5 km", _plan(_param(0, 6, 5000.0)), "plan", "drone", "NAV_TAKEOFF altitude 5000.00 m .* above 1000"),
    ("speed 1e6 m/s", _plan(_param(1, 1, 1e6)), "plan", "drone", "DO_CHANGE_SPEED speed must be > 0 and <= 30"),
    ("loiter 5000 s", _wpl((3, 3, "19"), (3, 4, "5000")), "wpl", "drone", "line 4: NAV_LOITER_TIME .* <= 3600 s"),
    ("loiter radius 1e6", _wpl((3, 3, "19"), (3, 4, "10"), (3, 6, "1e6")), "wpl", "drone", "radius .* wider than"),
    ("WPL latitude 95", _wpl((3, 8, "95.0")), "wpl", "drone", r"line 4: NAV_WAYPOINT lat 95.0"),
    ("WPL command 16.5", _wpl((3, 3, "16.5")), "wpl", "drone", "line 4: column 'command' must be an integer"),
    ("rover 1000 km away", _wpl((3, 8, "58.26"), text=ROVER_WPL), "wpl", "rover", "km from home"),
]


@pytest.mark.parametrize("text, fmt, vehicle, pattern", [c[1:] for c in MISSIONS_BAD], ids=[c[0] for c in MISSIONS_BAD])
def test_bad_mission_files(text, fmt, vehicle, pattern):
  with pytest.raises(MissionFileError, match=pattern) as e:
    mf.loads_mission(text, fmt, vehicle, name="m")
  _one_line(e)


def test_mission_file_format_detection_and_bom(tmp_path):
  p = tmp_path / "m.waypoints"
  p.write_text("[1, 2]")
  with pytest.raises(MissionFileError, match="m.waypoints: not a .plan object"):
    mf.load_mission(p, "drone")
  p = tmp_path / "m.plan"
  p.write_text("QGC WPL 110\n")   # a .plan is JSON whatever it holds
  with pytest.raises(MissionFileError, match="m.plan: line 1: not valid JSON"):
    mf.load_mission(p, "drone")
  p.write_bytes(b"\xef\xbb\xbf" + PLAN.encode())
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    assert int(mf.load_mission(p, "drone").n_waypoints) > 0


def test_mission_longer_than_the_episode_cap():
  text = _wpl((3, 3, "19"), (3, 4, "3000"))   # a 3000 s loiter: about 3093 s nominal
  with pytest.warns(MissionFileWarning, match=r"m: the mission's nominal duration 3093 s exceeds the episode cap of "
                    r"400 s"):
    m = mf.loads_mission(text, "wpl", "drone", name="m")
  assert float(m.loiter_time) == 3000.0
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    mf.loads_mission(text, "wpl", "drone", name="m", max_episode_s=3100.0)
  with pytest.raises(MissionFileError, match="m: the mission's nominal duration 3093 s exceeds the episode cap") as e:
    mf.loads_mission(text, "wpl", "drone", name="m", strict=True)
  _one_line(e)


# -------------------------------------------------------------------------------------------- property-based tests

STL_TOKENS = ["x", "y", "A", ">", "<", ">=", "<=", "0", "1.5", "2e3", "1e999", "inf", "nan", "(", ")", "[", "]", ",",
              ":", "not", "and", "or", "->", "until", "always", "eventually", "G", "F", "-", "+", "*", "/", "s", "ms",
              "1e9", "!", "&&", "||", "$"]


@PROPERTY
@given(st.one_of(st.text(max_size=40),
                 st.lists(st.sampled_from(STL_TOKENS), max_size=30).map(" ".join),
                 st.lists(st.sampled_from(STL_TOKENS), max_size=30).map("".join)))
def test_stl_parser_never_crashes(text):
  try:
    f = stl.parse(text, params={"A": 2.0})
  except stl.STLError:
    return
  try:
    g = stl.to_steps(f, 0.1)
  except stl.STLError:
    return
  assert stl.ast.window_span(g) <= stl.MAX_WINDOW_STEPS
  sig = {n: np.linspace(-2.0, 2.0, 5) for n in stl.signals_of(g)}
  assert np.shape(stl.robustness(g, sig)) == (5,)
  try:
    stl.OnlineMonitor.create(g)
  except stl.UnsupportedOnlineError:
    pass


NASTY = ["NaN", "Infinity", "-Infinity", "1e999", "true", "false", "null", "[", "]", "{", "}", '"', ",", ":", "-",
         "-1", "0", "1e308", "9" * 30, "\t", "\n", "\r\n", "[[[[[[[[", "16", "17", "19", "20", "21", "22", "178",
         "0.5", "95", "200", "#", "\x00", "\xff", "\ufeff", " "]


@st.composite
def _mutated(draw, bases):
  """A valid file with 1-3 random edits: a span of up to 12 characters replaced by a nasty token or random text."""
  text = draw(st.sampled_from(bases))
  for _ in range(draw(st.integers(1, 3))):
    i = draw(st.integers(0, len(text)))
    j = draw(st.integers(i, min(len(text), i + 12)))
    text = text[:i] + draw(st.one_of(st.sampled_from(NASTY), st.text(max_size=6))) + text[j:]
  return text


def _load_mission(text, fmt, vehicle):
  with warnings.catch_warnings():
    warnings.simplefilter("ignore", MissionFileWarning)
    try:
      mf.loads_mission(text, fmt, vehicle, name="m")
    except MissionFileError:
      pass


@PROPERTY
@given(_mutated([PLAN]), st.sampled_from(["drone", "rover"]))
def test_mutated_plan_files_never_crash(text, vehicle):
  _load_mission(text, "plan", vehicle)


@PROPERTY
@given(_mutated([WPL, ROVER_WPL]), st.sampled_from(["drone", "rover"]))
def test_mutated_wpl_files_never_crash(text, vehicle):
  _load_mission(text, "wpl", vehicle)


@pytest.fixture(scope="module")
def byte_dir(tmp_path_factory):
  return tmp_path_factory.mktemp("bytes")


@settings(PROPERTY, max_examples=100, suppress_health_check=[HealthCheck.too_slow,
                                                             HealthCheck.function_scoped_fixture])
@given(st.one_of(st.binary(max_size=200), _mutated([PLAN, WPL]).map(lambda t: t.encode("utf-8", "surrogatepass"))),
       st.sampled_from(["m.plan", "m.waypoints", "m.txt"]))
def test_random_mission_bytes_never_crash(byte_dir, data, fname):
  p = byte_dir / fname
  p.write_bytes(data)
  with warnings.catch_warnings():
    warnings.simplefilter("ignore", MissionFileWarning)
    try:
      mf.load_mission(p, "drone")
    except MissionFileError:
      pass


@PROPERTY
@given(st.one_of(st.binary(max_size=200), _mutated([PX4_OK, PARM_OK])), st.sampled_from(["params", "parm"]))
def test_random_parameter_files_never_crash(data, fmt):
  with warnings.catch_warnings():
    warnings.simplefilter("ignore", ParamFileWarning)
    try:
      got = specs.loads_params(data, fmt)
    except SpecError:
      return
  assert all(np.isfinite(v) for v in got.values())
