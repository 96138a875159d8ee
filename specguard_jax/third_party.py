"""Third-party imports and logging with the notices that do not concern this project filtered out, each narrowly:

- mujoco.mjx prints "Failed to import warp: ..." and "Failed to import mujoco_warp: ..." on stdout when its optional
  Warp backend (NVIDIA Warp, not a dependency: the env runs on MJX's JAX backend) is not installed. Importing this
  module imports mujoco.mjx once with exactly those lines dropped; any other output of the import passes through.
  Import it before anything that imports mujoco.mjx (brax, envs).
- `quiet_checkpoint_logging()`: Orbax's CheckpointManager warns through absl logging that "Waiting for previous save
  to complete took N seconds" whenever the caller waited for the last save, as the trainer does on purpose after every
  save (a checkpoint on disk before training goes on); that one message is dropped, every other Orbax log passes.
"""

from __future__ import annotations

import contextlib
import io
import logging
import sys

WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")
ORBAX_SAVE_WAIT = "Waiting for previous save to complete took"


def _import_mjx() -> None:
  if "mujoco.mjx" in sys.modules:
    return
  out = io.StringIO()
  try:
    with contextlib.redirect_stdout(out):
      import mujoco.mjx  # noqa: F401, PLC0415
  finally:
    sys.stdout.write("".join(line for line in out.getvalue().splitlines(keepends=True)
                             if not line.startswith(WARP_NOTICES)))


class _DropOrbaxSaveWait(logging.Filter):
  def filter(self, record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith(ORBAX_SAVE_WAIT)


def quiet_checkpoint_logging() -> None:
  """Drops Orbax's "Waiting for previous save to complete" warning (absl's Python logger "absl"); idempotent."""
  logger = logging.getLogger("absl")
  if not any(isinstance(f, _DropOrbaxSaveWait) for f in logger.filters):
    logger.addFilter(_DropOrbaxSaveWait())


_import_mjx()
