"""One phase of training as compiled functions: acting (lax.scan over the vmapped env), GAE and the PPO updates of
SpecGuard (SG) and the attack agent (AA), with K iterations per host call.

Phase 1 (compliance): SpecGuard flies every phase of EnvConfig.override_phases (velocity-setpoint override; the
trainer's default: all flight phases), no attacks.
Phase 2 (adversarial, paper Algorithm 2): the attack agent drives the attacks (ppo/attacker.py) against the
variant's controller (RC: override only while the detector's alarm is up; PC: always), with state reconstruction in
the loop unless disabled. Iterations alternate: `alternate_iters` iterations update SG with AA frozen, then the
reverse; the turn is data in the carry, so both branches are one compiled program (lax.cond).

Reward seen by SG: the env's per-step compliance reward (in [0, 1] normalised) + the completion bonus on mission
completion - the violation penalty on the step a spec's violation becomes certain (TrainConfig.violation_penalty)
- the stall penalty on the step an episode ends in a stall (TrainConfig.stall_penalty); it learns from that + the
progress pay (TrainConfig.progress_reward) - the action cost (TrainConfig.action_cost);
AA's: AttackerEnv.reward (zero-sum by default). SG's policy loss is masked to the steps where its action
reached the vehicle (override active: a phase of override_phases, and the alarm up for RC); its value function
learns from all.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from specguard_jax import third_party  # noqa: F401 - before brax: mujoco.mjx without its Warp notices
from brax.envs.base import State
from brax.envs.wrappers.training import VmapWrapper
from flax import struct

import envs as envs_lib
from envs.base import override_in_phase
from envs.wrappers import AutoReset, violation_onsets
from specguard_jax import evaluation
from specguard_jax.ekf_lanes import resolve_ekf_kernel
from specguard_jax.ppo import attacker as attacker_lib
from specguard_jax.ppo import campaign_mix
from specguard_jax.ppo import distributed, losses, networks
from specguard_jax.ppo.config import PPOConfig, TrainConfig, env_config, network_precision
from specguard_jax.types import RESIDUAL_DETECTORS, SENSOR_NAMES

AA_SENSOR_KEYS = tuple(f"aa_{s}" for s in SENSOR_NAMES)
STAT_KEYS = ("episodes", "complete", "collision", "crash", "stall", "nan", "fence_breach", "violated", "critical",
             "attacked", "attacked_complete", "attacked_violated", "return_sum", "return_aa_sum", "reward_sum",
             "override_steps", "aa_launches", "aa_onset_sum", "aa_attack_s") + AA_SENSOR_KEYS
"""The per-iteration totals of the rollout's episode statistics (sums over steps and envs; metrics of run()). The
attack agent's choices (phase 2; 0 in phase 1): attacks launched, the sum of their onsets (s), attack time (s), and
per sensor the attacks that spoofed it (aa_<sensor>; a multi-sensor attack counts for each of its sensors)."""


@struct.dataclass
class Carry:
  """Everything a phase's iterations thread through (checkpointed whole)."""
  sg: losses.AgentState
  aa: losses.AgentState
  env_state: State
  ep_return: jnp.ndarray      # [G, B/G] SG return of the running episodes (G env groups, ppo/distributed.py)
  ep_return_aa: jnp.ndarray   # [G, B/G]
  rng: jnp.ndarray
  iteration: jnp.ndarray      # [] int32 iterations done in this phase


def trainer_env_options(detector: str = "none") -> dict:
  """EnvConfig fields the trainer sets on every env it trains in (benches reuse them for "the trainer's env"; the
  trainer's own come from config.env_config): no NaN fallback (its AutoReset replaces a NaN-terminated env's state,
  EnvConfig.nan_fallback) and no EKF per-channel records unless the detector reads them (detector 'residual' or
  'mixed', EnvConfig.ekf_records)."""
  return dict(nan_fallback=False, ekf_records=detector in RESIDUAL_DETECTORS)


def _make(vehicle: str, config):
  """The env of `vehicle` with EnvConfig `config` (every field of it, through envs.make's checks)."""
  return envs_lib.make(vehicle, **{f.name: getattr(config, f.name) for f in dataclasses.fields(config)})


def make_env(cfg: TrainConfig, phase: int):
  """The unbatched env of a phase (config.env_config(cfg, phase); phase 2 wrapped in AttackerEnv)."""
  env = _make(cfg.vehicle, env_config(cfg, phase))
  if phase == 1:
    return env
  acfg = attacker_lib.AttackerConfig(sensors=tuple(cfg.attack_sensors), max_duration_s=cfg.attack_max_duration_s,
                                     alpha=cfg.attack_alpha, beta=cfg.attack_beta, gamma=cfg.attack_gamma,
                                     max_sensors=min(cfg.attack_max_sensors, len(cfg.attack_sensors)),
                                     min_onset_s=cfg.attack_min_onset_s)
  mix = campaign_mix.CampaignMix(share=cfg.campaign_share, campaigns=tuple(cfg.campaigns),
                                 sensors=tuple(cfg.attack_sensors))
  return attacker_lib.AttackerEnv(env, acfg, cfg.speeds, mix=mix)


def sg_policy(cfg: TrainConfig) -> networks.Policy:
  n = 6 if cfg.action == "discrete" else len(cfg.action_scales)   # 6 moves, or a setpoint of 3 or 6 outputs
  return networks.Policy(cfg.action, n, tuple(cfg.hidden), cfg.activation, init_log_std=cfg.init_log_std)


def aa_policy(cfg: TrainConfig) -> networks.Policy:
  return networks.Policy("gaussian", attacker_lib.N_ACT, (128, 128), "tanh", init_log_std=0.0)


def _iterations(cfg: TrainConfig, phase: int) -> int:
  steps = cfg.phase1_steps if phase == 1 else cfg.phase2_steps
  return max(1, -(-steps // cfg.steps_per_iter))


def bootstrap_values(value_fn, obs, next_obs, done, terminated, max_truncations: int, steps_per_pass: int):
  """(V(obs), V(next_obs)), each [T, *batch], on T + 1 + max_truncations rows per env instead of 2T.

  For an auto-reset rollout, next_obs[t] (the observation step t produced) is obs[t+1] wherever done[t] = 0, so
  V(next_obs[t]) = V(obs[t+1]) there. Where the env finished: terminated rows are not bootstrapped (GAE multiplies
  them by 0; they get V(obs[t+1]), finite), truncated rows (done, not terminated) get V of their own next_obs,
  gathered per env for at most `max_truncations` truncations in steps 0..T-2 (the caller's bound; the env cannot be
  truncated more often in a rollout), and the last step's always comes from next_obs[T-1].
  value_fn: [..., n] -> [...]. obs, next_obs: [T, *batch, n]; done, terminated: [T, *batch], 0/1 floats.
  steps_per_pass: steps of obs per value-network pass (lax.map's batch_size).
  """
  T = obs.shape[0]
  v = jax.lax.map(value_fn, obs, batch_size=steps_per_pass)                 # [T, *batch]
  trunc = (done[:-1] > 0) & (terminated[:-1] <= 0)                          # [T-1, *batch]
  t_idx = jnp.arange(T - 1).reshape((T - 1,) + (1,) * (trunc.ndim - 1))
  rows, picks = [next_obs[-1]], []
  for _ in range(max_truncations):
    first = jnp.argmax(trunc, axis=0)                                       # earliest truncation left (0 if none)
    hit = (t_idx == first[None]) & trunc
    rows.append(jnp.take_along_axis(next_obs[:-1], first[None, ..., None], axis=0)[0])
    picks.append(hit)
    trunc = trunc & ~hit
  extra = value_fn(jnp.stack(rows))                                         # [1 + max_truncations, *batch]
  following = v[1:]
  for k, hit in enumerate(picks):
    following = jnp.where(hit, extra[1 + k][None], following)
  return v, jnp.concatenate([following, extra[:1]], axis=0)


def make_agents(cfg: TrainConfig):
  """(SG agent, AA agent); their step-size schedules span the whole run's updates."""
  n_sg = (_iterations(cfg, 1) + _iterations(cfg, 2)) * cfg.sg.update_epochs * cfg.sg.num_minibatches
  n_aa = _iterations(cfg, 2) * cfg.aa.update_epochs * cfg.aa.num_minibatches
  dt = cfg.network_dtype   # training only: evaluation and the ONNX export run sg_policy(cfg) in float32
  sg = losses.make_agent(dataclasses.replace(sg_policy(cfg), dtype=dt), tuple(cfg.hidden), cfg.activation, cfg.sg,
                         n_sg, cfg.obs_clip)
  aa = losses.make_agent(dataclasses.replace(aa_policy(cfg), dtype=dt), (128, 128), "tanh", cfg.aa, n_aa,
                         cfg.obs_clip)
  return sg, aa


def group_step(batched, mesh=None, per_device: bool = False):
  """The env step of G auto-reset groups: (state [G, B/G, ...], action [G, B/G, n]) -> state.

  per_device and a mesh of several devices: the groups axis is split explicitly (shard_map), each device stepping its
  own groups. The lanes EKF kernel (a Pallas call, which has no sharding rule) needs that. Otherwise a plain vmap
  that XLA's SPMD partitioner splits along the groups' sharding: on several GPUs with jax 0.11.2 the shard_map inside
  the training scan makes XLA's `shardy-xla` pass segfault at compile time, with or
  without the kernel, so it is used only where the kernel needs it."""
  step = jax.vmap(batched.step)
  if mesh is None or mesh.size == 1 or not per_device:
    return step
  spec = jax.sharding.PartitionSpec(distributed.AXIS)
  return jax.shard_map(step, mesh=mesh, in_specs=(spec, spec), out_specs=spec, check_vma=False)


@dataclasses.dataclass
class Phase:
  """A phase's env and compiled entry points: init(key, sg_state, aa_state) -> Carry; run(carry) -> (carry,
  metrics [K]). The carry's env state is [G, B/G, ...] (`groups` = G), sharded over `mesh` along G."""
  cfg: TrainConfig
  number: int
  env: Any
  batched: Any
  sg: losses.Agent
  aa: losses.Agent
  init: Any
  run: Any
  iterations: int
  mesh: Any = None
  groups: int = 1


def program_config(cfg: TrainConfig) -> TrainConfig:
  """cfg without what is data in the compiled program (seed, the agents' losses.HPARAMS, host-side knobs), so runs
  and sweep members that differ only there share one compiled phase. The runner sets those values in the carry."""
  d = PPOConfig()
  clear = lambda p: dataclasses.replace(p, **{k: getattr(d, k) for k in losses.HPARAMS})  # noqa: E731
  return dataclasses.replace(cfg, seed=0, sg=clear(cfg.sg), aa=clear(cfg.aa), eval_missions=0,
                             checkpoint_every_s=0.0, converge_eps=0.0)


def make_phase(cfg: TrainConfig, phase: int, mesh=None, members: int = 0) -> Phase:
  """The phase's env and compiled functions, cached per program_config(cfg) and mesh (a resumed run or another seed
  in the same process reuses them); `Phase.cfg` is that program config, and the agents' `init` gives default
  hyperparameters (set the run's with losses.with_hparams). mesh: the 1-D 'data' device mesh (default:
  distributed.make_mesh(cfg.num_devices)); the env groups are sharded over it, agents replicated
  (ppo/distributed.py). members > 0: a sweep phase: init and run are vmapped over a leading member axis, which is
  the one sharded over the mesh (each member's envs stay on one device)."""
  mesh = mesh if mesh is not None else distributed.make_mesh(cfg.num_devices)
  pc = program_config(cfg)
  key = pc
  if pc.sg.lr_schedule == "constant" and pc.aa.lr_schedule == "constant":
    # The step budgets only size the step-size schedules: with constant ones they are host-side iteration counts,
    # so e.g. a phase-2-only run (phase1_steps=0) shares phase 2's compiled programs with a full run.
    key = dataclasses.replace(pc, phase1_steps=0, phase2_steps=0)
  return dataclasses.replace(_make_phase(key, phase, mesh, members), cfg=pc, iterations=_iterations(pc, phase))


@functools.lru_cache(maxsize=8)
def _make_phase(cfg: TrainConfig, phase: int, mesh, members: int) -> Phase:
  if members:
    if members % mesh.size:
      raise ValueError(f"sweep members ({members}) must be divisible by the device count ({mesh.size})")
    G = cfg.env_groups or 1
    if cfg.num_envs % G:
      raise ValueError(f"num_envs ({cfg.num_envs}) must be divisible by env_groups ({G})")
  else:
    G = distributed.groups_for(cfg.num_envs, cfg.env_groups, mesh)
  Bg = cfg.num_envs // G
  # env groups one device holds (a sweep's members each keep their G groups on one device): sizes the network passes
  groups_per_device = (members // mesh.size) * G if members else max(1, G // mesh.size)
  for name, p in (("sg", cfg.sg), ("aa", cfg.aa)):
    if (Bg * cfg.unroll_length) % p.num_minibatches:
      raise ValueError(f"num_envs / env_groups * unroll_length ({Bg * cfg.unroll_length}) must be divisible by "
                       f"{name}.num_minibatches ({p.num_minibatches})")
  if members:   # the member axis is the sharded one (outside); nothing inside a member is constrained
    shard = rep = lambda t: t  # noqa: E731
  else:
    shard = functools.partial(distributed.constrain, sharding=distributed.data_sharding(mesh))
    rep = functools.partial(distributed.constrain, sharding=distributed.replicated(mesh))
  env = make_env(cfg, phase)
  # The reset pool is refreshed once per rollout (after the scan), not inside every env step (envs/wrappers.py).
  batched = AutoReset(VmapWrapper(env), refresh_in_step=False)
  sg, aa = make_agents(cfg)
  adversarial = phase == 2
  base = env.env if adversarial else env
  crit = np.asarray(base.spec_table.critical)    # critical specs (S1, S2, S12 by default) of the env's table
  gamma = cfg.sg.gamma
  bonus = (-cfg.completion_bonus / (1.0 - gamma)) if cfg.completion_bonus < 0 else cfg.completion_bonus
  violation_cost = cfg.violation_penalty / (1.0 - gamma)
  stall_cost = cfg.stall_penalty / (1.0 - gamma)
  spec_weights = base.reward_fn.weights(base.config.critical_weight)   # [n_specs]
  rc = adversarial and cfg.variant == "rc"
  B = cfg.num_envs

  nets = functools.partial(network_precision, cfg.matmul_precision)   # the agents' networks only, not the env
  reset = jax.vmap(batched.reset)   # [G, B/G] keys -> G independent auto-reset groups
  lanes = resolve_ekf_kernel(cfg.env.ekf_kernel) == "lanes"   # the env's EKF kernel: a Pallas call
  step = group_step(batched, None if members else mesh, per_device=lanes)
  if lanes and not members:   # group_step's shard_map
    distributed.use_gspmd_for_shard_map(mesh)
  refresh_pool = jax.vmap(lambda s: batched.refresh_pool(s, cfg.unroll_length))

  def init(key, sg_state, aa_state) -> Carry:
    k_env, k_run = jax.random.split(key)
    keys = jax.random.split(k_env, B)
    state = shard(reset(keys.reshape((G, Bg) + keys.shape[1:])))
    return Carry(sg=rep(sg_state), aa=rep(aa_state), env_state=state, ep_return=shard(jnp.zeros((G, Bg))),
                 ep_return_aa=shard(jnp.zeros((G, Bg))), rng=rep(k_run), iteration=jnp.zeros((), jnp.int32))

  def aa_obs(state, setpoint):
    info = state.info
    keys = ("adv", "time", "mission") + (("alarm",) if "alarm" in info else ())
    light = state.replace(info={k: info[k] for k in keys}, pipeline_state=None, metrics={})
    return jax.vmap(jax.vmap(env.observe))(light, setpoint)

  def act_step(c, key):
    sg_s, aa_s, state, ep_ret, ep_ret_aa, totals = c
    k1, k2 = jax.random.split(key)
    obs = state.obs
    with jax.named_scope("policy"), nets():
      a_sg, logp_sg = sg.sample(sg_s, obs, k1)
      setpoint = networks.to_setpoint(cfg.action, a_sg, cfg.action_scales)
    phase_now = state.info["sim"]["nav"].phase
    mask = override_in_phase(base.config.override_phases, phase_now).astype(jnp.float32)
    if rc:
      mask = mask * state.info["alarm"]
    out = {}
    if adversarial:
      with jax.named_scope("attack_agent"), nets():
        o_aa = aa_obs(state, setpoint)
        a_aa, logp_aa = aa.sample(aa_s, o_aa, k2)
      with jax.named_scope("env_step"):
        nxt = step(state, jnp.concatenate([setpoint, a_aa], axis=-1))
    else:
      with jax.named_scope("env_step"):
        nxt = step(state, setpoint)
    nxt = shard(nxt)
    info = nxt.info
    done = nxt.done
    trunc = info["truncation"]
    last = info["last_episode"]
    complete = last["complete"] * done
    term = done * (1.0 - trunc)
    r_sg = jnp.where(jnp.isfinite(nxt.reward), nxt.reward, 0.0) + bonus * complete
    if cfg.violation_penalty > 0:   # a spec whose violation became certain in this step
      r_sg = r_sg - violation_cost * violation_onsets(base.spec_eval, spec_weights, state.info, info, done)
    if cfg.stall_penalty > 0:   # the episode ended in this step in a stall (a failed mission no spec charges)
      r_sg = r_sg - stall_cost * last["stall"] * done
    final_obs = info["final_obs"]   # the observation the step produced, before any auto-reset
    # Values are computed after the rollout, in a few large batches (`values`), not here.
    r_learn = r_sg
    if cfg.action_cost > 0 and base.config.override_residual:   # residual setpoints only, not absolute moves
      r_learn = r_sg - networks.residual_cost(setpoint, cfg.action_scales, mask, cfg.action_cost)
    if cfg.progress_reward > 0:   # metres closer to the current goal than ever on this leg (the env's metric)
      r_learn = r_learn + cfg.progress_reward * nxt.metrics["progress"]
    out["sg"] = {"obs": obs, "next_obs": final_obs, "action": a_sg, "logp": logp_sg, "reward": r_learn,
                 "terminated": term, "done": done, "mask": mask}
    ep_ret = ep_ret + r_sg
    if adversarial:
      r_aa = env.reward(r_sg, info["aa_extra"])
      with jax.named_scope("attack_agent"):
        o_aa_next = aa_obs(nxt.replace(obs=final_obs), setpoint)  # approximation: next attacker obs from final obs
      # the agent's own episodes (a scripted campaign's flies its attack, not the agent's: no sample of it)
      agent_turn = (1.0 - state.info["scripted"].astype(jnp.float32) if "scripted" in state.info
                    else jnp.ones_like(done))
      out["aa"] = {"obs": o_aa, "next_obs": o_aa_next, "action": a_aa, "logp": logp_aa, "reward": r_aa,
                   "terminated": term, "done": done, "mask": agent_turn}
      ep_ret_aa = ep_ret_aa + r_aa
    # ---- episode statistics (finished episodes only), accumulated per env and summed once after the rollout ----
    with jax.named_scope("episode_stats"):
      stats = _episode_stats(info, done, complete, r_sg, mask, ep_ret, ep_ret_aa)
      stats.update(_attack_stats(state.info, info, done))
      totals = jax.tree.map(jnp.add, totals, stats)
    ep_ret = ep_ret * (1.0 - done)
    ep_ret_aa = ep_ret_aa * (1.0 - done)
    return (sg_s, aa_s, nxt, ep_ret, ep_ret_aa, totals), out

  def _attack_stats(before, after, done):
    """{aa_* STAT_KEYS: [G, B/G]} this step's attack-agent choices: an attack launched in this step (its onset, its
    sensors) and the attack time it used; zeros without an attack agent."""
    zero = jnp.zeros_like(done)
    if not adversarial:
      return {k: zero for k in ("aa_launches", "aa_onset_sum", "aa_attack_s") + AA_SENSOR_KEYS}
    a0, a1 = before["adv"], after["adv"]   # after: the next episode's fresh state where this one ended
    launch = (a1["started"] & ~a0["started"] & (done == 0)).astype(jnp.float32)
    if "scripted" in before:   # the agent's launches only
      launch = launch * (1.0 - before["scripted"].astype(jnp.float32))
    out = {"aa_launches": launch, "aa_onset_sum": launch * a1["onset"], "aa_attack_s": a1["on"] * base.dt}
    out.update({k: launch * a1["mask"][..., i] for i, k in enumerate(AA_SENSOR_KEYS)})
    return out

  def _episode_stats(info, done, complete, r_sg, mask, ep_ret, ep_ret_aa):
    """{name: [G, B/G] float32} this step's contribution of each env to the iteration's STAT_KEYS totals."""
    last = info["last_episode"]
    viol = jnp.any(info["final_spec_robustness"] < 0, axis=-1).astype(jnp.float32)
    crit_viol = jnp.any((info["final_spec_robustness"] < 0) & crit, axis=-1).astype(jnp.float32)
    attacked = last["attacked"]
    stats = {"episodes": done, "complete": complete, "collision": last["collision"] * done,
             "crash": last["crash"] * done, "stall": last["stall"] * done, "nan": last["nan"] * done,
             "fence_breach": last["fence_breach"] * done, "violated": viol * done, "critical": crit_viol * done,
             "attacked": attacked * done, "attacked_complete": attacked * complete,
             "attacked_violated": attacked * viol * done, "return_sum": ep_ret * done,
             "return_aa_sum": ep_ret_aa * done, "reward_sum": r_sg, "override_steps": mask}
    assert tuple(stats) == STAT_KEYS[:len(stats)]
    return stats

  # How often one env can be truncated in steps 0..T-2 of a rollout (EnvBase.min_truncated_episode_steps): SG's
  # next-step values then come from the next step's observations (bootstrap_values).
  T = cfg.unroll_length
  max_trunc = -(-(T - 1) // base.min_truncated_episode_steps())

  def values(agent, agent_state, tr, p, shifted: bool):
    """(V(obs), V(next_obs)), each [T, G, B/G], for a rollout's observations [T, G, B/G, n]: the value network
    run after the rollout in a few large passes (2T / num_minibatches steps each, fewer where that would put more
    than 2 x max_rows_per_pass rows on a device: forward only, half the update's rows' memory), not inside every
    env step.
    shifted: next_obs[t] is obs[t+1] wherever the env did not finish (SG's; the attacker's observation holds the
    next setpoint), so V(next_obs) comes from V(obs) but at truncations (bootstrap_values)."""
    per_pass = max(1, min(2 * (T // p.num_minibatches), 2 * p.max_rows_per_pass // (Bg * groups_per_device)))
    value_fn = functools.partial(agent.value_of, agent_state)
    with nets():
      if shifted and 1 + max_trunc < T:
        return bootstrap_values(value_fn, tr["obs"], tr["next_obs"], tr["done"], tr["terminated"], max_trunc,
                                per_pass)
      v = jax.lax.map(lambda x: value_fn(jnp.stack(x)), (tr["obs"], tr["next_obs"]), batch_size=max(1, per_pass // 2))
    return v[:, 0], v[:, 1]

  def advantages(agent, agent_state, tr, p, shifted: bool):
    """Values and GAE over [T, G, B/G], then [T, G, B/G, ...] -> [T, B, ...] for losses.update (which splits B
    into G); only what the PPO loss reads goes on (losses.ppo_loss)."""
    with jax.named_scope("values"):
      value, next_value = values(agent, agent_state, tr, p, shifted)
    with jax.named_scope("gae"):
      adv, target = losses.gae(tr["reward"], value, next_value, tr["terminated"], tr["done"], p.gamma, p.gae_lambda)
    batch = {k: tr[k] for k in ("obs", "action", "logp", "mask")}
    return jax.tree.map(lambda a: a.reshape((a.shape[0], B) + a.shape[3:]),
                        dict(batch, value=value, adv=adv, target=target))

  def upd(agent, state, batch, key):
    with jax.named_scope("ppo_update"), nets():
      chunks = losses.chunks_per_minibatch(agent.ppo, Bg * T // agent.ppo.num_minibatches, groups_per_device)
      return losses.update(agent, state, batch, key, groups=G, constrain=shard, chunks=chunks)

  def one_iteration(carry: Carry, _, turn=None):
    """One iteration; turn: phase 2's learner (0 SG, 1 AA), from carry.iteration unless given (sweeps pass the
    members' common turn unbatched, so lax.cond stays a branch under vmap instead of running both updates)."""
    rng, k_roll, k_sg, k_aa = jax.random.split(carry.rng, 4)
    # per-env running sums of the episode statistics (elementwise adds in the step; one reduction per iteration)
    totals = {k: jnp.zeros_like(carry.ep_return) for k in STAT_KEYS}
    init_c = (carry.sg, carry.aa, carry.env_state, carry.ep_return, carry.ep_return_aa, totals)
    (_, _, state, ep_ret, ep_ret_aa, totals), tr = jax.lax.scan(
        act_step, init_c, jax.random.split(k_roll, cfg.unroll_length))
    with jax.named_scope("pool_refresh"):
      state = refresh_pool(state)
    with jax.named_scope("episode_stats"):
      stats = jax.tree.map(jnp.sum, totals)
    sg_batch = advantages(sg, carry.sg, tr["sg"], cfg.sg, shifted=True)
    sg_shape = jax.eval_shape(lambda: upd(sg, carry.sg, sg_batch, k_sg)[1])
    zeros = lambda shape: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)
    if adversarial:
      turn = (carry.iteration // cfg.alternate_iters) % 2 if turn is None else turn
      aa_batch = advantages(aa, carry.aa, tr["aa"], cfg.aa, shifted=False)
      aa_shape = jax.eval_shape(lambda: upd(aa, carry.aa, aa_batch, k_aa)[1])
      sg_new, sg_aux = jax.lax.cond(turn == 0, lambda: upd(sg, carry.sg, sg_batch, k_sg),
                                    lambda: (carry.sg, zeros(sg_shape)))
      aa_new, aa_aux = jax.lax.cond(turn == 1, lambda: upd(aa, carry.aa, aa_batch, k_aa),
                                    lambda: (carry.aa, zeros(aa_shape)))
    else:
      turn = jnp.zeros((), jnp.int32)
      sg_new, sg_aux = upd(sg, carry.sg, sg_batch, k_sg)
      aa_new, aa_aux = carry.aa, {}
    metrics = dict(stats, turn=turn, **{f"sg_{k}": v for k, v in sg_aux.items()},
                   **{f"aa_{k}": v for k, v in aa_aux.items()})
    new = Carry(sg=rep(sg_new), aa=rep(aa_new), env_state=shard(state), ep_return=shard(ep_ret),
                ep_return_aa=shard(ep_ret_aa), rng=rep(rng), iteration=carry.iteration + 1)
    return new, metrics

  def run(carry: Carry):
    return jax.lax.scan(one_iteration, carry, None, length=cfg.iters_per_call)

  def run_members(c):
    """K iterations of every member: carry [S, ...] -> (carry, metrics [S, K]); all members share the turn."""
    def body(c, _):
      turn = (c.iteration[0] // cfg.alternate_iters) % 2
      return jax.vmap(lambda ci: one_iteration(ci, None, turn))(c)
    c, m = jax.lax.scan(body, c, None, length=cfg.iters_per_call)
    return c, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), m)

  if members:
    msh = functools.partial(distributed.constrain, sharding=distributed.data_sharding(mesh))
    init_fn = jax.jit(lambda k, s, a: msh(jax.vmap(init)(k, s, a)))
    # Members never talk to each other: XLA's SPMD partitioner splits them along the member axis. With the lanes EKF
    # kernel (a Pallas call, which has no sharding rule) each device runs its own members explicitly (shard_map).
    spec = jax.sharding.PartitionSpec(distributed.AXIS)
    per_device = run_members
    if mesh.size > 1 and lanes:
      distributed.use_gspmd_for_shard_map(mesh)
      per_device = jax.shard_map(run_members, mesh=mesh, in_specs=(spec,), out_specs=spec, check_vma=False)
    run_fn = jax.jit(lambda c: msh(per_device(msh(c))), donate_argnums=0)
  else:
    init_fn, run_fn = jax.jit(init), jax.jit(run, donate_argnums=0)
  return Phase(cfg=cfg, number=phase, env=env, batched=batched, sg=sg, aa=aa, init=init_fn, run=run_fn,
               iterations=_iterations(cfg, phase), mesh=mesh, groups=G)


@dataclasses.dataclass(frozen=True)
class DeterministicPolicy:
  """Hashable deterministic SpecGuard controller for evaluation: params {'policy', 'mean', 'std'} and obs [B, n] ->
  setpoint [B, len(speeds)] (velocity m/s [3], then the acceleration residual m/s^2 [3] of an override_attitude run;
  yaw frame): mode of the action head on clipped normalised observations. speeds: the scale per output."""
  policy: networks.Policy
  kind: str
  speeds: tuple
  clip: float

  def __call__(self, p, obs):
    x = jnp.clip((obs - p["mean"]) / p["std"], -self.clip, self.clip)
    return networks.to_setpoint(self.kind, self.policy.mode(p["policy"], x), self.speeds)


def eval_env(cfg: TrainConfig):
  """The deployment env of the run's variant (scripted attacks are given per episode by the evaluator). One object
  per distinct env setting, so a second held-out evaluation (e.g. after a resume) reuses the compiled rollout."""
  return _eval_env(cfg.vehicle, env_config(cfg, "eval"))


@functools.lru_cache(maxsize=8)
def _eval_env(vehicle, config):
  return _make(vehicle, config)


def _heldout_job(cfg: TrainConfig, sg_state, missions: int) -> dict:
  """The held-out evaluation's rollout arguments (evaluation.precompile's job) for a SpecGuard agent state."""
  fn = DeterministicPolicy(sg_policy(cfg), cfg.action, cfg.action_scales, cfg.obs_clip)
  p = {"policy": sg_state.params["policy"], "mean": sg_state.normalizer.mean, "std": sg_state.normalizer.std}
  return {"env": eval_env(cfg), "policy": fn, "policy_params": p, "missions": missions,
          "believed": False}   # as evaluation.evaluate flies it (no blind-violation record)


def heldout(cfg: TrainConfig, sg_state: losses.AgentState, missions: int, seed: int = 10_000) -> dict:
  """Held-out quality of the trained SpecGuard policy (specguard_jax.evaluation) in the run's deployment env."""
  job = _heldout_job(cfg, sg_state, missions)
  return evaluation.evaluate(job["env"], job["policy"], job["policy_params"], missions=missions, seed=seed)


def precompile_heldout(cfg: TrainConfig, sg_state, missions: int) -> None:
  """Compile `heldout`'s rollout for an agent state of these shapes (abstract leaves are fine) and keep it for
  heldout's call (evaluation.precompile); used by the runner's compile-ahead thread (ppo/ahead.py)."""
  job = _heldout_job(cfg, sg_state, missions)
  evaluation.precompile([dict(job, settings=evaluation.default_settings())], workers=1)
