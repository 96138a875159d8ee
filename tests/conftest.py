"""Shared pytest setup: CPU by default; tests marked `gpu` are skipped where no GPU is present."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("SPECGUARD_COMPILE_CACHE", "off")   # CLIs called in-process must not write ~/.cache
# Cheaper XLA:CPU compiles: the suite's time is compiling programs that then run a few tiny steps. LLVM at -O0 without
# its expensive passes and the older elemental emitters instead of the fusion emitters compile a drone env step ~3x
# faster (16 -> 6 s on the 2-core machine); the same float semantics (no fast math either way). Subprocesses inherit
# it. Opt out with SPECGUARD_TEST_FAST_COMPILE=0.
FAST_COMPILE_FLAGS = ("--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true "
                      "--xla_cpu_use_fusion_emitters=false")
if os.environ["JAX_PLATFORMS"] == "cpu" and os.environ.get("SPECGUARD_TEST_FAST_COMPILE", "1") != "0":
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + FAST_COMPILE_FLAGS).strip()

import jax  # noqa: E402
import pytest  # noqa: E402


def pytest_collection_modifyitems(config, items):
  if jax.default_backend() == "gpu":
    return
  skip = pytest.mark.skip(reason="needs a GPU")
  for item in items:
    if "gpu" in item.keywords:
      item.add_marker(skip)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_code():
  """Drop each module's compiled executables when it ends. XLA:CPU maps every executable's code into memory; a whole
  suite in one process otherwise climbs past the kernel's 65,530-mapping limit and LLVM aborts mid-compile."""
  yield
  import gc
  jax.clear_caches()
  gc.collect()
