"""The shipped system-identification models as JSON: save and load them.

The env's state reconstruction (EnvConfig.reconstruction) needs fitted DynParams at construction time. Fitting is
cheap (one ridge solve) but recording the flights costs a compile and some simulation, so the fitted weights are
shipped as constants in assets/dynamics_<vehicle>.json and regenerated (calibration.dynamics_fit) with

  python tools/fit_dynamics.py --vehicle drone --missions 16 --seconds 40
  python tools/fit_dynamics.py --vehicle rover --missions 16 --seconds 40

(seeded; the file records the seed, missions, worlds and training residuals).
"""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np

from specguard_jax import assets
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.types import VEHICLES



def default_path(vehicle: str) -> str:
  return assets.asset_path(f"dynamics_{vehicle}.json")


def save_params(params: dyn.DynParams, path: str, meta: dict | None = None) -> None:
  """Write fitted DynParams and `meta` (how they were fitted) as JSON."""
  out = {k: np.asarray(getattr(params, k)).tolist() for k in ("w_lin", "w_ang", "rms_lin", "rms_ang")}
  out["meta"] = meta or {}
  with open(path, "w") as f:
    json.dump(out, f, indent=1)


def load_params(path: str, n_controls: int | None = None) -> dyn.DynParams:
  """DynParams from a JSON file written by save_params; one-line ValueError if missing or malformed."""
  try:
    with open(path) as f:
      d = json.load(f)
    p = dyn.DynParams(**{k: jnp.asarray(np.asarray(d[k], np.float32)) for k in ("w_lin", "w_ang", "rms_lin",
                                                                                 "rms_ang")})
  except (OSError, KeyError, TypeError, ValueError) as e:
    raise ValueError(f"cannot load dynamics model {path}: {type(e).__name__}: {e}") from None
  f_lin = 2 * (n_controls or 0) + 10
  if p.w_lin.shape[0] != 3 or p.w_ang.shape[0] != 3 or (n_controls and p.w_lin.shape[1] != f_lin):
    raise ValueError(f"dynamics model {path} has shapes {p.w_lin.shape}/{p.w_ang.shape}, expected [3, {f_lin}] "
                     f"for {n_controls} controls")
  return p
