"""Fly a batch of missions to completion in one jitted call (no auto-reset; finished envs freeze).

`lax.while_loop` stops as soon as every env is done (or `max_steps` is reached), so short missions don't pay for
the longest possible episode. The true trajectory of one env (index `record`) is kept for plotting.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from envs import missions as missions_lib
from envs.base import tree_where
from specguard_jax import attacks as attacks_lib

EPISODE_FLAGS = ("complete", "collision", "crash", "fence_breach", "stall", "nan")


def draw_paired_episode(env, key, settings, index):
  """Reset one env for a paired closed-loop experiment (bench/gps_xcheck.py, bench/*_trace.py, the recovery tests).

  Mission, attack and world are drawn from `key` the same way whatever the setting, so episodes with one key share
  their plan, world and noise and differ only in the attack. settings: static tuple of (sensor, profile) pairs or None
  (no attack); index: [] int, which of them. The world is drawn uniformly from the env's `worlds`. Returns a State.
  """
  k_m, k_a, k_w, k_r = jax.random.split(key, 4)
  m = missions_lib.generate_mission(env.mission_cfg, k_m)
  cand = [attacks_lib.no_attack() if s is None else attacks_lib.sample_attack(
      attacks_lib.AttackConfig(sensors=(s[0],), profiles=(s[1],)), k_a, m.nominal_duration) for s in settings]
  atk = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v, jnp.float32) for v in x])[index], *cand)
  atk = atk.replace(profile=atk.profile.astype(jnp.int32))
  wid = jnp.asarray(env.world_ids)[jax.random.randint(k_w, (), 0, len(env.world_ids))]
  return env.reset_in_world(k_r, wid, m, atk)


def _policy_zero(obs, key):
  return jnp.zeros(obs.shape[:-1] + (3,))


@functools.partial(jax.jit, static_argnames=("env", "max_steps", "policy"))
def fly_batch(env, keys, max_steps: int, policy=_policy_zero, missions=None, world_ids=None, attacks=None):
  """Roll out len(keys) episodes. Returns (final State [B], trajectory dict of env 0, steps run []).

  policy(obs [B, n], key) -> action [B, 3] (ignored in control_mode='autopilot').
  missions: optional batched Mission to fly instead of generated ones.
  world_ids: optional [B] int32 world preset ids (envs.worlds.PRESET_NAMES); None: the env's config.
  attacks: optional batched AttackSchedule; None: drawn from the env's config.attack (or none).
  Trajectory: pos [T, 3] (true), est [T, 3] (EKF), phase [T] and valid [T] of env 0, with T = max_steps.
  """
  state = jax.vmap(env.reset_in_world)(keys, world_ids, missions, attacks)
  step = jax.vmap(env.step)
  traj = {"pos": jnp.zeros((max_steps, 3)), "est": jnp.zeros((max_steps, 3)),
          "phase": jnp.zeros((max_steps,), jnp.int32), "valid": jnp.zeros((max_steps,), bool)}

  def cond(carry):
    state, _, t, _ = carry
    return (t < max_steps) & ~jnp.all(state.done > 0)

  def body(carry):
    state, traj, t, key = carry
    key, k_act = jax.random.split(key)
    action = policy(state.obs, k_act)
    nxt = step(state, action)
    nxt = tree_where(state.done > 0, state, nxt)
    sim = nxt.info["sim"]
    traj = {"pos": traj["pos"].at[t].set(sim["truth"].pos[0]), "est": traj["est"].at[t].set(sim["ekf"].pos[0]),
            "phase": traj["phase"].at[t].set(sim["nav"].phase[0]), "valid": traj["valid"].at[t].set(state.done[0] == 0)}
    return nxt, traj, t + 1, key

  state, traj, t, _ = jax.lax.while_loop(cond, body, (state, traj, jnp.zeros((), jnp.int32), keys[0]))
  return state, traj, t


def summarize(state) -> dict:
  """Per-batch outcome counts from final states: each flag summed over envs, plus truncations and mission times."""
  ep = state.info["episode"]
  out = {k: int(jnp.sum(ep[k] > 0)) for k in EPISODE_FLAGS}
  out["truncated"] = int(jnp.sum(state.info["truncation"] > 0))
  out["unfinished"] = int(jnp.sum(state.done == 0))
  out["mission_time_s"] = [float(x) for x in state.info["time"]]
  violated = jnp.asarray(state.info["spec_robustness"]) < 0           # [B, n_specs], whole-episode verdicts
  out["missions_violating"] = int(jnp.sum(jnp.any(violated, axis=-1)))
  out["violations_per_spec"] = [int(x) for x in jnp.sum(violated, axis=0)]
  out["attacked"] = int(jnp.sum(ep["attacked"] > 0))
  return out
