"""Fly a batch of missions in one jitted call: the env's public ways to fly and record a batch.

- `fly_batch`: env steps under a policy until every env is done (no auto-reset; finished envs freeze);
  `lax.while_loop` stops as soon as every env is done (or `max_steps` is reached), so short missions don't pay for
  the longest possible episode. The true trajectory of env 0 is kept for plotting.
- `record`: autopilot ticks for a fixed time, recording chosen per-tick (and per-env-step) fields: what detector
  calibration, stealthy-attack design, dynamics fitting and the prior-work baselines learn from.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from envs import missions as missions_lib
from envs.base import tree_where
from specguard_jax import attacks as attacks_lib
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.estimation import traces as traces_lib

EPISODE_FLAGS = ("complete", "collision", "crash", "fence_breach", "stall", "nan")


def draw_paired_episode(env, key, settings, index):
  """Reset one env for a paired closed-loop experiment (the recovery and diagnosis tests).

  Mission, attack and world are drawn from `key` the same way whatever the setting, so episodes with one key share
  their plan, world and noise and differ only in the attack. settings: static tuple of (sensor, profile) pairs or None
  (no attack); index: [] int, which of them. The world is drawn uniformly from the env's `worlds`. Returns a State.
  """
  k_m, k_a, k_w, k_r = jax.random.split(key, 4)
  m = env.sample_mission(k_m)
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


# What `record` can record per autopilot tick (leaves [B, T, ...]). "Before" is the tick's start, "after" its end.
TICK_FIELDS = {
    "truth": "TrueState at the tick's start (what the sensors sample)",
    "readings": "SensorReadings of the tick, after the attack",
    "ekf": "the autopilot's EKFState after the tick ('ekf.<field>' records one field, e.g. 'ekf.pos')",
    "controls": "actuator commands of the previous tick, which moved the truth to this tick's start "
                "(estimation.traces.vehicle_controls: drone rotor thrusts [4] N, rover (throttle, steer) [2])",
    "actuation": "the same commands as the residual detector's vehicle model takes them (drone rotors [4], rover "
                 "(steer, throttle) [2])",
    "time": "the navigator's clock after the tick (s)",
    "start_time": "the navigator's clock at the tick's start (s): the attack clock of the tick",
    "phase": "the navigator's mission phase after the tick (autopilot.navigator: TAKEOFF ... DONE)",
    "attack_on": "whether the attack is active at the tick's start (bool)",
    "alive": "after the tick the physics is finite, the mission not finished and (drone) nothing hit (bool; "
             "not cumulative)",
    "vel_nav": "the navigator's velocity setpoint of the tick (m/s), from its state at the tick's start and the "
               "tick's EKF position",
    "leg_vel": "the plan's leg velocity of the tick (m/s): the navigator's active leg direction (from its state at the "
               "tick's start: waypoints only) x the mission's cruise speed, what PID-Piper's FFC takes as its target",
    "x_rec": "x'_t [15] after the tick as reconstructed (estimation.recon.INPUT_NAMES; an env with reconstruction)",
    "alarm": "the detector's alarm after the tick (0/1; an env with a detector)",
}
# ... per env step (leaves [B, n_ticks // ticks_per_step, ...]), at the step's start.
STEP_FIELDS = {"obs": "the policy observation [24] a policy deciding at this step would see"}
# ... once per mission (leaves [B, ...]), at reset.
INITIAL_FIELDS = {"ekf": "the autopilot's EKFState at reset (before the first tick)"}


def _check_fields(names, table, kind: str) -> None:
  for name in names:
    if name.split(".")[0] not in table:
      raise ValueError(f"unknown {kind} field {name!r}; choose from {', '.join(table)}")


def record(env, keys, n_ticks: int, fields, *, step_fields=(), initial_fields=(), world_ids=None, attacks=None):
  """Fly len(keys) missions for `n_ticks` autopilot ticks with the autopilot in control (no policy, no override) and
  record the chosen fields. One jitted call (a `lax.scan` over ticks, vmapped over missions); compiled once per
  (env, n_ticks, field names).

  keys: [B] PRNG keys (mission, world draw, noise: `env.reset_in_world`; the tick noise from fold_in(key, 7)).
  fields: names of TICK_FIELDS (or 'ekf.<field>'); step_fields: names of STEP_FIELDS (n_ticks must then be a multiple
  of env.config.ticks_per_step); initial_fields: names of INITIAL_FIELDS.
  world_ids: optional [B] int32 world preset ids (envs.worlds.PRESET_NAMES; None: the env's config).
  attacks: optional batched AttackSchedule [B] (None: the one reset draws from the env's config.attack, or none).
  Returns {name: leaves [B, n_ticks, ...]} for fields, {name: [B, n_steps, ...]} for step fields and
  {"initial_<name>": [B, ...]} for initial fields. Missions that end keep being ticked (record 'alive' to mask them).
  """
  _check_fields(fields, TICK_FIELDS, "tick")
  _check_fields(step_fields, STEP_FIELDS, "step")
  _check_fields(initial_fields, INITIAL_FIELDS, "initial")
  k = env.config.ticks_per_step
  if step_fields and n_ticks % k:
    raise ValueError(f"n_ticks ({n_ticks}) must be a multiple of ticks_per_step ({k}) to record step fields")
  if world_ids is not None:
    world_ids = jnp.asarray(world_ids, jnp.int32)
  return _record(env, keys, world_ids, attacks, n_ticks=int(n_ticks), fields=tuple(fields),
                 step_fields=tuple(step_fields), initial_fields=tuple(initial_fields))


def _tick_field(env, name, attack, before, after):
  """One TICK_FIELDS entry from the (phys, sim) before and after a tick."""
  sim0, (phys1, sim1) = before[1], after
  if name == "truth":
    return sim0["truth"]
  if name == "readings":
    return sim1["readings"]
  if name == "ekf":
    return sim1["ekf"]
  if name.startswith("ekf."):
    return getattr(sim1["ekf"], name[4:])
  if name == "controls":
    return traces_lib.vehicle_controls(env.vehicle, sim0)
  if name == "actuation":
    return env._actuation(sim0)
  if name == "time":
    return sim1["nav"].time
  if name == "start_time":
    return sim0["nav"].time
  if name == "phase":
    return sim1["nav"].phase
  if name == "attack_on":
    return jnp.zeros((), bool) if attack is None else attacks_lib.attack_active(attack, sim0["nav"].time)
  if name == "alive":
    ok = jnp.all(jnp.isfinite(phys1.qpos)) & (sim1["nav"].phase != nav_lib.DONE)
    return ok & ~sim1["vehicle"]["hit"] if env.vehicle == "drone" else ok
  if name == "x_rec":
    return sim1["x_rec"]
  if name == "alarm":
    return sim1["det"].alarm
  assert name in ("vel_nav", "leg_vel"), name
  mission = before[2]
  _, vel_nav, leg_dir = nav_lib.nav_step(env._nav_params(), sim0["nav"], mission, sim1["ekf"].pos,
                                         env._vehicle_landed(sim0), env.config.tick_dt)
  return vel_nav if name == "vel_nav" else leg_dir * mission.cruise_speed


@functools.partial(jax.jit, static_argnames=("env", "n_ticks", "fields", "step_fields", "initial_fields"))
def _record(env, keys, world_ids, attacks, *, n_ticks, fields, step_fields, initial_fields):
  k = env.config.ticks_per_step
  no_override = jnp.zeros((), bool)

  def one(key, world_id, attack):
    state = env.reset_in_world(key, world_id, None, attack)
    info = state.info
    mission, world = info["mission"], info["world"]
    if attack is None and env.config.attack is not None:   # the attack reset drew from the config
      attack = info["attack"]

    def tick(carry, kt):
      phys, sim = carry
      after = env._tick(phys, sim, mission, world, jnp.zeros(3), no_override, kt, attack)
      return after, {f: _tick_field(env, f, attack, (phys, sim, mission), after) for f in fields}

    ticks = jax.random.split(jax.random.fold_in(key, 7), n_ticks)
    carry = (state.pipeline_state, info["sim"])
    if step_fields:
      def step(carry, ks):
        obs = {"obs": env._observation(world, mission, carry[1])} if "obs" in step_fields else {}
        carry, out = jax.lax.scan(tick, carry, ks)
        return carry, (obs, out)

      _, (per_step, out) = jax.lax.scan(step, carry, ticks.reshape((n_ticks // k, k) + ticks.shape[1:]))
      out = jax.tree.map(lambda a: a.reshape((n_ticks,) + a.shape[2:]), out)
      out.update(per_step)
    else:
      _, out = jax.lax.scan(tick, carry, ticks)
    if "ekf" in initial_fields:
      out["initial_ekf"] = info["sim"]["ekf"]
    return out

  return jax.vmap(one)(keys, world_ids, attacks)
