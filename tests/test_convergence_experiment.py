"""experiments/convergence.py (the paper's Fig. 3a protocol) on constructed metrics.jsonl files."""

import json
import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "experiments"))
import convergence  # noqa: E402


def _run(tmp_path, name, returns, window=2, eps=1e-3, every=1):
  """A run dir: 3 phase-1 iterations, then one phase-2 iteration per return, 100 env steps each at 100 steps/s."""
  d = tmp_path / name
  d.mkdir()
  rows = [{"phase": 1, "iteration": i + 1, "env_steps": 100 * (i + 1), "sps": 50.0, "return": 0.0} for i in range(3)]
  # phase 2's first call (its first iteration here) logs its steps over compile + run: 1 step/s
  rows += [{"phase": 2, "iteration": i + 1, "env_steps": 300 + 100 * (i + 1), "sps": 1.0 if i == 0 else 100.0,
            "first_call": i == 0, "return": r, "return_aa": -r, "svr": 0.1 * (i + 1)} for i, r in enumerate(returns)]
  (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
  (d / "config.json").write_text(json.dumps({"converge_window": window, "converge_eps": eps, "iters_per_call": every}))
  return str(d)


def test_first_iteration_of_the_stop_rule_its_steps_and_seconds(tmp_path):
  settles = _run(tmp_path, "rc", [50, 40, 30, 20, 10, 10, 10, 10, 10, 10, 10, 10])
  climbs = _run(tmp_path, "pc", [10.0 * i for i in range(1, 13)])
  out = str(tmp_path / "out.json")
  assert convergence.main(["--runs", f"rc={settles}", f"pc={climbs}", "--json", out]) == 0
  res = json.load(open(out))
  # iterations 5-8 all return 10: the two last windows of 2 agree at iteration 8
  assert res["rc"]["iteration"] == 8 and res["rc"]["env_steps"] == 800 and res["rc"]["train_s"] == pytest.approx(8.0)
  assert res["rc"]["return"] == 10.0 and res["rc"]["svr"] == pytest.approx(0.75)   # iterations 7 and 8
  assert res["pc"]["iteration"] is None and res["pc"]["train_s"] == pytest.approx(12.0)
  assert res["pc"]["phase2_iterations"] == 12
  # a wider window from the command line: 4 + 4 equal returns needed, iterations 5-12
  assert convergence.time_to_convergence(convergence.load_run(settles)["rows"], 4, 1e-3)["iteration"] == 12
  # checked where the trainer checks it: after each call of iters_per_call (4) iterations
  early = [50, 40, 10, 10, 10, 10, 10, 10]
  assert convergence.time_to_convergence(convergence.load_run(_run(tmp_path, "a", early))["rows"], 2, 1e-3,
                                         )["iteration"] == 6
  run = convergence.load_run(_run(tmp_path, "b", early, every=4))
  assert run["every"] == 4 and convergence.time_to_convergence(run["rows"], 2, 1e-3, 4)["iteration"] == 8


def test_bad_runs_are_one_line_errors(tmp_path, capsys):
  with pytest.raises(SystemExit) as e:
    convergence.main(["--runs", f"x={tmp_path / 'missing'}"])
  assert e.value.code == 2 and "metrics.jsonl: cannot read the run's metrics" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    convergence.main(["--runs", "no_equals_sign"])
  assert "expected NAME=DIR" in capsys.readouterr().err
