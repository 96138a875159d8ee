"""The shipped system-identification models: fit on attack-free autopilot flights, save/load as JSON.

The env's state reconstruction (EnvConfig.reconstruction) needs fitted DynParams at construction time. Fitting is
cheap (one ridge solve) but recording the flights costs a compile and some simulation, so the fitted weights are
shipped as constants in assets/dynamics_<vehicle>.json and regenerated with

  python -m specguard_jax.estimation.model_file --vehicle drone --missions 16 --seconds 40
  python -m specguard_jax.estimation.model_file --vehicle rover --missions 16 --seconds 40

(seeded; the file records the seed, missions, worlds and training residuals).
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax.estimation import dynamics as dyn
from specguard_jax.types import VEHICLES

ASSETS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "assets")
FIT_WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")


def default_path(vehicle: str) -> str:
  return os.path.join(ASSETS, f"dynamics_{vehicle}.json")


def save_params(params: dyn.DynParams, path: str, meta: dict | None = None) -> None:
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


def fit_vehicle(vehicle: str, missions: int = 16, seconds: float = 40.0, seed: int = 0):
  """Record `missions` attack-free flights (worlds FIT_WORLDS round robin) and fit. Returns (DynParams, meta)."""
  import envs
  from envs import worlds as worlds_lib
  from envs.missions import MissionConfig
  from specguard_jax.estimation import traces

  mcfg = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      min_duration_s=seconds + 10.0, max_duration_s=seconds + 60.0)
  env = envs.make(vehicle, mission=mcfg)
  ids = jnp.asarray([worlds_lib.PRESET_NAMES.index(FIT_WORLDS[i % len(FIT_WORLDS)]) for i in range(missions)],
                    jnp.int32)
  n_ticks = int(round(seconds / env.config.tick_dt))
  tr = traces.record(env, jax.random.split(jax.random.PRNGKey(seed), missions), ids, n_ticks)
  params = dyn.fit_dynamics(tr, dt=env.config.tick_dt, airborne_only=(vehicle == "drone"))
  meta = {"vehicle": vehicle, "missions": missions, "seconds": seconds, "seed": seed, "worlds": list(FIT_WORLDS),
          "source": "ekf", "rms_lin_m_s2": np.asarray(params.rms_lin).tolist(),
          "rms_ang_rad_s2": np.asarray(params.rms_ang).tolist()}
  return params, meta


def main(argv=None):
  ap = argparse.ArgumentParser(description="fit and save the vehicle's dynamics model for state reconstruction")
  ap.add_argument("--vehicle", choices=VEHICLES, default="drone")
  ap.add_argument("--missions", type=int, default=16)
  ap.add_argument("--seconds", type=float, default=40.0)
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--out", default="", help="default: assets/dynamics_<vehicle>.json")
  a = ap.parse_args(argv)
  params, meta = fit_vehicle(a.vehicle, a.missions, a.seconds, a.seed)
  out = a.out or default_path(a.vehicle)
  save_params(params, out, meta)
  print(f"wrote {out}: residual rms lin {meta['rms_lin_m_s2']} ang {meta['rms_ang_rad_s2']}")


if __name__ == "__main__":
  main()
