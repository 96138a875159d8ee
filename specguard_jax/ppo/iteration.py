"""One phase of training as compiled functions: acting (lax.scan over the vmapped env), GAE and the PPO updates of
SpecGuard (SG) and the attack agent (AA), with K iterations per host call.

Phase 1 (compliance): SpecGuard flies every cruise/loiter segment (velocity-setpoint override), no attacks.
Phase 2 (adversarial, paper Algorithm 2): the attack agent drives the attacks (ppo/attacker.py) against the
variant's controller (RC: override only while the detector's alarm is up; PC: always), with state reconstruction in
the loop unless disabled. Iterations alternate: `alternate_iters` iterations update SG with AA frozen, then the
reverse; the turn is data in the carry, so both branches are one compiled program (lax.cond).

Reward seen by SG: the env's per-step compliance reward (in [0, 1] normalised) + the completion bonus on mission
completion; AA's: AttackerEnv.reward (zero-sum by default). SG's policy loss is masked to the steps where its action
reached the vehicle (override active: cruise/loiter, and the alarm up for RC); its value function learns from all.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
from brax.envs.base import State
from brax.envs.wrappers.training import VmapWrapper
from flax import struct

import envs as envs_lib
from envs.wrappers import AutoReset
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.ppo import attacker as attacker_lib
from specguard_jax.ppo import losses, networks
from specguard_jax.ppo.config import TrainConfig

@struct.dataclass
class Carry:
  """Everything a phase's iterations thread through (checkpointed whole)."""
  sg: losses.AgentState
  aa: losses.AgentState
  env_state: State
  ep_return: jnp.ndarray      # [B] SG return of the running episodes
  ep_return_aa: jnp.ndarray   # [B]
  rng: jnp.ndarray
  iteration: jnp.ndarray      # [] int32 iterations done in this phase


def make_env(cfg: TrainConfig, phase: int):
  """The unbatched env of a phase (phase 2 wrapped in AttackerEnv)."""
  common = dict(worlds=tuple(cfg.worlds), reward=cfg.reward, override_frame="body", override_residual=cfg.residual)
  if phase == 1:
    return envs_lib.make(cfg.vehicle, control_mode="override", **common)
  env = envs_lib.make(cfg.vehicle, control_mode="reactive" if cfg.variant == "rc" else "override",
                      detector=cfg.detector, detector_delay=cfg.detector_delay,
                      reconstruction=cfg.reconstruction, **common)
  acfg = attacker_lib.AttackerConfig(sensors=tuple(cfg.attack_sensors), max_duration_s=cfg.attack_max_duration_s,
                                     alpha=cfg.attack_alpha, beta=cfg.attack_beta, gamma=cfg.attack_gamma)
  return attacker_lib.AttackerEnv(env, acfg, cfg.speeds)


def sg_policy(cfg: TrainConfig) -> networks.Policy:
  return networks.Policy(cfg.action, 6 if cfg.action == "discrete" else 3, tuple(cfg.hidden), cfg.activation,
                         init_log_std=cfg.init_log_std)


def aa_policy(cfg: TrainConfig) -> networks.Policy:
  return networks.Policy("gaussian", attacker_lib.N_ACT, (128, 128), "tanh", init_log_std=0.0)


def _iterations(cfg: TrainConfig, phase: int) -> int:
  steps = cfg.phase1_steps if phase == 1 else cfg.phase2_steps
  return max(1, -(-steps // cfg.steps_per_iter))


def make_agents(cfg: TrainConfig):
  """(SG agent, AA agent); their step-size schedules span the whole run's updates."""
  n_sg = (_iterations(cfg, 1) + _iterations(cfg, 2)) * cfg.sg.update_epochs * cfg.sg.num_minibatches
  n_aa = _iterations(cfg, 2) * cfg.aa.update_epochs * cfg.aa.num_minibatches
  sg = losses.make_agent(sg_policy(cfg), tuple(cfg.hidden), cfg.activation, cfg.sg, n_sg, cfg.obs_clip)
  aa = losses.make_agent(aa_policy(cfg), (128, 128), "tanh", cfg.aa, n_aa, cfg.obs_clip)
  return sg, aa


@dataclasses.dataclass
class Phase:
  """A phase's env and compiled entry points: init(key, sg_state, aa_state) -> Carry; run(carry) -> (carry,
  metrics [K])."""
  cfg: TrainConfig
  number: int
  env: Any
  batched: Any
  sg: losses.Agent
  aa: losses.Agent
  init: Any
  run: Any
  iterations: int


@functools.lru_cache(maxsize=8)
def make_phase(cfg: TrainConfig, phase: int) -> Phase:
  """The phase's env and compiled functions (cached per config: a resumed run in the same process reuses them)."""
  env = make_env(cfg, phase)
  batched = AutoReset(VmapWrapper(env))
  sg, aa = make_agents(cfg)
  adversarial = phase == 2
  base = env.env if adversarial else env
  crit = jnp.asarray(base.spec_table.critical)   # critical specs (S1, S2, S12 by default) of the env's table
  gamma = cfg.sg.gamma
  bonus = (-cfg.completion_bonus / (1.0 - gamma)) if cfg.completion_bonus < 0 else cfg.completion_bonus
  rc = adversarial and cfg.variant == "rc"
  B = cfg.num_envs

  def init(key, sg_state, aa_state) -> Carry:
    k_env, k_run = jax.random.split(key)
    state = batched.reset(jax.random.split(k_env, B))
    return Carry(sg=sg_state, aa=aa_state, env_state=state, ep_return=jnp.zeros(B), ep_return_aa=jnp.zeros(B),
                 rng=k_run, iteration=jnp.zeros((), jnp.int32))

  def aa_obs(state, setpoint):
    info = state.info
    keys = ("adv", "time", "mission") + (("alarm",) if "alarm" in info else ())
    light = state.replace(info={k: info[k] for k in keys}, pipeline_state=None, metrics={})
    return jax.vmap(env.observe)(light, setpoint)

  def act_step(c, key):
    sg_s, aa_s, state, ep_ret, ep_ret_aa = c
    k1, k2 = jax.random.split(key)
    obs = state.obs
    a_sg, logp_sg, v_sg = sg.act(sg_s, obs, k1)
    setpoint = networks.to_setpoint(cfg.action, a_sg, cfg.speeds)
    phase_now = state.info["sim"]["nav"].phase
    mask = ((phase_now == nav_lib.CRUISE) | (phase_now == nav_lib.LOITER)).astype(jnp.float32)
    if rc:
      mask = mask * state.info["alarm"]
    out = {}
    if adversarial:
      o_aa = aa_obs(state, setpoint)
      a_aa, logp_aa, v_aa = aa.act(aa_s, o_aa, k2)
      nxt = batched.step(state, jnp.concatenate([setpoint, a_aa], axis=-1))
    else:
      nxt = batched.step(state, setpoint)
    info = nxt.info
    done = nxt.done
    trunc = info["truncation"]
    last = info["last_episode"]
    complete = last["complete"] * done
    term = done * (1.0 - trunc)
    r_sg = jnp.where(jnp.isfinite(nxt.reward), nxt.reward, 0.0) + bonus * complete
    final_obs = info["final_obs"]
    out["sg"] = {"obs": obs, "action": a_sg, "logp": logp_sg, "value": v_sg, "reward": r_sg,
                 "next_value": sg.value_of(sg_s, final_obs), "terminated": term, "done": done, "mask": mask}
    ep_ret = ep_ret + r_sg
    if adversarial:
      r_aa = env.reward(r_sg, info["aa_extra"])
      o_aa_next = aa_obs(nxt.replace(obs=final_obs), setpoint)  # approximation: next attacker obs from final obs
      out["aa"] = {"obs": o_aa, "action": a_aa, "logp": logp_aa, "value": v_aa, "reward": r_aa,
                   "next_value": aa.value_of(aa_s, o_aa_next), "terminated": term, "done": done,
                   "mask": jnp.ones_like(done)}
      ep_ret_aa = ep_ret_aa + r_aa
    # ---- episode statistics (finished episodes only) ----
    viol = jnp.any(info["final_spec_robustness"] < 0, axis=-1).astype(jnp.float32)
    crit_viol = jnp.any((info["final_spec_robustness"] < 0) & crit, axis=-1).astype(jnp.float32)
    attacked = last["attacked"]
    stats = {"episodes": done, "complete": complete, "collision": last["collision"] * done,
             "crash": last["crash"] * done, "stall": last["stall"] * done, "nan": last["nan"] * done,
             "fence_breach": last["fence_breach"] * done, "violated": viol * done, "critical": crit_viol * done,
             "attacked": attacked * done, "attacked_complete": attacked * complete,
             "attacked_violated": attacked * viol * done, "return_sum": ep_ret * done,
             "return_aa_sum": ep_ret_aa * done, "reward_sum": r_sg, "override_steps": mask}
    stats = jax.tree.map(lambda x: jnp.sum(x), stats)
    ep_ret = ep_ret * (1.0 - done)
    ep_ret_aa = ep_ret_aa * (1.0 - done)
    return (sg_s, aa_s, nxt, ep_ret, ep_ret_aa), (out, stats)

  def advantages(tr, p):
    adv, target = losses.gae(tr["reward"], tr["value"], tr["next_value"], tr["terminated"], tr["done"],
                             p.gamma, p.gae_lambda)
    return dict(tr, adv=adv, target=target)

  def one_iteration(carry: Carry, _):
    rng, k_roll, k_sg, k_aa = jax.random.split(carry.rng, 4)
    init_c = (carry.sg, carry.aa, carry.env_state, carry.ep_return, carry.ep_return_aa)
    (_, _, state, ep_ret, ep_ret_aa), (tr, stats) = jax.lax.scan(
        act_step, init_c, jax.random.split(k_roll, cfg.unroll_length))
    stats = jax.tree.map(jnp.sum, stats)
    sg_batch = advantages(tr["sg"], cfg.sg)
    sg_shape = jax.eval_shape(lambda: losses.update(sg, carry.sg, sg_batch, k_sg)[1])
    zeros = lambda shape: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)
    if adversarial:
      turn = (carry.iteration // cfg.alternate_iters) % 2
      aa_batch = advantages(tr["aa"], cfg.aa)
      aa_shape = jax.eval_shape(lambda: losses.update(aa, carry.aa, aa_batch, k_aa)[1])
      sg_new, sg_aux = jax.lax.cond(turn == 0, lambda: losses.update(sg, carry.sg, sg_batch, k_sg),
                                    lambda: (carry.sg, zeros(sg_shape)))
      aa_new, aa_aux = jax.lax.cond(turn == 1, lambda: losses.update(aa, carry.aa, aa_batch, k_aa),
                                    lambda: (carry.aa, zeros(aa_shape)))
    else:
      turn = jnp.zeros((), jnp.int32)
      sg_new, sg_aux = losses.update(sg, carry.sg, sg_batch, k_sg)
      aa_new, aa_aux = carry.aa, {}
    metrics = dict(stats, turn=turn, **{f"sg_{k}": v for k, v in sg_aux.items()},
                   **{f"aa_{k}": v for k, v in aa_aux.items()})
    new = Carry(sg=sg_new, aa=aa_new, env_state=state, ep_return=ep_ret, ep_return_aa=ep_ret_aa, rng=rng,
                iteration=carry.iteration + 1)
    return new, metrics

  def run(carry: Carry):
    return jax.lax.scan(one_iteration, carry, None, length=cfg.iters_per_call)

  return Phase(cfg=cfg, number=phase, env=env, batched=batched, sg=sg, aa=aa, init=jax.jit(init),
               run=jax.jit(run, donate_argnums=0), iterations=_iterations(cfg, phase))


@dataclasses.dataclass(frozen=True)
class DeterministicPolicy:
  """Hashable deterministic SpecGuard controller for evaluation: params {'policy', 'mean', 'std'} and obs [B, n] ->
  velocity setpoint [B, 3] (m/s, yaw frame): mode of the action head on clipped normalised observations."""
  policy: networks.Policy
  kind: str
  speeds: tuple
  clip: float

  def __call__(self, p, obs):
    x = jnp.clip((obs - p["mean"]) / p["std"], -self.clip, self.clip)
    return networks.to_setpoint(self.kind, self.policy.mode(p["policy"], x), self.speeds)


def eval_env(cfg: TrainConfig):
  """The deployment env of the run's variant (scripted attacks are given per episode by the evaluator)."""
  return envs_lib.make(cfg.vehicle, worlds=tuple(cfg.worlds), reward=cfg.reward, override_frame="body",
                       override_residual=cfg.residual,
                       control_mode="reactive" if cfg.variant == "rc" else "override", detector=cfg.eval_detector,
                       detector_delay=cfg.detector_delay, reconstruction=cfg.reconstruction)


def heldout(cfg: TrainConfig, sg_state: losses.AgentState, missions: int, seed: int = 10_000) -> dict:
  """Held-out quality of the trained SpecGuard policy (specguard_jax.evaluation) in the run's deployment env."""
  from specguard_jax import evaluation
  env = eval_env(cfg)
  fn = DeterministicPolicy(sg_policy(cfg), cfg.action, tuple(cfg.speeds), cfg.obs_clip)
  p = {"policy": sg_state.params["policy"], "mean": sg_state.normalizer.mean, "std": sg_state.normalizer.std}
  return evaluation.evaluate(env, fn, p, missions=missions, seed=seed)
