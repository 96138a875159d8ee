"""The CLIs' persistent XLA compilation cache (specguard_jax/compile_cache.py): where it goes, 'off', bad
directories, and that a second process reads back what the first one wrote."""

import os
import subprocess
import sys

import pytest

from specguard_jax import compile_cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_PROG = """
import sys, time, jax, jax.numpy as jnp
from specguard_jax import compile_cache
hits = []
jax.monitoring.register_event_listener(lambda name, **kw: hits.append(name) if "cache_hits" in name else None)
print(compile_cache.enable(sys.argv[1], min_compile_s=0.0))
def f(x):
  for i in range(40):
    x = jnp.sin(x @ x.T + i)
  return x
t = time.perf_counter()
jax.jit(f).lower(jnp.ones((64, 64))).compile()
print('compile_s', time.perf_counter() - t)
print('hits', len(hits))
"""


def test_default_dir_follows_env(monkeypatch, tmp_path):
  monkeypatch.delenv(compile_cache.ENV_VAR, raising=False)
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
  assert compile_cache.default_dir() == os.path.join(str(tmp_path), "specguard_jax", "xla")
  monkeypatch.setenv(compile_cache.ENV_VAR, "off")
  assert compile_cache.default_dir() == "off"
  assert compile_cache.enable() is None
  assert compile_cache.enable("OFF") is None


def test_unusable_dir_is_one_line_error(tmp_path):
  blocker = tmp_path / "file"
  blocker.write_text("x")
  with pytest.raises(ValueError, match="cannot be created"):
    compile_cache.enable(str(blocker / "xla"))


def test_cli_rejects_unusable_dir(tmp_path):
  blocker = tmp_path / "file"
  blocker.write_text("x")
  r = subprocess.run([sys.executable, os.path.join(ROOT, "train.py"), "--compile-cache", str(blocker / "xla"),
                      "--steps", "1000", "--out", str(tmp_path / "run")], capture_output=True, text=True, cwd=ROOT,
                     env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=300)
  assert r.returncode == 2, r.stderr[-2000:]
  assert "compile cache directory" in r.stderr and len(r.stderr.strip().splitlines()) == 1
  assert not (tmp_path / "run").exists()


def test_second_process_reads_back(tmp_path):
  d = tmp_path / "xla"
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
  runs = [subprocess.run([sys.executable, "-c", _PROG, str(d)], capture_output=True, text=True, env=env,
                         timeout=300) for _ in range(2)]
  for r in runs:
    assert r.returncode == 0, r.stderr[-2000:]
  assert runs[0].stdout.splitlines()[0] == str(d)
  entries = sorted(os.listdir(d))
  assert entries, "the first process wrote no cache entry"
  hits = [int(r.stdout.split("hits")[-1]) for r in runs]
  assert hits[0] == 0 and hits[1] >= 1, hits    # the second process read the first one's executables back
  assert sorted(os.listdir(d)) == entries          # and wrote nothing new
