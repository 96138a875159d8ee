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
