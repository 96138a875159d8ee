"""The evaluation's scripted attack campaigns mixed into phase-2 training (TrainConfig.campaign_share).

The attack agent's attacks last at most its time budget and it learns slowly where to aim, so without help the policy
rarely meets what the hard benchmark flies: attacks lasting to the landing, timed before a hazard, or on two sensors
at once (specguard_jax.evaluation, CAMPAIGNS). A share of phase-2 episodes therefore flies one of those campaigns
instead, drawn at reset exactly as the evaluation draws it (same AttackConfigs, the hazard onset from the mission and
the world, envs.hazards); the agent's actions are then ignored and its samples of those episodes are masked out of its
loss (ppo.iteration).

  long    one of the attackable sensors, overt or stealthy, from 15-50 % into the mission to its end;
  hazard  one sensor, overt, a few seconds before a hazard point of the mission (evaluation.HAZARD_LEAD_S);
  multi   a GPS pair of evaluation.MULTI_PAIRS (both sensors attackable), overt or stealthy.
Each named campaign is drawn with equal probability (a multi episode picks its pair uniformly).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from envs import hazards as hazards_lib
from specguard_jax import attacks as attacks_lib
from specguard_jax import evaluation

TRAIN_CAMPAIGNS = ("long", "hazard", "multi")
_STREAM = 0xCA3B   # fold_in tag of the mix's keys (the env's own reset key is left as it is)


@dataclasses.dataclass(frozen=True)
class CampaignMix:
  """share: probability that a phase-2 episode flies a scripted campaign.  campaigns: names in TRAIN_CAMPAIGNS.
  sensors: the attackable sensors (TrainConfig.attack_sensors)."""
  share: float = 0.25
  campaigns: tuple = TRAIN_CAMPAIGNS
  sensors: tuple = attacks_lib.SENSOR_NAMES

  def __post_init__(self):
    bad = [c for c in self.campaigns if c not in TRAIN_CAMPAIGNS]
    if bad:
      raise ValueError(f"unknown training campaign(s) {bad}; choose from {', '.join(TRAIN_CAMPAIGNS)}")
    if not 0.0 <= self.share <= 1.0:
      raise ValueError(f"campaign_share must be in [0, 1], got {self.share}")

  @property
  def active(self) -> bool:
    return self.share > 0 and bool(self.entries())

  def entries(self) -> tuple:
    """((AttackConfig, hazard-timed?, weight), ...): every campaign's configs, weights summing to 1 per campaign."""
    out = []
    sens = tuple(self.sensors)
    for c in self.campaigns:
      if c == "long":
        cfg = attacks_lib.AttackConfig(sensors=sens, profiles=attacks_lib.PROFILES, until_end=True)
        out.append([(cfg, False)])
      elif c == "hazard":
        out.append([(attacks_lib.AttackConfig(sensors=sens, profiles=("overt",), onset="given"), True)])
      else:
        pairs = [p for p in evaluation.MULTI_PAIRS if all(x in sens for x in p)]
        if pairs:
          out.append([(attacks_lib.AttackConfig(sensors=p, profiles=attacks_lib.PROFILES, n_sensors=2), False)
                      for p in pairs])
    return tuple((cfg, hz, 1.0 / len(group)) for group in out for cfg, hz in group)

  def draw(self, env, info: dict, rng):
    """(scripted [] bool, AttackSchedule) of one episode at reset: info is its reset state's info (mission, world),
    env the unwrapped env (its mission config)."""
    entries = self.entries()
    k_on, k_pick, k_h, k_a = jax.random.split(jax.random.fold_in(rng, _STREAM), 4)
    mission = info["mission"]
    scheds = []
    for i, (cfg, hazard, _) in enumerate(entries):
      onset = (hazards_lib.hazard_onset(mission, info["world"], env.mission_cfg, jax.random.fold_in(k_h, i),
                                        evaluation.HAZARD_LEAD_S)[0] if hazard else None)
      scheds.append(attacks_lib.sample_attack(cfg, jax.random.fold_in(k_a, i), mission.nominal_duration, onset))
    weights = np.asarray([w for _, _, w in entries], np.float32)
    pick = jax.random.categorical(k_pick, jnp.log(jnp.asarray(weights / weights.sum())))
    sched = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v, jnp.asarray(x[0]).dtype) for v in x])[pick], *scheds)
    scripted = jax.random.uniform(k_on) < self.share
    return scripted, sched
