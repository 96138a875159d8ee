"""Shared pytest setup: CPU by default; tests marked `gpu` are skipped where no GPU is present."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("SPECGUARD_COMPILE_CACHE", "off")   # CLIs called in-process must not write ~/.cache

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
