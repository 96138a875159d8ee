"""Up-front checks of the CLIs' paths, run before JAX starts or anything is built: a refused command writes nothing."""

from __future__ import annotations

import os
import tempfile


def check_output_dir(path: str, flag: str) -> None:
  """One-line ValueError unless `path` is a directory this process can create files in, or can be created: its
  nearest existing ancestor must be a writable directory. Probed with an anonymous temporary file (nothing is left
  behind, and nothing is created when the check fails); permission bits alone do not say it for root or on a
  read-only mount."""
  full = os.path.abspath(path)
  probe = full
  while not os.path.exists(probe):
    probe = os.path.dirname(probe)
  if not os.path.isdir(probe):
    where = "is a file" if probe == full else f"lies under the file {probe}"
    raise ValueError(f"{flag} {path} {where}; give a directory")
  try:
    with tempfile.TemporaryFile(dir=probe):
      pass
  except OSError as e:
    raise ValueError(f"{flag} {path}: cannot write in {probe} ({e.strerror or e})") from None
