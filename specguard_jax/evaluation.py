"""Held-out evaluation of a controller: many missions per setting (attack-free, overt/stealthy per sensor), one
episode each, all settings in ONE batched, jitted rollout (settings are data).

A setting is (sensor or None, profile): its missions get a random Table 3 attack on that sensor
(specguard_jax.attacks.sample_attack: onset 15-50 % into the mission, 15-40 s). Missions and worlds are drawn from
`seed` (use a seed the training never saw: training seeds its env resets from TrainConfig.seed).

Per setting: missions, svr (share of missions with any spec's episode robustness < 0), critical (S1/S2/S12
violated; the table's critical flags), rsr (completed / missions, for attacked settings the paper's recovery success rate), collision, crash,
stall, fence_breach, detected (alarm raised at least once).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from envs import missions as missions_lib
from envs.base import tree_where
from specguard_jax import attacks as attacks_lib

def default_settings(sensors=attacks_lib.SENSOR_NAMES, profiles=attacks_lib.PROFILES):
  return [(None, "none")] + [(s, p) for s in sensors for p in profiles]


@functools.partial(jax.jit, static_argnames=("env", "settings", "n", "max_steps", "policy"))
def _rollout(env, policy, policy_params, key, settings, n: int, max_steps: int):
  n_set = len(settings)
  keys = jax.random.split(key, n_set * n)
  setting_id = jnp.repeat(jnp.arange(n_set), n)
  world_ids = jnp.asarray(env.world_ids, jnp.int32)

  def reset_one(k, sid):
    k_m, k_a, k_w, k_r = jax.random.split(k, 4)
    mission = missions_lib.generate_mission(env.mission_cfg, k_m)
    scheds = []
    for sensor, profile in settings:
      if sensor is None:
        scheds.append(attacks_lib.no_attack())
      else:
        acfg = attacks_lib.AttackConfig(sensors=(sensor,), profiles=(profile,))
        scheds.append(attacks_lib.sample_attack(acfg, k_a, mission.nominal_duration))
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *scheds)
    attack = jax.tree.map(lambda x: x[sid], stacked)
    wid = world_ids[jax.random.randint(k_w, (), 0, len(env.world_ids))]
    return env.reset_in_world(k_r, wid, mission, attack)

  state = jax.vmap(reset_one)(keys, setting_id)
  step = jax.vmap(env.step)

  def cond(c):
    s, t = c
    return (t < max_steps) & ~jnp.all(s.done > 0)

  def body(c):
    s, t = c
    nxt = step(s, policy(policy_params, s.obs))
    return tree_where(s.done > 0, s, nxt), t + 1

  state, t = jax.lax.while_loop(cond, body, (state, jnp.zeros((), jnp.int32)))
  ep = state.info["episode"]
  rob = state.info["spec_robustness"]
  crit = jnp.asarray(env.spec_table.critical)
  out = {"violated": jnp.any(rob < 0, -1), "critical": jnp.any((rob < 0) & crit, -1),
         "complete": ep["complete"] > 0, "collision": ep["collision"] > 0, "crash": ep["crash"] > 0,
         "stall": ep["stall"] > 0, "fence_breach": ep["fence_breach"] > 0, "attacked": ep["attacked"] > 0,
         "unfinished": state.done == 0, "per_spec": rob < 0}
  if "detected" in ep:
    out["detected"] = ep["detected"] > 0
  return out, setting_id, t


def evaluate(env, policy, policy_params, *, missions: int = 1000, settings=None, seed: int = 10_000,
             max_s: float = 400.0) -> dict:
  """Fly `missions` held-out missions per setting with `policy(params, obs [B, n]) -> action [B, 3]` (a hashable,
  module-level function: it is a static argument). Returns {setting name: metrics dict} (see module docstring)."""
  settings = tuple(settings or default_settings())
  out, sid, t = _rollout(env, policy, policy_params, jax.random.PRNGKey(seed), settings, missions,
                         int(max_s / env.dt))
  out, sid = jax.device_get((out, sid))
  res = {}
  for i, (sensor, profile) in enumerate(settings):
    m = np.asarray(sid) == i
    name = "attack_free" if sensor is None else f"{sensor}/{profile}"
    r = {"missions": int(m.sum())}
    for k in ("violated", "critical", "complete", "collision", "crash", "stall", "fence_breach", "attacked",
              "unfinished", "detected"):
      if k in out:
        r[k if k != "violated" else "svr"] = float(np.mean(out[k][m]))
    r["rsr"] = r["complete"]
    r["violations_per_spec"] = dict(zip(env.spec_names, np.mean(out["per_spec"][m], 0).round(4).tolist()))
    res[name] = r
  res["_steps"] = int(t)
  return res
