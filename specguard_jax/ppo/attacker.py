"""The attack agent's side of the game (paper App. "Multi-Agent Training"): observation, action -> attack, reward.

Input S = {u'_t, x'_t, B, t_a} (paper): SpecGuard's velocity setpoint this step (normalised by its speeds) [3],
SpecGuard's state input x'_t (first 12 entries of the env observation: position relative to the target, velocity,
acceleration, Euler angles) [12], the bias being injected per sensor, normalised by the sensor's Table 3 maximum
[6 x 3], the mask of the spoofed sensors [6], t_a (attack time used / budget) [1], flags attack on / window
closed / detector alarm [3], mission progress (time / nominal duration) [1] and obstacle distance / 50 [1]:
N_OBS = 45.

Output A = {target sensor, biases, timing}: a diagonal Gaussian over a raw vector [10] read as
  [0:6]  sensor scores: when the attack starts (then latched) the best-scored attackable sensor is spoofed, with
         the next ones whose score is > 0 up to `max_sensors` at once (multi-sensor attacks);
  [6:9]  bias: tanh -> fraction of each spoofed sensor's Table 3 maximum per component (norm clipped to that
         maximum); the agent sets it every step, so ramps (stealthy) and steps (overt) are both reachable;
  [9]    launch: > 0 keeps the attack on. One contiguous window per episode: it starts the first time launch > 0 at
         or after `min_onset_s`, ends the first time launch <= 0 after that or when `max_duration_s` is used up.
The env sees an ordinary AttackSchedule (specguard_jax.attacks) rebuilt each step, so fusion gating, detection,
diagnosis and reconstruction are exercised exactly as for scripted attacks.

Reward R_AA = alpha * R_disruption + beta * R_stealthiness + gamma * R_complexity with
  R_disruption = -r_SG (SpecGuard's per-step compliance reward: the zero-sum term),
  R_stealthiness = 1 per step with the attack on and the detector's alarm down,
  R_complexity = attack on x risk, risk = clip(1 - obstacle_distance / 20 m, 0, 1) (launching near obstacles).
Defaults alpha=1, beta=0, gamma=0.1: the zero-sum term plus a small pull towards attacking near obstacles (the
paper's location term; gamma=0 makes the game exactly zero-sum, R_AA = -R_SG).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from specguard_jax import third_party  # noqa: F401 - before brax: mujoco.mjx without its Warp notices
from brax.envs.base import State, Wrapper

from specguard_jax import attacks as attacks_lib
from specguard_jax.types import SENSOR_NAMES

N_ACT = 10
N_OBS = 45
_HI = np.array([attacks_lib.BIAS_RANGES[n][1] for n in SENSOR_NAMES], np.float32)
_DIMS = np.array([[float(i < attacks_lib.BIAS_DIMS[n]) for i in range(3)] for n in SENSOR_NAMES], np.float32)


@dataclasses.dataclass(frozen=True)
class AttackerConfig:
  """sensors: attackable sensors.  max_duration_s: attack-time budget per episode (s).  scale: multiplies the
  Table 3 maxima.  alpha / beta / gamma: reward weights (see module docstring).  max_sensors: how many sensors one
  attack may spoof at once (the best-scored one, plus the next ones whose score is > 0).  min_onset_s: no attack
  starts before this time in the episode (s; e.g. after take-off, when there is a trusted state to recover from)."""
  sensors: tuple = SENSOR_NAMES
  max_duration_s: float = 40.0
  scale: float = 1.0
  alpha: float = 1.0
  beta: float = 0.0
  gamma: float = 0.1
  max_sensors: int = 2
  min_onset_s: float = 0.0

  def __post_init__(self):
    bad = [s for s in self.sensors if s not in SENSOR_NAMES]
    if bad or not self.sensors:
      raise ValueError(f"unknown or no attack sensor(s) {bad}; choose from {', '.join(SENSOR_NAMES)}")
    if self.max_duration_s <= 0:
      raise ValueError("attacker max_duration_s must be > 0")
    if not 1 <= self.max_sensors <= len(self.sensors):
      raise ValueError(f"attacker max_sensors must be in 1..{len(self.sensors)} (its sensors), got {self.max_sensors}")
    if not self.min_onset_s >= 0:
      raise ValueError(f"attacker min_onset_s must be >= 0, got {self.min_onset_s}")


def adv_init():
  """The attack agent's per-episode state (unbatched): target sensor index (the best-scored), the mask of every
  spoofed sensor [6], started / ended flags, onset (s; 1e9 until started), attack time used (s), the bias injected
  this step [6, 3] and whether the attack is on."""
  return {"target": jnp.zeros((), jnp.int32), "mask": jnp.zeros((6,), jnp.float32), "started": jnp.zeros((), bool),
          "ended": jnp.zeros((), bool), "onset": jnp.full((), 1e9, jnp.float32), "used": jnp.zeros(()),
          "bias": jnp.zeros((6, 3)), "on": jnp.zeros(())}


def observation(cfg: AttackerConfig, speeds, state: State, adv: dict, sg_setpoint) -> jax.Array:
  """Attacker observation [45] (module docstring) of an unbatched env state (reads obs and info's time, mission and
  alarm), the agent's state `adv` and the controller's setpoint of this step, of which it sees the velocity [3] (m/s;
  an attitude residual after it is left out, so the attack agent's inputs are the same for either interface)."""
  info = state.info
  speeds = np.asarray(speeds, np.float32)
  alarm = info.get("alarm", jnp.zeros(()))
  progress = info["time"] / jnp.maximum(info["mission"].nominal_duration, 1.0)
  return jnp.concatenate([
      sg_setpoint[..., :3] / jnp.maximum(speeds[:3], 1e-3), state.obs[:12],
      (adv["bias"] / (_HI[:, None] * cfg.scale)).reshape(-1), adv["mask"] * adv["started"],
      jnp.stack([adv["used"] / cfg.max_duration_s, adv["on"], adv["ended"].astype(jnp.float32), alarm,
                 jnp.minimum(progress, 2.0), jnp.minimum(state.obs[18], 50.0) / 50.0])]).astype(jnp.float32)


def plan(cfg: AttackerConfig, adv: dict, raw, t, dt: float):
  """(AttackSchedule of this step, the agent's next state) for the raw action [10] at time t (s), unbatched; dt:
  the env step (s). The schedule is an ordinary one (on from t while the attack is on), so the env treats it as a
  scripted attack."""
  allowed = np.array([s in cfg.sensors for s in SENSOR_NAMES])
  scores = jnp.where(jnp.asarray(allowed), raw[:6], -jnp.inf)
  launch = raw[9] > 0.0
  budget_left = adv["used"] < cfg.max_duration_s
  on = launch & ~adv["ended"] & budget_left & (t >= cfg.min_onset_s)
  target = jnp.where(adv["started"], adv["target"], jnp.argmax(scores)).astype(jnp.int32)
  # the spoofed set, latched at the start: the best-scored sensor and the next max_sensors - 1 scoring > 0
  rank = jnp.argsort(jnp.argsort(-scores))                  # 0 = best
  pick = (rank < cfg.max_sensors) & ((rank == 0) | (scores > 0.0)) & jnp.asarray(allowed)
  mask = jnp.where(adv["started"], adv["mask"], pick.astype(jnp.float32))
  hi = jnp.asarray(_HI) * cfg.scale                           # [6]
  b = jnp.tanh(raw[6:9])[None, :] * hi[:, None] * jnp.asarray(_DIMS)   # [6, 3]: the same fractions per sensor
  b = b * jnp.minimum(1.0, hi / (jnp.linalg.norm(b, axis=-1) + 1e-9))[:, None]
  onset = jnp.where(on & ~adv["started"], t, adv["onset"])
  bias = mask[:, None] * b * on
  sched = attacks_lib.AttackSchedule(
      mask=jnp.asarray(mask * on, jnp.float32), bias=jnp.asarray(bias, jnp.float32),
      onset=jnp.asarray(jnp.where(on, t, 1e9), jnp.float32), duration=jnp.full((), 1e9, jnp.float32),
      ramp_time=jnp.ones(()), profile=jnp.asarray(0, jnp.int32))
  started = adv["started"] | on
  ended = adv["ended"] | (adv["started"] & ~on)
  f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731  strong types: a weak-typed carry would recompile the step
  new_adv = {"target": target, "mask": f32(mask), "started": started, "ended": ended, "onset": f32(onset),
             "used": f32(adv["used"] + on * dt), "bias": f32(bias), "on": f32(on)}
  return sched, new_adv


class AttackerEnv(Wrapper):
  """Unbatched wrapper: step(state, action) with action = concat(SpecGuard action [env.action_size], attacker raw [10]).
  mix: optional scripted campaigns (ppo.campaign_mix.CampaignMix) that replace the agent's attack in a share of the
  episodes (info['scripted'] [] bool, drawn at reset with the attack it flies, info['scripted_attack'])."""

  def __init__(self, env, cfg: AttackerConfig, speeds, mix=None):
    super().__init__(env)
    self.cfg = cfg
    self.speeds = np.asarray(speeds, np.float32)
    self.allowed = np.array([s in cfg.sensors for s in SENSOR_NAMES])
    self.mix = mix if mix is not None and mix.active else None

  @property
  def action_size(self) -> int:
    return self.env.action_size + N_ACT

  def reset(self, rng):
    s = self.env.reset(rng)
    none = jax.tree.map(lambda x: jnp.asarray(x, x.dtype), attacks_lib.no_attack())  # strong-typed leaves
    info = dict(s.info, adv=adv_init(), attack=none, aa_extra=jnp.zeros(()))
    if self.mix is not None:
      info["scripted"], sched = self.mix.draw(self.env, s.info, rng)
      info["scripted_attack"] = jax.tree.map(lambda a, b: jnp.asarray(a, jnp.asarray(b).dtype), sched, none)
    return s.replace(info=info)

  def observe(self, state: State, sg_setpoint) -> jax.Array:
    """Attacker observation [45] given SpecGuard's velocity setpoint [3] (m/s) of this step."""
    return observation(self.cfg, self.speeds, state, state.info["adv"], sg_setpoint)

  def step(self, state: State, action) -> State:
    cfg, info = self.cfg, state.info
    n_sg = self.env.action_size   # SpecGuard's setpoint: [3], or [6] with the attitude residual
    sg_action, raw = action[:n_sg], action[n_sg:]
    sched, new_adv = plan(cfg, info["adv"], raw, info["time"], self.env.dt)
    if self.mix is not None:   # a scripted campaign's episode flies its own attack
      sched = jax.tree.map(lambda a, b: jnp.where(info["scripted"], a, b), info["scripted_attack"], sched)
    out = self.env.step(state.replace(info=dict(info, attack=sched)), sg_action)
    on = new_adv["on"]
    alarm = out.info.get("alarm", jnp.zeros(()))
    risk = jnp.clip(1.0 - out.obs[18] / 20.0, 0.0, 1.0)
    extra = jnp.asarray(cfg.beta * on * (1.0 - alarm) + cfg.gamma * on * risk, jnp.float32)
    return out.replace(info=dict(out.info, adv=new_adv, aa_extra=extra))

  def reward(self, sg_reward, extra):
    """R_AA from SpecGuard's (shaped) reward and the stealth/complexity terms info['aa_extra']."""
    return self.cfg.alpha * (-sg_reward) + extra
