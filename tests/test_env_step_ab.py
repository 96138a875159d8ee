"""bench/env_step_ab.py: trees from git revisions, each timed in its own process, one line per tree."""

import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(ROOT, "bench", "env_step_ab.py")


def _run(*args, timeout=600):
  return subprocess.run([sys.executable, BENCH, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def test_a_tree_of_head_times_its_env_step(tmp_path):
  made = _run("--make-trees", str(tmp_path), "HEAD")
  assert made.returncode == 0, made.stderr
  tree = tmp_path / "HEAD"
  assert (tree / "specguard_jax" / "stl").is_dir() and (tree / "envs" / "base.py").is_file()
  r = _run(str(tree), "--vehicle", "rover", "--envs", "4", "--steps", "2", "--calls", "1")
  assert r.returncode == 0, r.stderr
  line = r.stdout.strip().splitlines()[-1]
  assert re.fullmatch(r"HEAD rover 4: [0-9.]+ ms per env step \(first call [0-9.]+ s\), obs sum [-0-9.e+]+, "
                      r"reward sum [-0-9.e+]+", line), line


def test_a_directory_without_the_library_is_a_one_line_error(tmp_path):
  r = _run(str(tmp_path))
  assert r.returncode == 2 and f"{tmp_path}: not a source tree" in r.stderr.strip().splitlines()[-1]
  r = _run("--make-trees", str(tmp_path))
  assert r.returncode == 2 and "--make-trees needs DIR and at least one REV" in r.stderr
