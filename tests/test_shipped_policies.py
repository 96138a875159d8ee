"""The trained policies shipped in docs/eval/policies (the runs docs/eval's reports and BENCHMARKS.md evaluate) still
load with today's code: config.json validates as a TrainConfig, the weights load, the observation layout they were
trained on is the one the code builds under that name, and a forward pass gives a finite velocity setpoint."""

import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

from envs import observation as obs_lib
from specguard_jax import controllers, export

ROOT = os.path.join(os.path.dirname(__file__), "..", "docs", "eval", "policies")
RUNS = sorted(d for d in os.listdir(ROOT) if os.path.isdir(os.path.join(ROOT, d))) if os.path.isdir(ROOT) else []


def test_the_reference_runs_are_shipped():
  assert {"rc_s0", "rc_s1", "rc_s2", "pc_s0", "binary_s0", "suburban_s0", "urban_s0", "rover_s0"} <= set(RUNS)


@pytest.mark.parametrize("name", RUNS)
def test_shipped_policy_loads_and_acts(name):
  run = os.path.join(ROOT, name)
  fn, params, cfg = controllers.load_run_policy(run)
  n_obs = params["mean"].shape[0]
  desc = export.load_obs_layout(run)
  assert desc is not None and desc["name"] == cfg.env.obs_layout
  assert desc == obs_lib.describe(desc["name"], obs_lib.sectors_of(desc), obs_lib.history_of(desc)), (
      f"{name}: the code's '{desc['name']}' observation layout changed since this policy was trained")
  assert obs_lib.size(desc["name"], obs_lib.sectors_of(desc), obs_lib.history_of(desc)) == n_obs
  obs = jnp.asarray(np.random.default_rng(0).normal(size=(4, n_obs)), jnp.float32)
  act = np.asarray(fn(params, obs))
  assert act.shape == (4, 3) and np.isfinite(act).all()
  with open(os.path.join(run, "summary.json")) as f:
    summary = json.load(f)
  assert summary["env_steps"] > 0
  if cfg.eval_missions:   # the paper suite's unseen-world and rover runs were trained without a held-out evaluation
    assert "attack_free" in summary["heldout"]
