"""A normal run's output: no notices about MJX's absent Warp backend, no Orbax save-wait warnings, "-" for metrics
not defined yet and a line before each compile."""

import logging
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_importing_the_trainer_and_envs_prints_no_warp_notice():
  code = "import specguard_jax.ppo.runner, envs; print('imported')"
  p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                     env=dict(os.environ, JAX_PLATFORMS="cpu"))
  assert p.returncode == 0, p.stderr[-2000:]
  assert p.stdout == "imported\n" and "Failed to import" not in p.stderr, (p.stdout, p.stderr[-2000:])


def test_orbax_save_wait_warning_dropped_others_kept(caplog):
  from absl import logging as absl_logging

  from specguard_jax import third_party
  third_party.quiet_checkpoint_logging()
  third_party.quiet_checkpoint_logging()   # idempotent: one filter
  assert sum(isinstance(f, third_party._DropOrbaxSaveWait) for f in logging.getLogger("absl").filters) == 1
  with caplog.at_level(logging.WARNING):
    absl_logging.warning("Waiting for previous save to complete took %f seconds. If this number is high, ...", 2.0)
    absl_logging.warning("some other warning")
  assert [r.getMessage() for r in caplog.records] == ["some other warning"]


def test_progress_prints_dash_for_undefined_metrics_and_a_compile_line(capsys):
  from specguard_jax.ppo import runner
  bar = runner._Progress(True)
  bar.compiling("phase 1")
  bar.show(1, 100, 1000, 5000.0, float("nan"), float("nan"), float("nan"), force=True)
  bar.show(1, 200, 1000, 5000.0, 0.25, 0.75, 12.5, force=True)
  lines = capsys.readouterr().err.replace("\r", "\n").split("\n")
  lines = [x for x in lines if x]
  assert lines[0] == "compiling phase 1 (first run takes a while; cached afterwards)"
  assert "nan" not in lines[1] and lines[1].endswith("SVR     -  RSR     -  return        -"), lines[1]
  assert lines[2].endswith("SVR 0.250  RSR 0.750  return    12.50"), lines[2]
  runner._Progress(False).compiling("phase 2")
  assert capsys.readouterr().err == ""
