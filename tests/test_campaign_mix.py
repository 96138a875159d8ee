"""Phase 2's scripted campaigns (specguard_jax/ppo/campaign_mix.py): drawn at reset as the evaluation draws them, flown
instead of the attack agent's attack, and out of the agent's samples."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.missions import MissionConfig
from specguard_jax import attacks
from specguard_jax.ppo import attacker, campaign_mix
from specguard_jax.ppo import config as config_lib
from specguard_jax.ppo import iteration


def test_mix_configuration():
  mix = campaign_mix.CampaignMix(share=0.5, campaigns=("long", "multi"), sensors=("gps", "gyro", "baro"))
  entries = mix.entries()
  assert [cfg.until_end for cfg, _, _ in entries] == [True, False, False]        # long, then gps+baro, gps+gyro
  assert [cfg.sensors for cfg, _, _ in entries][1:] == [("gps", "baro"), ("gps", "gyro")]
  assert [w for _, _, w in entries] == [1.0, 0.5, 0.5]                           # each campaign equally likely
  assert not campaign_mix.CampaignMix(share=0.0).active
  with pytest.raises(ValueError, match="unknown training campaign"):
    campaign_mix.CampaignMix(campaigns=("designed",))
  with pytest.raises(ValueError, match="campaign_share"):
    config_lib.TrainConfig(campaign_share=1.5).validate()
  env = iteration.make_env(config_lib.TrainConfig(campaign_share=0.0).with_env(worlds=("urban_park",)).validate(), 2)
  assert env.mix is None


def test_scripted_episodes_fly_the_campaign_attack():
  env = envs.make("drone", world="urban_park", mission=MissionConfig.drone(min_duration_s=30.0, max_duration_s=40.0),
                  detector="oracle", control_mode="reactive", reconstruction=True)
  mix = campaign_mix.CampaignMix(share=0.5)
  aenv = attacker.AttackerEnv(env, attacker.AttackerConfig(), (4.0, 4.0, 2.0), mix=mix)
  n = 16
  s = jax.jit(jax.vmap(aenv.reset))(jax.random.split(jax.random.PRNGKey(3), n))
  scripted = np.asarray(s.info["scripted"])
  assert 0 < scripted.sum() < n                                     # about half the episodes
  sched = jax.tree.map(np.asarray, s.info["scripted_attack"])
  k = sched.mask.sum(-1)
  assert set(k.tolist()) <= {1.0, 2.0} and (k == 2).any()          # single-sensor campaigns and GPS pairs
  assert np.all((k < 2) | (sched.mask[:, attacks.SENSOR_NAMES.index("gps")] == 1))
  assert np.all(sched.onset < np.asarray(s.info["mission"].nominal_duration))
  # the agent asks for no attack; the scripted episodes fly theirs regardless
  raw = jnp.full((n, attacker.N_ACT), -5.0)
  nxt = jax.jit(jax.vmap(aenv.step))(s, jnp.concatenate([jnp.zeros((n, 3)), raw], axis=-1))
  flown = np.asarray(nxt.info["attack"].mask)
  np.testing.assert_array_equal(flown[scripted], sched.mask[scripted])
  assert not flown[~scripted].any()
