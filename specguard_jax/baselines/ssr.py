"""SSR baseline (Choi et al., RAID 2020, "software sensors"): the controller 'ssr'.

The in-tick estimator (software sensors substituting the diagnosed sensor's readings in the autopilot's EKF) lives in
the core, specguard_jax.estimation.software_sensors; this module fits its specific-force model on attack-free flights
and registers the deployment (EnvConfig.recovery_estimator='software_sensors').
"""

from __future__ import annotations

import os

import numpy as np

from specguard_jax import controllers
from specguard_jax.baselines import common
from specguard_jax.estimation.software_sensors import fit_force_model, load_force_model


ENV_OVERRIDES = (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
                 ("reconstruction", False), ("recovery_estimator", "software_sensors"))


def build(ctx):
  """Controller 'ssr': fit (or load from ctx.cache_dir) the software sensors' specific-force model on attack-free
  flights; deploy with the autopilot, the residual detector and software-sensor substitution."""
  path = common.cache_path(ctx, "ssr", "msgpack")
  n_u = 4 if ctx.vehicle == "drone" else 2
  if not os.path.exists(path):
    _, tr = common.flights(ctx.vehicle, tuple(ctx.worlds), ctx.train_budget, ctx.seed)
    n = tr["time"].shape[0]
    _, rms_test = fit_force_model(tr, ctx.vehicle, heldout=max(1, n // 5))   # generalisation check
    fm, _ = fit_force_model(tr, ctx.vehicle)                                  # the deployed model: all missions
    common.save_tree(path, fm, {"baseline": "ssr", "vehicle": ctx.vehicle, "budget": ctx.train_budget,
                                "seed": ctx.seed, "missions": n, "rms_m_s2": np.asarray(fm.rms).tolist(),
                                "heldout_rms_m_s2": np.round(np.asarray(rms_test), 4).tolist()})
  load_force_model(path, n_u)   # validates the cache (one-line ValueError)
  return controllers.Controller("ssr", ENV_OVERRIDES + (("recovery_model", os.path.abspath(path)),),
                                controllers.zero_policy, None,
                                "SSR: software sensors (model-predicted readings of the diagnosed sensor, open loop "
                                "from a checkpoint) replace it in the autopilot's EKF; original controller")
