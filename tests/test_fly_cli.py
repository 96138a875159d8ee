"""`python -m envs.fly`: JSON output, QGroundControl mission files end to end, plots, one-line errors."""

import json
import os

import pytest

from envs import fly

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "envs", "data")


def test_fly_rover_mission_file_json_and_plot(tmp_path, capsys):
  png = tmp_path / "loop.png"
  rc = fly.main(["--vehicle", "rover", "--world", "urban_park", "--missions", "2",
                 "--mission", os.path.join(DATA, "rover_loop.waypoints"), "--plot", str(png), "--json"])
  assert rc == 0
  out = json.loads(capsys.readouterr().out)
  for key in ("completion_rate", "collisions", "geofence_entries", "crashes", "stalls", "nan_resets"):
    assert key in out
  assert out["completion_rate"] == 1.0 and out["collisions"] == 0 and out["geofence_entries"] == 0
  assert png.stat().st_size > 10_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("argv, message", [
    (["--world", "moon"], "unknown world 'moon'"),
    (["--missions", "0"], "--missions must be >= 1"),
    (["--mission", "/nonexistent.plan"], "mission file not found"),
])
def test_bad_arguments_one_line(argv, message, capsys):
  with pytest.raises(SystemExit) as e:
    fly.main(argv)
  assert e.value.code == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert message in err[-1]


def test_broken_mission_file_one_line(tmp_path, capsys):
  bad = tmp_path / "bad.waypoints"
  bad.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\tnot-a-number\t8.5\t10\t1\n")
  rc = fly.main(["--vehicle", "rover", "--mission", str(bad)])
  assert rc == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("error:") and "bad.waypoints" in err[0]


def test_fly_own_plan_through_an_exclusion_zone_with_params(tmp_path, capsys):
  """A 14-waypoint rover plan (more than the generated missions' 12 slots) whose route crosses its own exclusion
  polygon counts a geofence entry; the parameter file's CRUISE_SPEED sets the speed, its fence the home circle."""
  from envs import mission_files as mf
  home = (49.2606, -123.2460, 80.0)
  ll = lambda x, y: [float(v) for v in mf.enu_to_latlon(x, y, home[0], home[1])]  # noqa: E731
  items = [{"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0, None, *ll(5.0 * k, 0.0), 0],
            "autoContinue": True} for k in range(1, 15)]
  plan = {"fileType": "Plan", "version": 1,
          "mission": {"items": items, "plannedHomePosition": list(home), "version": 2},
          "geoFence": {"version": 2, "polygons": [{"inclusion": False, "version": 1,
                                                   "polygon": [ll(30, -5), ll(40, -5), ll(40, 5), ll(30, 5)]}]},
          "rallyPoints": {"version": 2, "points": [ll(0, 20) + [0]]}}
  path = tmp_path / "crossing.plan"
  path.write_text(json.dumps(plan))
  parm = tmp_path / "rover.parm"
  parm.write_text("CRUISE_SPEED 4.0\nWP_RADIUS 1.5\nFENCE_ENABLE 1\nFENCE_TYPE 2\nFENCE_RADIUS 300\nBRD_TYPE 3\n")
  png = tmp_path / "crossing.png"
  rc = fly.main(["--vehicle", "rover", "--world", "urban_park", "--missions", "1", "--mission", str(path),
                 "--params", str(parm), "--plot", str(png), "--json"])
  captured = capsys.readouterr()
  assert rc == 0, captured.err
  out = json.loads(captured.out)
  assert out["waypoints"] == 14 and out["geofence_entries"] == 1 and out["violations_per_spec"]["S12"] == 1
  assert out["completion_rate"] == 1.0 and out["collisions"] == 0
  assert 70 / 4.0 < out["mean_mission_time_s"] < 70 / 2.0     # 70 m at CRUISE_SPEED 4 m/s
  assert "BRD_TYPE" in captured.err and len(captured.err.strip().splitlines()) == 1   # the ignored names, one line
  assert png.stat().st_size > 10_000
