"""bench/brax_ppo.py: Brax's ppo.train runs on our env through the bench's wrappers and reports its figures.

Slow on the 2-core CPU (mostly compiling the env's reset and Brax's training epoch around the env step).
"""

import importlib.util
import math
import os

import jax
import jax.numpy as jnp
import pytest

_PATH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench", "brax_ppo.py")


def _bench():
  spec = importlib.util.spec_from_file_location("brax_ppo_bench", _PATH)
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return mod


def test_jax_shims_single_host():
  bench = _bench()
  bench.install_jax_shims()
  ds = jax.local_devices()[:1]
  rep = jax.device_put_replicated({"a": jnp.arange(3.0)}, ds)
  assert rep["a"].shape == (1, 3)
  sh = jax.device_put_sharded([jnp.ones(2)], ds)
  assert sh.shape == (1, 2)


@pytest.mark.slow
def test_brax_ppo_tiny_run():
  import envs
  bench = _bench()
  env = envs.make("drone", control_mode="override", override_frame="body")
  requested = 2000
  r = bench.run_brax_ppo(env, num_envs=8, num_timesteps=requested, unroll_length=10, batch_size=4, num_minibatches=2,
                         num_updates_per_batch=2, episode_length=50, hidden=(16, 16), num_evals=3, run_evals=False)
  assert r["env_steps"] >= requested
  assert math.isfinite(r["sps"]) and r["sps"] > 0
  assert math.isfinite(r["wall_s"]) and r["wall_s"] > 0
  assert r["compile_s"] >= 0 and r["train_epochs"] == 2
  assert math.isnan(r["final_reward"])  # no evals
