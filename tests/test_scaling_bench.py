"""bench/scaling.py --memory-plan: XLA's memory plan of init and one training call, compiled and never run."""

import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))

import scaling  # noqa: E402


def test_memory_plan_reports_both_programs(tmp_path, capsys):
  assert scaling.main(["--smoke", "--no-throughput", "--memory-plan", "--phases", "1", "--devices", "1",
                       "--out", str(tmp_path)]) == 0
  (row,) = json.load(open(tmp_path / "scaling.json"))["memory_plan"]
  assert row["envs"] == 16 and row["phase"] == 1
  assert row["init_temp"] > 0 and row["run_temp"] > 0
  # the training call's arguments are the carry init makes (donated and aliased), on one device all of it
  assert row["run_carry"] == row["carry_bytes_global"]
  assert abs(row["init_output"] - row["run_carry"]) < 0.01 * row["run_carry"]   # init's output buffers: the carry
  assert row["peak"] == max(row["init_temp"] + row["init_output"], row["run_temp"] + row["run_carry"])
  assert "| 16 | 1 |" in capsys.readouterr().out
