"""Red-team attack agents: the best response of the attack agent (ppo/attacker.py) to one frozen controller.

The controller under evaluation (specguard_jax.controllers: its env overrides and its policy) is fixed: only the
attack agent learns, by PPO (ppo/losses.py), in the controller's own deployment env wrapped in AttackerEnv, with the
zero-sum reward of the trainer's phase 2 (R_AA = -(the compliance reward + the completion bonus on completion)).
Every controller gets the same budget (RedteamConfig: envs x steps), seeded.

The trained agent is saved as <dir>/redteam.msgpack (flax.serialization: {'policy', 'mean', 'std'}) and
<dir>/redteam.json (the agent's and the training's configuration, the per-iteration training history), reloaded
with `load`, and flown deterministically (the mode of its Gaussian head) as the evaluation's red-team setting
(specguard_jax.evaluation.redteam_setting; `RedteamAgent` is the rollout's `attacker`). It chooses the sensors (up
to max_sensors at once), the bias, the onset (not before min_onset_s: after take-off, when a controller has a
trusted state to recover from, as the random campaigns' onsets) and the duration of its one attack window per mission
(at most max_duration_s).
"""

from __future__ import annotations

import dataclasses
import json
import os

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
from specguard_jax import third_party  # noqa: F401 - before brax: mujoco.mjx without its Warp notices
from brax.envs.wrappers.training import VmapWrapper

from envs.wrappers import AutoReset, violation_onsets
from specguard_jax.ppo import attacker as attacker_lib
from specguard_jax.ppo import losses, networks
from specguard_jax.ppo.config import PPOConfig, TrainConfig
from specguard_jax.types import SENSOR_NAMES

AGENT_FILE = "redteam.msgpack"
META_FILE = "redteam.json"
HIDDEN = (128, 128)   # the trainer's attack agent (ppo.iteration.aa_policy)


@dataclasses.dataclass(frozen=True)
class RedteamConfig:
  """Training budget and game of one red-team agent. num_envs parallel missions, unroll_length steps each per PPO
  iteration, steps: total env steps (rounded up to whole iterations). sensors / max_duration_s / max_sensors /
  min_onset_s: what the agent may attack, for how long per mission (s), how many sensors at once, from when (s).
  completion_bonus / violation_penalty / speeds: as TrainConfig's (the zero-sum reward, the setpoint normalisation of
  the agent's observation; violation_penalty > 0 pays the agent on each spec violation's onset, the aim of a best
  response). seed: initial networks, missions and exploration."""
  num_envs: int = 32
  unroll_length: int = 32
  steps: int = 65_536
  sensors: tuple = SENSOR_NAMES
  max_duration_s: float = TrainConfig.attack_max_duration_s
  max_sensors: int = 2
  min_onset_s: float = 10.0
  completion_bonus: float = TrainConfig.completion_bonus
  violation_penalty: float = TrainConfig.violation_penalty
  speeds: tuple = TrainConfig.speeds
  ppo: PPOConfig = PPOConfig(ent_coef=0.01, num_minibatches=4)
  seed: int = 0

  def __post_init__(self):
    if self.num_envs < 1 or self.unroll_length < 1 or self.steps < 1:
      raise ValueError("red-team num_envs, unroll_length and steps must be >= 1")
    if not self.violation_penalty >= 0:
      raise ValueError(f"red-team violation_penalty must be >= 0, got {self.violation_penalty}")
    if (self.num_envs * self.unroll_length) % self.ppo.num_minibatches:
      raise ValueError(f"red-team num_envs * unroll_length ({self.num_envs * self.unroll_length}) must be divisible "
                       f"by num_minibatches ({self.ppo.num_minibatches})")
    self.attack_config()   # validates

  def attack_config(self) -> attacker_lib.AttackerConfig:
    """The agent's game: the zero-sum reward alone (gamma = 0: a best response maximises violations, no shaping)."""
    return attacker_lib.AttackerConfig(sensors=tuple(self.sensors), max_duration_s=self.max_duration_s, gamma=0.0,
                                       max_sensors=min(self.max_sensors, len(self.sensors)),
                                       min_onset_s=self.min_onset_s)

  @property
  def iterations(self) -> int:
    return max(1, -(-self.steps // (self.num_envs * self.unroll_length)))


# 'ci': CPU minutes per controller (drone, short missions); 'full': a GPU-sized budget (the trainer's env count).
BUDGETS = {"ci": RedteamConfig(),
           "full": RedteamConfig(num_envs=4096, unroll_length=32, steps=50_000_000,
                                 ppo=PPOConfig(ent_coef=0.01, num_minibatches=8))}


@dataclasses.dataclass(frozen=True)
class RedteamAgent:
  """A trained attack agent as the evaluation rollout's `attacker` (hashable: a static jit argument); its arrays
  are the separate `params` {'policy', 'mean', 'std'}. dt: the env step (s) its attack-time budget counts in."""
  attack: attacker_lib.AttackerConfig
  speeds: tuple
  dt: float
  obs_clip: float = 10.0
  hidden: tuple = HIDDEN

  @property
  def policy(self) -> networks.Policy:
    return networks.Policy("gaussian", attacker_lib.N_ACT, tuple(self.hidden), "tanh", init_log_std=0.0)

  def init(self, b: int):
    """The agent's state of b missions before their first step: {name: [b, ...]}."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), attacker_lib.adv_init())

  def observe(self, state, adv, setpoint):
    """Observations [b, N_OBS] of a batched env state, the agent's state [b, ...] and the controller's setpoints
    [b, 3] (m/s)."""
    info = state.info
    keys = ("time", "mission") + (("alarm",) if "alarm" in info else ())
    light = state.replace(info={k: info[k] for k in keys}, pipeline_state=None, metrics={})
    return jax.vmap(lambda s, a, u: attacker_lib.observation(self.attack, self.speeds, s, a, u))(light, adv,
                                                                                                 setpoint)

  def raw_action(self, params, obs):
    """The deterministic raw action [b, N_ACT] (the Gaussian head's mean) for observations [b, N_OBS]."""
    x = jnp.clip((obs - params["mean"]) / params["std"], -self.obs_clip, self.obs_clip)
    return self.policy.mode(params["policy"], x)

  def act(self, params, state, adv, setpoint):
    """(AttackSchedule [b] of this step, the agent's next state [b, ...]) for a batched env state."""
    raw = self.raw_action(params, self.observe(state, adv, setpoint))
    return jax.vmap(lambda a, r, t: attacker_lib.plan(self.attack, a, r, t, self.dt))(adv, raw, state.info["time"])


def agent_for(env, cfg: RedteamConfig) -> RedteamAgent:
  return RedteamAgent(cfg.attack_config(),
                      tuple(float(s) for s in cfg.speeds), float(env.dt))


def train(env, policy, policy_params, cfg: RedteamConfig, progress=None):
  """Train the best-response attack agent against the frozen controller policy(policy_params, obs [B, n]) ->
  setpoint [B, 3] flying `env` (its deployment env). Returns (RedteamAgent, params {'policy', 'mean', 'std'},
  history: per-iteration {'iteration', 'episodes', 'complete', 'violated', 'attacked', 'return_aa'} over the
  episodes that ended in it). progress(i, n, row): optional per-iteration callback."""
  agent_def = agent_for(env, cfg)
  aenv = attacker_lib.AttackerEnv(env, agent_def.attack, cfg.speeds)
  batched = AutoReset(VmapWrapper(aenv), refresh_in_step=False)
  iters = cfg.iterations
  p = cfg.ppo
  aa = losses.make_agent(agent_def.policy, HIDDEN, "tanh", p, iters * p.update_epochs * p.num_minibatches)
  gamma = p.gamma
  bonus = (-cfg.completion_bonus / (1.0 - gamma)) if cfg.completion_bonus < 0 else cfg.completion_bonus
  violation_cost = cfg.violation_penalty / (1.0 - gamma)
  spec_weights = env.reward_fn.weights(env.config.critical_weight)   # [n_specs]
  B, T = cfg.num_envs, cfg.unroll_length

  @jax.jit
  def init(key):
    k_agent, k_env, k_run = jax.random.split(key, 3)
    state = batched.reset(jax.random.split(k_env, B))
    return losses.with_hparams(aa.init(k_agent, attacker_lib.N_OBS), p), state, k_run

  def obs_of(state, setpoint):
    return agent_def.observe(state, state.info["adv"], setpoint)

  def act_step(c, key):
    aa_s, state = c
    setpoint = policy(policy_params, state.obs)
    o = obs_of(state, setpoint)
    a, logp = aa.sample(aa_s, o, key)
    nxt = batched.step(state, jnp.concatenate([setpoint, a], axis=-1))
    info = nxt.info
    last, done = info["last_episode"], nxt.done
    complete = last["complete"] * done
    r_sg = jnp.where(jnp.isfinite(nxt.reward), nxt.reward, 0.0) + bonus * complete
    if cfg.violation_penalty > 0:   # as the trainer's SpecGuard reward (ppo.iteration), in this agent's gamma
      r_sg = r_sg - violation_cost * violation_onsets(env.spec_eval, spec_weights, state.info, info, done)
    r = aenv.reward(r_sg, info["aa_extra"])
    o_next = obs_of(nxt.replace(obs=info["final_obs"]), setpoint)   # as the trainer: next obs from the final obs
    viol = jnp.any(info["final_spec_robustness"] < 0, axis=-1)
    stats = jnp.stack([done, complete, viol * done, last["attacked"] * done])
    tr = {"obs": o, "next_obs": o_next, "action": a, "logp": logp, "reward": r,
          "terminated": done * (1.0 - info["truncation"]), "done": done, "mask": jnp.ones_like(done)}
    return (aa_s, nxt), (tr, stats)

  @jax.jit
  def iteration(aa_s, state, ep_ret, key):
    k_roll, k_upd = jax.random.split(key)
    (_, state), (tr, stats) = jax.lax.scan(act_step, (aa_s, state), jax.random.split(k_roll, T))
    state = batched.refresh_pool(state, T)
    value = aa.value_of(aa_s, tr["obs"])
    next_value = aa.value_of(aa_s, tr["next_obs"])
    adv, target = losses.gae(tr["reward"], value, next_value, tr["terminated"], tr["done"], gamma, p.gae_lambda)
    batch = {k: tr[k] for k in ("obs", "action", "logp", "mask")}
    aa_s, _ = losses.update(aa, aa_s, dict(batch, value=value, adv=adv, target=target), k_upd)

    def ret(c, x):   # the attack agent's episode returns, summed over the episodes that ended
      r, d = x
      c = c + r
      return c * (1.0 - d), jnp.sum(c * d)
    ep_ret, ended = jax.lax.scan(ret, ep_ret, (tr["reward"], tr["done"]))
    return aa_s, state, ep_ret, jnp.sum(stats, axis=(0, 2)), jnp.sum(ended)

  aa_s, state, key = init(jax.random.PRNGKey(cfg.seed))
  ep_ret = jnp.zeros((B,))
  history = []
  for i in range(iters):
    key, sub = jax.random.split(key)
    aa_s, state, ep_ret, stats, ret_sum = iteration(aa_s, state, ep_ret, sub)
    s = np.asarray(stats)
    n = max(float(s[0]), 1.0)
    row = {"iteration": i + 1, "episodes": int(s[0]), "complete": float(s[1] / n), "violated": float(s[2] / n),
           "attacked": float(s[3] / n), "return_aa": float(ret_sum) / n}
    history.append(row)
    if progress is not None:
      progress(i + 1, iters, row)
  params = {"policy": aa_s.params["policy"], "mean": aa_s.normalizer.mean, "std": aa_s.normalizer.std}
  return agent_def, jax.device_get(params), history


def save(out_dir: str, agent: RedteamAgent, params, cfg: RedteamConfig, history=(), extra: dict | None = None):
  """Write out_dir/redteam.msgpack and out_dir/redteam.json (the directory is created)."""
  os.makedirs(out_dir, exist_ok=True)
  with open(os.path.join(out_dir, AGENT_FILE), "wb") as f:
    f.write(flax.serialization.to_bytes(jax.device_get(params)))
  a = agent.attack
  meta = {"agent": {"sensors": list(a.sensors), "max_duration_s": a.max_duration_s, "scale": a.scale,
                    "alpha": a.alpha, "beta": a.beta, "gamma": a.gamma, "max_sensors": a.max_sensors,
                    "min_onset_s": a.min_onset_s, "speeds": list(agent.speeds),
                    "dt": agent.dt, "obs_clip": agent.obs_clip, "hidden": list(agent.hidden)},
          "training": {**{k: v for k, v in dataclasses.asdict(cfg).items() if k != "ppo"},
                       "ppo": dataclasses.asdict(cfg.ppo), "iterations": cfg.iterations},
          "history": list(history), **(extra or {})}
  meta["training"]["sensors"] = list(cfg.sensors)
  meta["training"]["speeds"] = list(cfg.speeds)
  with open(os.path.join(out_dir, META_FILE), "w") as f:
    json.dump(meta, f, indent=1)


def exists(out_dir: str) -> bool:
  return all(os.path.isfile(os.path.join(out_dir, n)) for n in (AGENT_FILE, META_FILE))


def load(out_dir: str):
  """(RedteamAgent, params, meta dict) saved by `save`; ValueError (one line) when missing or unreadable."""
  try:
    with open(os.path.join(out_dir, META_FILE)) as f:
      meta = json.load(f)
    with open(os.path.join(out_dir, AGENT_FILE), "rb") as f:
      tree = flax.serialization.msgpack_restore(f.read())
    m = meta["agent"]
    attack = attacker_lib.AttackerConfig(sensors=tuple(m["sensors"]), max_duration_s=float(m["max_duration_s"]),
                                         scale=float(m["scale"]), alpha=float(m["alpha"]), beta=float(m["beta"]),
                                         gamma=float(m["gamma"]),
                                         max_sensors=int(m.get("max_sensors", 1)),
                                         min_onset_s=float(m.get("min_onset_s", 0.0)))
    agent = RedteamAgent(attack, tuple(float(s) for s in m["speeds"]), float(m["dt"]), float(m["obs_clip"]),
                         tuple(int(h) for h in m["hidden"]))
  except (OSError, ValueError, KeyError, TypeError) as e:
    raise ValueError(f"{out_dir}: no readable red-team agent ({' '.join(str(e).split())})") from None
  params = jax.tree.map(jnp.asarray, tree)
  return agent, params, meta
