"""Where the shipped data files are: the MJCF models (drone.xml, rover.xml), the detector presets
(detector_<vehicle>.json) and the fitted dynamics (dynamics_<vehicle>.json).

They live in the repository's top-level assets/. A checkout (editable install, PYTHONPATH, `python train.py`) reads
them there; a built wheel carries the same files inside the package as specguard_jax/_assets/ (setup.py maps that
package onto assets/). The package's own location decides which, so code imported from a worktree reads that
worktree's assets, never those of another checkout that happens to be installed. MuJoCo reads models from a file
system path, and wheels install unzipped, so the paths here are plain file names.
"""

from __future__ import annotations

import os

_PACKAGE = os.path.dirname(os.path.abspath(__file__))
_INSTALLED = os.path.join(_PACKAGE, "_assets")                       # wheel: site-packages/specguard_jax/_assets
_CHECKOUT = os.path.join(os.path.dirname(_PACKAGE), "assets")       # checkout: <repo>/assets

ASSETS_DIR = _INSTALLED if os.path.isdir(_INSTALLED) else _CHECKOUT


def asset_path(name: str) -> str:
  """The path of the shipped asset `name` (e.g. "drone.xml", "detector_rover.json")."""
  return os.path.join(ASSETS_DIR, name)
