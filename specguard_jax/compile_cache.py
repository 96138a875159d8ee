"""JAX's persistent compilation cache for the CLIs (train.py, evaluate.py): XLA executables written to disk and
reused by the next process that compiles the same program on the same device kind and jax/jaxlib version.

Compiling, not flying, dominates short jobs: on a GPU `evaluate.py --suite paper` spends about as long compiling its
17 rollouts as flying 70,500 missions, and `train.py` compiles its two phases for minutes. A second run of
the same code (another seed, a sweep, the next evaluation of a new checkpoint: params are jit arguments, not
constants) reads the executables back instead, in seconds rather than a minute or more. Tracing and lowering
still run each time.

Where: `--compile-cache DIR` on the CLIs, else $SPECGUARD_COMPILE_CACHE, else $XDG_CACHE_HOME/specguard_jax/xla
(~/.cache/specguard_jax/xla). `off` (flag or variable) disables it. Entries are keyed by JAX on the program, the
compile options, the device and the jax/jaxlib versions, so a code change only misses; the directory may be
deleted at any time. The library itself never enables it (no global state on import); tests leave it off.
"""

from __future__ import annotations

import os

ENV_VAR = "SPECGUARD_COMPILE_CACHE"
OFF = ("off", "none", "0", "false", "")


def default_dir() -> str:
  """$SPECGUARD_COMPILE_CACHE if set (may be 'off'), else $XDG_CACHE_HOME/specguard_jax/xla."""
  if ENV_VAR in os.environ:
    return os.environ[ENV_VAR]
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return os.path.join(base, "specguard_jax", "xla")


def enable(path: str | None = None, *, min_compile_s: float = 1.0) -> str | None:
  """Point JAX's persistent compilation cache at `path` (None: default_dir()); 'off' disables it. Programs that
  compile faster than `min_compile_s` seconds are not stored. Returns the directory in use, or None when off.
  Raises ValueError (one line) when the directory cannot be created or written."""
  import jax
  path = default_dir() if path is None else path
  if path.strip().lower() in OFF:
    return None
  path = os.path.abspath(os.path.expanduser(path))
  try:
    os.makedirs(path, exist_ok=True)
  except OSError as e:
    raise ValueError(f"compile cache directory {path!r} cannot be created: {e.strerror}") from None
  if not os.access(path, os.W_OK):
    raise ValueError(f"compile cache directory {path!r} is not writable (pass --compile-cache off to disable)")
  jax.config.update("jax_compilation_cache_dir", path)
  jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
  jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
  return path
