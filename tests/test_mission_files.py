"""QGroundControl mission files: example files, coordinate round trips, and clear errors for broken files."""

import json
import math
import pathlib

import jax
import numpy as np
import pytest

from envs import mission_files as mf
from envs.mission_files import MissionFileError, load_mission, loads_mission
from envs.missions import MAX_WAYPOINTS, MissionConfig, generate_mission

DATA = pathlib.Path(__file__).resolve().parents[1] / "envs" / "data"
HOME = (49.2606, -123.2460, 80.0)


def _np(m):
  return jax.tree.map(np.asarray, m)


def test_example_drone_plan():
  m = _np(load_mission(DATA / "drone_inspection.plan", "drone"))
  assert m.n_waypoints == 5 and m.waypoints.shape == (MAX_WAYPOINTS, 3)
  np.testing.assert_allclose(m.waypoints[:5], [[60, 0, 15], [130, 30, 15], [170, 100, 16], [120, 160, 16],
                                               [40, 140, 14]], atol=1e-3)
  np.testing.assert_allclose(m.waypoints[5:], np.broadcast_to(m.waypoints[4], (7, 3)))
  assert m.takeoff_alt == 15.0 and m.cruise_speed == 8.0 and m.land == 1.0
  assert m.loiter_wp == 3 and m.loiter_time == 20.0 and m.loiter_radius == 8.0
  np.testing.assert_array_equal(m.home, 0.0)
  assert np.all(np.diff(m.deadline[:5]) > 0)
  # deadlines as for generated missions: 1.5 * nominal arrival + 10 s
  arrival0 = 15.0 / 2.0 + 60.0 / 8.0
  assert m.deadline[0] == pytest.approx(1.5 * arrival0 + 10.0, rel=1e-5)
  assert m.window_open[0] == pytest.approx(0.5 * arrival0, rel=1e-5)


def test_example_drone_wpl():
  m = _np(load_mission(str(DATA / "drone_patrol.waypoints"), "drone"))
  # 4 waypoints + RTL (above home at the last altitude) and a landing there; wp 3 is in frame 0 (AMSL 95 m)
  assert m.n_waypoints == 5 and m.land == 1.0 and m.takeoff_alt == 18.0 and m.loiter_wp == -1
  np.testing.assert_allclose(m.waypoints[:5], [[0, 90, 18], [70, 150, 18], [150, 150, 15], [170, 40, 15],
                                               [0, 0, 15]], atol=1e-3)
  assert m.cruise_speed == pytest.approx(8.0)  # middle of MissionConfig.drone().cruise_speed


def test_example_rover_wpl():
  m = _np(load_mission(DATA / "rover_loop.waypoints", "rover"))
  assert m.n_waypoints == 6 and m.land == 0.0 and m.takeoff_alt == 0.0 and m.cruise_speed == 7.0
  np.testing.assert_allclose(m.waypoints[:6, :2], [[50, 0], [100, 40], [100, 110], [40, 140], [-10, 90], [0, 0]],
                             atol=1e-3)
  np.testing.assert_array_equal(m.waypoints[:, 2], 0.0)
  with pytest.raises(MissionFileError, match=r"drone_inspection.plan: item 1: NAV_TAKEOFF is not supported"):
    load_mission(DATA / "drone_inspection.plan", "rover")


def test_latlon_projection():
  # 1 arc-minute of latitude is ~1852 m (on the 6378137 m sphere: 1855.3 m); east scales with cos(lat)
  x, y = mf.latlon_to_enu(HOME[0] + 1 / 60, HOME[1] + 1 / 60, HOME[0], HOME[1])
  assert float(y) == pytest.approx(6378137.0 * math.radians(1 / 60), rel=1e-9)
  assert float(x) == pytest.approx(float(y) * math.cos(math.radians(HOME[0])), rel=1e-9)
  lat, lon = mf.enu_to_latlon(x, y, HOME[0], HOME[1])
  assert float(lat) == pytest.approx(HOME[0] + 1 / 60, abs=1e-12)
  assert float(lon) == pytest.approx(HOME[1] + 1 / 60, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_generated_mission_round_trip(seed):
  cfg = MissionConfig.drone(p_loiter=0.6)
  m = _np(jax.jit(generate_mission, static_argnums=0)(cfg, jax.random.key(seed)))
  text = mf.to_wpl(m, *HOME)
  back = _np(loads_mission(text, "wpl", "drone", cfg))
  n = m.n_waypoints
  assert back.n_waypoints == n
  np.testing.assert_allclose(back.waypoints, m.waypoints, atol=2e-3)
  for f in ("takeoff_alt", "cruise_speed", "loiter_wp", "loiter_time", "land", "loiter_radius"):
    np.testing.assert_allclose(getattr(back, f), getattr(m, f), atol=1e-4, err_msg=f)
  np.testing.assert_allclose(back.deadline, m.deadline, rtol=1e-4)
  np.testing.assert_allclose(back.window_open, m.window_open, rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(back.nominal_duration, m.nominal_duration, rtol=1e-4)


def _wpl(*rows):
  head = "0\t1\t0\t16\t0\t0\t0\t0\t49.2606\t-123.246\t80\t1"
  return "\n".join(["QGC WPL 110", head, *rows]) + "\n"


WP1 = "1\t0\t3\t16\t0\t0\t0\t0\t49.2612\t-123.246\t15\t1"


@pytest.mark.parametrize("text, pattern", [
  ("QGC WPL 100\n", r"m.txt: line 1: missing header 'QGC WPL 110'"),
  ("", r"m.txt: line 1: empty file"),
  (_wpl("1\t0\t3\t16\t0\t0\t0\t0\t49.2612\t-123.246\t15"), r"m.txt: line 3: expected 12 tab-separated columns, got 11"),
  (_wpl("1\t0\t3\t16\t0\t0\t0\t0\tabc\t-123.246\t15\t1"), r"m.txt: line 3: column 'lat' is not a number: 'abc'"),
  (_wpl("1\t0\t3\t16\t0\t0\t0\t0\tnan\t-123.246\t15\t1"), r"m.txt: line 3: column 'lat' is not finite"),
  (_wpl("1\t0\t3\t84\t0\t0\t0\t0\t49.2612\t-123.246\t15\t1"), r"m.txt: line 3: unsupported command 84"),
  (_wpl("1\t0\t10\t16\t0\t0\t0\t0\t49.2612\t-123.246\t15\t1"), r"m.txt: line 3: unsupported frame 10"),
  (_wpl("2\t0\t3\t16\t0\t0\t0\t0\t49.2612\t-123.246\t15\t1"), r"m.txt: line 3: sequence number 2, expected 1"),
  (_wpl(), r"m.txt: empty mission"),
  (_wpl("1\t0\t3\t22\t0\t0\t0\t0\t0\t0\t15\t1"), r"m.txt: empty mission"),
  (_wpl("1\t0\t3\t16\t0\t0\t0\t0\t0\t0\t15\t1"), r"m.txt: line 3: NAV_WAYPOINT without coordinates"),
  (_wpl(WP1, "2\t0\t3\t21\t0\t0\t0\t0\t0\t0\t0\t1", "3\t0\t3\t16\t0\t0\t0\t0\t49.2615\t-123.246\t15\t1"),
   r"m.txt: line 5: NAV_WAYPOINT after NAV_LAND"),
  (_wpl(WP1, "2\t0\t3\t22\t0\t0\t0\t0\t0\t0\t15\t1"), r"m.txt: line 4: NAV_TAKEOFF must come before"),
  (_wpl(WP1, "2\t0\t3\t19\t0\t0\t0\t0\t0\t0\t15\t1"), r"m.txt: line 4: NAV_LOITER_TIME time .* must be > 0"),
])
def test_broken_wpl(tmp_path, text, pattern):
  p = tmp_path / "m.txt"
  p.write_text(text)
  with pytest.raises(MissionFileError, match=pattern) as e:
    load_mission(p, "drone")
  assert "\n" not in str(e.value)
  assert isinstance(e.value, ValueError)


def test_too_many_waypoints(tmp_path):
  rows = [f"{i}\t0\t3\t16\t0\t0\t0\t0\t{49.2606 + 0.0005 * i:.7f}\t-123.246\t15\t1" for i in range(1, 15)]
  p = tmp_path / "long.waypoints"
  p.write_text(_wpl(*rows))
  msg = r"long.waypoints: line 14: too many waypoints \(more than 11; the limit is load_mission's max_waypoints"
  with pytest.raises(MissionFileError, match=msg):
    load_mission(p, "drone", max_waypoints=11)
  m = load_mission(p, "drone")   # longer than the generated missions' slots: the array is the file's own length
  assert int(m.n_waypoints) == 14 and m.waypoints.shape == (14, 3) and m.deadline.shape == (14,)
  p.write_text(_wpl(*rows[:3]))
  assert load_mission(p, "drone").waypoints.shape == (MAX_WAYPOINTS, 3)   # short: the generated missions' shape


def test_home_at_zero(tmp_path):
  """A home at 0, 0 is taken from the first positioned item, with one notice; a file whose first position is 0, 0
  itself (a simulator's frame around 0, 0) keeps zero coordinates as positions."""
  p = tmp_path / "m.txt"
  p.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t0\t0\t80\t1\n" + WP1
               + "\n2\t0\t3\t16\t0\t0\t0\t0\t49.2615\t-123.246\t15\t1\n")
  with pytest.warns(mf.MissionFileWarning, match=r"m.txt: home at lat = lon = 0 .*home taken from line 3"):
    m = _np(load_mission(p, "drone"))
  np.testing.assert_allclose(m.waypoints[:2, :2], [[0, 0], [0, 6378137.0 * math.radians(0.0003)]], atol=1e-3)
  rows = ["1\t0\t3\t16\t0\t0\t0\t0\t-0.0\t-0.0\t0.3\t1", "2\t0\t3\t16\t0\t0\t0\t0\t0.0002\t0\t0.3\t1",
          "3\t0\t3\t16\t0\t0\t0\t0\t0.0002\t-0.0003\t0.3\t1"]
  p.write_text("QGC WPL 110\n0\t0\t0\t16\t0\t0\t0\t0\t0\t0\t-0.13\t1\n" + "\n".join(rows) + "\n")
  with pytest.warns(mf.MissionFileWarning, match="zero coordinates are positions"):
    m = _np(load_mission(p, "rover"))
  assert m.n_waypoints == 3
  np.testing.assert_allclose(m.waypoints[:3, :2], [[0, 0], [0, 22.26], [-33.40, 22.26]], atol=0.01)


def _plan(items, home=(49.2606, -123.246, 80.0)):
  return json.dumps({"fileType": "Plan", "version": 1,
                     "mission": {"items": items, "plannedHomePosition": list(home), "version": 2}})


def _item(cmd, params, frame=3):
  return {"type": "SimpleItem", "command": cmd, "frame": frame, "params": params, "autoContinue": True}


@pytest.mark.parametrize("text, pattern", [
  ("{not json", r"p.plan: line 1: not valid JSON"),
  (json.dumps({"fileType": "Mission"}), r"p.plan: not a QGroundControl plan"),
  (_plan([{"type": "ComplexItem", "complexItemType": "CorridorScan"}]),
   r"p.plan: item 1: ComplexItem of type 'CorridorScan' is not supported \(only 'survey'"),
  (_plan([{"type": "ComplexItem", "complexItemType": "StructureScan"}]),
   r"p.plan: item 1: ComplexItem of type 'StructureScan' is not supported"),
  (_plan([{"type": "ComplexItem", "complexItemType": "survey"}]), r"p.plan: item 1: survey 'polygon' must be"),
  (_plan([_item(16, [0, 0, 0, None, 49.2612, -123.246])]), r"p.plan: item 1: 'params' must be a list of 7"),
  (_plan([_item(16, [0, 0, 0, None, "x", -123.246, 15])]), r"p.plan: item 1: param 5 is not a number"),
  (_plan([_item(16, [0, 0, 0, None, 49.2612, -123.246, 15]), _item(31000, [0] * 7)]),
   r"p.plan: item 2: unsupported command 31000"),
  (_plan([]), r"p.plan: empty mission"),
  (_plan([_item(178, [1, 5, -1, 0, 0, 0, 0])], home=(0, 0, 0)), r"p.plan: home position has lat = lon = 0 and no item"),
])
def test_broken_plan(tmp_path, text, pattern):
  p = tmp_path / "p.plan"
  p.write_text(text)
  with pytest.raises(MissionFileError, match=pattern):
    load_mission(p, "drone")


def test_plan_features():
  items = [_item(16, [0, 0, 0, None, 49.2612, -123.246, 95], frame=0),   # AMSL 95 -> 15 m above home
           _item(17, [0, 0, -12, None, 49.2612, -123.245, 15])]         # unlimited loiter, radius 12
  m = _np(loads_mission(_plan(items), "plan", "drone"))
  assert m.n_waypoints == 2 and m.loiter_wp == 1 and m.loiter_radius == 12.0
  assert m.loiter_time == MissionConfig.drone().loiter_time[1]
  assert m.waypoints[0, 2] == pytest.approx(15.0) and m.takeoff_alt == pytest.approx(15.0)
  assert m.waypoints[0, 1] == pytest.approx(6378137.0 * math.radians(0.0006), rel=1e-6)
  with pytest.raises(MissionFileError, match="item 3: NAV_WAYPOINT after NAV_LOITER_UNLIM"):
    loads_mission(_plan(items + [_item(16, [0, 0, 0, None, 49.2615, -123.246, 15])]), "plan", "drone", name="q.plan")
  # landing away from the last waypoint adds a waypoint there at the current altitude
  items = [_item(22, [0, 0, 0, None, None, None, 20]), _item(16, [0, 0, 0, None, 49.2612, -123.246, 15]),
           _item(21, [0, 0, 0, None, 49.2612, -123.245, 0])]
  m = _np(loads_mission(_plan(items), "plan", "drone"))
  assert m.n_waypoints == 2 and m.land == 1.0 and m.takeoff_alt == 20.0 and m.waypoints[1, 2] == 15.0
  with pytest.raises(ValueError, match="cfg is for a drone"):
    loads_mission(_plan(items), "plan", "rover", MissionConfig.drone())
