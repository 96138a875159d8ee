"""Repository hygiene: comments, docstrings and documents say what and why, not which work session measured what.

Dated, numbered history belongs in CHANGELOG.md alone; every other tracked file is read as the current state of the
project, so a "session N" label there is a leftover of that history."""

import os
import re
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SESSION_LABEL = re.compile(r"sessions?[\s-]+\d+", re.IGNORECASE)
ALLOWED = {"CHANGELOG.md"}


def _tracked_files():
  """Paths (relative to the repository root) of git's tracked files; skips the test outside a git checkout."""
  if shutil.which("git") is None:
    pytest.skip("git is not installed")
  r = subprocess.run(["git", "-C", ROOT, "ls-files", "-z"], capture_output=True)
  if r.returncode != 0:
    pytest.skip("not a git checkout")
  return [p for p in r.stdout.decode("utf-8", "surrogateescape").split("\0") if p]


def test_no_session_labels_outside_the_changelog():
  hits = []
  for rel in _tracked_files():
    if rel in ALLOWED:
      continue
    path = os.path.join(ROOT, rel)
    if not os.path.isfile(path):     # deleted in the work tree but still tracked, or a submodule
      continue
    with open(path, "rb") as f:
      data = f.read()
    if b"\0" in data:                # binary
      continue
    for n, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
      m = SESSION_LABEL.search(line)
      if m:
        hits.append(f"{rel}:{n}: {m.group(0)!r}")
  assert not hits, f"{len(hits)} 'session N' label(s) outside CHANGELOG.md:\n" + "\n".join(hits)


@pytest.mark.parametrize("name, budget", [("README.md", 150), ("BENCHMARKS.md", 300)])
def test_front_documents_keep_their_line_budgets(name, budget):
  """README.md is the front door (what, the two commands, results, usage, map); BENCHMARKS.md holds the latest table of
  each goal, not their history."""
  with open(os.path.join(ROOT, name), encoding="utf-8") as f:
    n = sum(1 for _ in f)
  assert n <= budget, f"{name} has {n} lines; its budget is {budget}"


def test_readme_starts_with_the_commands_ci_runs():
  """The README's first commands are the ones a newcomer types, and .ci/run runs the second one (quietly)."""
  with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
    readme = f.read()
  with open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8") as f:
    ci = f.read()
  block = readme.split("```bash\n", 1)[1].split("```", 1)[0].strip().splitlines()
  assert block[0] == "pip install -e . && python train.py"
  assert block[1] in [line.replace(" --quiet", "") for line in ci.splitlines()]
