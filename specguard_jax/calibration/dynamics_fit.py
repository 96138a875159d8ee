"""Fit the system-ID dynamics model the reconstruction rolls forward (assets/dynamics_<vehicle>.json).

Flies `missions` attack-free autopilot missions (worlds FIT_WORLDS round robin) through the env's own ticks
(`envs.record`), fits `estimation.dynamics.fit_dynamics` on the EKF's states and the applied controls (one ridge
solve) and writes the weights with `estimation.model_file.save_params`:

  python tools/fit_dynamics.py --vehicle drone --missions 16 --seconds 40
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import worlds as worlds_lib
from envs.missions import MissionConfig
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.estimation import model_file
from specguard_jax.estimation import traces
from specguard_jax.types import VEHICLES

FIT_WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")


def fit_vehicle(vehicle: str, missions: int = 16, seconds: float = 40.0, seed: int = 0):
  """Record `missions` attack-free flights (worlds FIT_WORLDS round robin) and fit. Returns (DynParams, meta)."""
  mcfg = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      min_duration_s=seconds + 10.0, max_duration_s=seconds + 60.0)
  env = envs.make(vehicle, mission=mcfg)
  ids = jnp.asarray([worlds_lib.PRESET_NAMES.index(FIT_WORLDS[i % len(FIT_WORLDS)]) for i in range(missions)],
                    jnp.int32)
  n_ticks = int(round(seconds / env.config.tick_dt))
  tr = envs.record(env, jax.random.split(jax.random.PRNGKey(seed), missions), n_ticks, traces.RECORD_FIELDS,
                   world_ids=ids)
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
  out = a.out or model_file.default_path(a.vehicle)
  model_file.save_params(params, out, meta)
  print(f"wrote {out}: residual rms lin {meta['rms_lin_m_s2']} ang {meta['rms_ang_rad_s2']}")
