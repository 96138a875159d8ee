"""Held-out evaluation rollouts: many missions per attack setting, one episode each, all settings in ONE batched,
jitted while_loop rollout per (env config, policy) (settings are data). The host only aggregates
(specguard_jax.metrics).

Missions are paired across settings and controllers: mission j of every setting has the same mission plan, world
and sensor-noise / domain-randomisation seed (all drawn from fold_in(key, j)); only the attack differs between
settings (drawn from mission j's attack key folded with the setting's name), and it is the same for every controller.
So the no-protection controller's records in the same setting are each mission's "twin" (was the attack meant to
cause a violation?) and its attack-free records are the ground-truth run T_GT of the mission delay.

A `Setting` is a named attack distribution (specguard_jax.attacks.AttackConfig, None = attack-free): a random
Table 3 attack on its sensor(s) (onset 15-50 % into the mission, 15-40 s).

Campaigns (`campaign_settings`, names '<campaign>/<sensors>/<profile>'): harder attack distributions, settings like
the others (the same missions, worlds and noise seeds; the same sensors and biases as the random settings of mission
j draw where the sensors agree, since only the timing options differ):
  long      onset as above, lasting until the episode ends (through the landing);
  hazard    onset a lead time (HAZARD_LEAD_S) before a hazard point of the mission in its world (envs.hazards: the
            nominal path's closest approach to an obstacle or a geofence, its sharpest turn, the start of the loiter
            or of the landing; one drawn per mission, the same in every hazard setting of that mission), overt,
            for the random duration above;
  designed  stealthy ramps at the rate designed against the calibrated detector (calibration.stealthy.design_rates:
            the fastest ramp it does not flag for a hidden time), onset as above, lasting until the episode ends;
  multi     two sensors at once: MULTI_PAIRS.
  redteam   (`redteam_setting`, not in CAMPAIGNS: it needs an agent per controller) a trained attack agent
            (specguard_jax.ppo.redteam, the best response to the controller flown) picks the sensor, the bias, the
            onset and the duration each step; `rollout(..., attacker=, attacker_params=)` flies it. Its attacks
            differ between controllers, so no protection's records in this setting are no twin.

`rollout` returns per-mission records (numpy, leading axis = missions, settings concatenated in order):
  setting [n] int, mission [n] int (index j), world [n] int
  violated [n, S] bool   spec robustness over the whole episode < 0 (online STL monitor, = offline robustness)
  complete, collision, crash, stall, nan, fence_breach, unfinished, attacked, detected [n] bool
  t_end [n] s            episode end (the completion time when complete)
  final_dist [n] m       true distance to the last waypoint at the end (horizontal when the mission lands there or
                         for the rover, else 3D)
  onset, attack_end [n] s  scheduled attack window (1e9 when attack-free)
  first_alarm [n] s      first detector alarm (any time; BIG when none or no detector)
  det_t [n] s            first alarm at or after the attack onset (BIG when none)
  bad_t [n] s            first step in [det_t, min(attack_end, t_end)] at which some spec's instantaneous
                         compliance failed (BIG when none)
  rec_t [n] s            first step of the first run of >= metrics.RECOVERY_HOLD_S s of instantaneous compliance
                         that began after bad_t (BIG when none): the recovery instant of T2R (metrics.t2r)
  ok_since [n] s         first step of the compliant run at the episode's end (BIG when its last step was not
                         compliant)
  override_s [n] s       time the recovery policy's override was active
  action_sum, action_max [n] m/s  sum and maximum over the steps the override was active of the size (norm) of the
                         policy's setpoint: the policy's effect (a residual policy doing nothing reads 0)
  min_obstacle [n] m     closest approach to an obstacle
  seen [n, S] bool       (rollout(believed=True), the default) the spec's step condition failed at some step on the
                         signals of the estimate the policy observes (env.believed_signals); True for a spec without
                         a step condition (metrics.blind)
  redteam_sensor [n] int  (only with an attacker) the red-team agent's target (index into SENSOR_NAMES; -1 when
                         it never attacked or the setting is not the red-team one); its onset and end are in onset
                         and attack_end;  redteam_mask [n, 6] every sensor it spoofed (multi-sensor attacks)
  hazard_kind [n] int    hazard-timed settings: the hazard point (index into envs.hazards.HAZARD_KINDS; -1 none or
                         not hazard-timed);  hazard_t [n] s its nominal time (BIG when not hazard-timed)
Instantaneous compliance of a spec at a step = its binary per-step reward (specguard_jax.rewards: the body of an
always-spec, guard -> condition for S5/S7/S10), over the specs that carry a reward.
Trajectories (`n_traj` > 0): the first n_traj missions of every setting also record per step
[true pos 3, estimated pos 3, true yaw, estimated yaw, altitude, alarm, override, time] (traj [T, K, 12]).
"""

from __future__ import annotations

import dataclasses
import functools
import time
import zlib

import jax
import jax.numpy as jnp
import numpy as np

import envs as envs_lib
from envs import hazards as hazards_lib
from envs import missions as missions_lib
from envs.base import tree_where
from specguard_jax import attacks as attacks_lib
from specguard_jax import math3d
from specguard_jax import metrics

BIG = 1e9
TRAJ_FIELDS = ("x", "y", "z", "est_x", "est_y", "est_z", "yaw", "est_yaw", "altitude", "alarm", "override", "time")


CAMPAIGNS = ("long", "hazard", "designed", "multi")
REDTEAM = "redteam"   # the red-team campaign (redteam_setting): flown with a trained attack agent per controller
MULTI_PAIRS = (("gps", "flow"), ("gps", "mag"), ("gps", "baro"), ("gps", "gyro"))
HAZARD_LEAD_S = (2.0, 5.0)   # s before the hazard point: the EKF and the autopilot need a few seconds to go astray
_HAZARD_SALT = 0x48415A   # folds mission j's attack key into its hazard-point key (shared by its hazard settings)


@dataclasses.dataclass(frozen=True)
class Setting:
  """A named attack distribution: attack None = attack-free. hazard_lead_s: (lo, hi) s, the lead time before the
  hazard point when attack.onset == 'given' (hazard-timed). redteam: the attack is chosen step by step by the
  rollout's attack agent (attack is then None)."""
  name: str
  attack: attacks_lib.AttackConfig | None = None
  hazard_lead_s: tuple = HAZARD_LEAD_S
  redteam: bool = False

  @property
  def attacked(self) -> bool:
    return self.attack is not None or self.redteam


def setting(sensors=None, profile: str = "overt") -> Setting:
  """Setting of a single- or multi-sensor attack: setting('gps', 'overt') -> 'gps/overt'; setting(('gps', 'gyro'))
  -> 'gps+gyro/overt' (both at once); setting(None) -> 'attack_free'."""
  if sensors is None:
    return Setting("attack_free")
  sensors = (sensors,) if isinstance(sensors, str) else tuple(sensors)
  acfg = attacks_lib.AttackConfig(sensors=sensors, profiles=(profile,), n_sensors=len(sensors))
  return Setting(f"{'+'.join(sensors)}/{profile}", acfg)


def campaign_setting(campaign: str, sensors, profile: str = "overt", designed_rates=None,
                     hazard_lead_s: tuple = HAZARD_LEAD_S) -> Setting:
  """Setting of an attack campaign (module docstring): campaign_setting('hazard', 'gps') -> 'hazard/gps/overt'.
  designed_rates: {sensor: ramp rate (bias units / s)} for 'designed' (every attacked sensor needs one; the profile
  is then stealthy)."""
  if campaign not in CAMPAIGNS:
    raise ValueError(f"unknown campaign {campaign!r}; choose from {', '.join(CAMPAIGNS)}")
  sensors = (sensors,) if isinstance(sensors, str) else tuple(sensors)
  kw = {}
  if campaign == "long":
    kw = dict(until_end=True)
  elif campaign == "hazard":
    kw = dict(onset="given")
  elif campaign == "designed":
    missing = [x for x in sensors if x not in (designed_rates or {})]
    if missing:
      raise ValueError(f"designed campaign: no designed ramp rate for {', '.join(missing)}")
    profile = "stealthy"
    kw = dict(until_end=True, ramp_rate=tuple((x, float(designed_rates[x])) for x in sensors))
  elif len(sensors) < 2:
    raise ValueError(f"the multi campaign attacks two or more sensors at once, got {sensors}")
  acfg = attacks_lib.AttackConfig(sensors=sensors, profiles=(profile,), n_sensors=len(sensors), **kw)
  return Setting(f"{campaign}/{'+'.join(sensors)}/{profile}", acfg, tuple(hazard_lead_s))


def false_alarm_setting(sensor: str) -> Setting:
  """'false_alarm/<sensor>': an attack-free mission with a zero-bias attack on the sensor (the random campaigns'
  timing), so that an oracle detector raises the alarm and blames the sensor while nothing is wrong: the cost of a
  false alarm (the reconstruction drops a good sensor, an RC policy takes control; evaluate.py --false-alarms)."""
  acfg = attacks_lib.AttackConfig(sensors=(sensor,), profiles=("overt",), scale=0.0)
  return Setting(f"false_alarm/{sensor}", acfg)


def redteam_setting(sensors=attacks_lib.SENSOR_NAMES) -> Setting:
  """The red-team campaign's setting 'redteam/<sensors>/agent' (module docstring): the attack agent may target any
  of `sensors` (its training's AttackerConfig.sensors; '+'-joined in the name)."""
  return Setting(f"{REDTEAM}/{'+'.join(sensors)}/agent", None, redteam=True)


def campaign_settings(campaigns=CAMPAIGNS, sensors=attacks_lib.SENSOR_NAMES, profiles=("overt",),
                      designed_rates=None, hazard_lead_s: tuple = HAZARD_LEAD_S) -> tuple:
  """The settings of `campaigns` over single `sensors` (the vehicle's): long x sensors x profiles, hazard x sensors
  (overt), designed x the sensors with a designed rate (stealthy), multi x MULTI_PAIRS within sensors x profiles."""
  out = []
  for c in campaigns:
    if c == "long":
      out += [campaign_setting(c, x, p) for x in sensors for p in profiles]
    elif c == "hazard":
      out += [campaign_setting(c, x, "overt", hazard_lead_s=hazard_lead_s) for x in sensors]
    elif c == "designed":
      out += [campaign_setting(c, x, designed_rates=designed_rates) for x in sensors if x in (designed_rates or {})]
    elif c == "multi":
      out += [campaign_setting(c, pair, p) for pair in MULTI_PAIRS if set(pair) <= set(sensors) for p in profiles]
    else:
      raise ValueError(f"unknown campaign {c!r}; choose from {', '.join(CAMPAIGNS)}")
  return tuple(out)


def campaign_of(name: str) -> str | None:
  """The campaign of a setting name ('hazard/gps/overt' -> 'hazard'; 'gps/overt' or 'attack_free' -> None)."""
  parts = name.split("/")
  return parts[0] if len(parts) == 3 else None


def default_settings(sensors=attacks_lib.SENSOR_NAMES, profiles=attacks_lib.PROFILES) -> tuple:
  return (setting(None),) + tuple(setting(s, p) for s in sensors for p in profiles)


def _as_settings(settings) -> tuple:
  """Accept Setting objects or the legacy (sensor | None, profile) pairs."""
  out = []
  for s in settings:
    out.append(s if isinstance(s, Setting) else setting(s[0], s[1]))
  names = [s.name for s in out]
  if len(set(names)) != len(names):
    raise ValueError(f"duplicate settings in {names}")
  return tuple(out)


_ENVS: dict = {}
_COMPILED: dict = {}


def make_env(vehicle: str, **overrides):
  """envs.make, cached per (vehicle, overrides): the env is a static jit argument, one object per config."""
  key = (vehicle, tuple(sorted(overrides.items())))
  if key not in _ENVS:
    _ENVS[key] = envs_lib.make(vehicle, **overrides)
  return _ENVS[key]


def clear_cache() -> None:
  """Drop the cached envs and compiled rollouts."""
  _ENVS.clear()
  _COMPILED.clear()


def cached_rollouts() -> int:
  """How many compiled rollouts `rollout` / `precompile` hold (each pins its executable's memory until clear_cache)."""
  return len(_COMPILED)


def _setting_salt(s: Setting) -> int:
  return zlib.crc32(s.name.encode()) & 0x7FFFFFFF


@functools.partial(jax.jit, static_argnames=("env", "settings", "n", "max_steps", "policy", "n_traj", "attacker",
                                             "believed"))
def _rollout(env, policy, policy_params, key, settings, n: int, max_steps: int, n_traj: int = 0, attacker=None,
             attacker_params=None, believed: bool = True):
  n_set = len(settings)
  mission_idx = jnp.tile(jnp.arange(n), n_set)
  setting_id = jnp.repeat(jnp.arange(n_set), n)
  world_ids = jnp.asarray(env.world_ids, jnp.int32)
  salts = jnp.asarray([_setting_salt(s) for s in settings], jnp.uint32)
  timed = [s.attack is not None and s.attack.onset == "given" for s in settings]

  def reset_one(j, sid):
    k_m, k_a, k_w, k_r = jax.random.split(jax.random.fold_in(key, j), 4)
    mission = env.sample_mission(k_m)   # EnvConfig.mission_file's plan, else a generated mission
    k_h = jax.random.fold_in(k_a, _HAZARD_SALT)
    k_a = jax.random.fold_in(k_a, salts[sid])
    wid = world_ids[jax.random.randint(k_w, (), 0, len(env.world_ids))]
    # The attack only enters the state's info at reset: reset first, so hazard timing can read the world.
    state = env.reset_in_world(k_r, wid, mission, attacks_lib.no_attack())
    hz = [hazards_lib.hazard_onset(mission, state.info["world"], env.mission_cfg, k_h, s.hazard_lead_s)
          if t else None for s, t in zip(settings, timed)]
    scheds = [attacks_lib.no_attack() if s.attack is None else
              attacks_lib.sample_attack(s.attack, k_a, mission.nominal_duration, h[0] if h else None)
              for s, h in zip(settings, hz)]
    attack = jax.tree.map(lambda *xs: jnp.stack(xs)[sid], *scheds)
    kind = jnp.stack([h[1] if h else jnp.int32(-1) for h in hz])[sid]
    t_h = jnp.stack([h[2] if h else jnp.float32(BIG) for h in hz])[sid]
    return state.replace(info=dict(state.info, attack=attack)), wid, kind, t_h

  state, wid, hazard_kind, hazard_t = jax.vmap(reset_one)(mission_idx, setting_id)
  step = jax.vmap(env.step)
  red = jnp.asarray([s.redteam for s in settings])[setting_id]   # [b] rows the attack agent drives
  has_det = "alarm" in state.info
  weights = env.reward_fn.weights() > 0
  per_spec = jax.vmap(lambda sig: env.reward_fn.per_spec(sig, binary=True))
  stepwise = jnp.asarray(env.reward_fn.step_conditions())
  b = n_set * n
  onset = state.info["attack"].onset
  attack_end = onset + state.info["attack"].duration
  big = jnp.full((b,), BIG, jnp.float32)
  hold_steps = max(1, int(round(metrics.RECOVERY_HOLD_S / env.dt)))
  rec0 = {"first_alarm": big, "det_t": big, "bad_t": big, "rec_t": big, "ok_since": big,
          "ok_steps": jnp.zeros((b,), jnp.int32), "override_s": jnp.zeros((b,), jnp.float32),
          "action_sum": jnp.zeros((b,), jnp.float32), "action_max": jnp.zeros((b,), jnp.float32)}
  if believed:   # specs without a step condition count as seen: never blind (metrics.blind is a lower bound)
    rec0["seen"] = jnp.broadcast_to(~stepwise, (b, stepwise.shape[0]))
  believed_signals = jax.vmap(env.believed_signals)
  traj_idx = np.asarray([s * n + j for s in range(n_set) for j in range(min(n_traj, n))], np.int32)
  if attacker is not None:
    rec0["adv"] = attacker.init(b)
  if len(traj_idx):
    rec0["traj"] = jnp.zeros((max_steps + 1, len(traj_idx), len(TRAJ_FIELDS)), jnp.float32)

  def traj_row(s):
    sim = jax.tree.map(lambda x: x[traj_idx], s.info["sim"])
    yaw = jax.vmap(math3d.quat_to_euler)(sim["truth"].quat)[:, 2]
    est_yaw = jax.vmap(math3d.quat_to_euler)(sim["ekf"].quat)[:, 2]
    alarm = s.info["alarm"][traj_idx] if has_det else jnp.zeros(len(traj_idx))
    cols = [sim["truth"].pos, sim["ekf"].pos, yaw[:, None], est_yaw[:, None],
            s.info["signals"]["altitude"][traj_idx, None], alarm[:, None],
            s.info["override_active"][traj_idx, None], s.info["time"][traj_idx, None]]
    return jnp.concatenate(cols, axis=-1).astype(jnp.float32)

  if len(traj_idx):
    rec0["traj"] = rec0["traj"].at[0].set(traj_row(state))

  def cond(c):
    s, t, _ = c
    return (t < max_steps) & ~jnp.all(s.done > 0)

  def body(c):
    s, t, rec = c
    live = s.done == 0
    rec = dict(rec)
    action = policy(policy_params, s.obs)
    onset_now, end_now = onset, attack_end
    if attacker is not None:   # the red-team rows' attack of this step, from the agent (the other rows keep theirs)
      sched, adv = attacker.act(attacker_params, s, rec["adv"], action)
      s = s.replace(info=dict(s.info, attack=tree_where(red, sched, s.info["attack"])))
      rec["adv"] = tree_where(red & live, adv, rec["adv"])
      a = rec["adv"]
      onset_now = jnp.where(red, a["onset"], onset)
      end_now = jnp.where(red, jnp.where(a["ended"], a["onset"] + a["used"], BIG), attack_end)
    nxt = step(s, action)
    now = nxt.info["time"]
    if has_det:
      alarm = (nxt.info["alarm"] > 0) & live
      rec["first_alarm"] = jnp.where(alarm & (rec["first_alarm"] >= BIG), now, rec["first_alarm"])
      rec["det_t"] = jnp.where(alarm & (now >= onset_now) & (rec["det_t"] >= BIG), now, rec["det_t"])
    ok = jnp.all((per_spec(nxt.info["signals"]) > 0.5) | ~weights, axis=-1)
    window = live & (rec["det_t"] < BIG) & (now >= rec["det_t"]) & (now <= end_now + 1e-6)
    rec["bad_t"] = jnp.where(window & ~ok & (rec["bad_t"] >= BIG), now, rec["bad_t"])
    # the current run of compliant steps: its first step and its length (steps)
    rec["ok_since"] = jnp.where(live, jnp.where(ok, jnp.minimum(rec["ok_since"], now), BIG), rec["ok_since"])
    rec["ok_steps"] = jnp.where(live, jnp.where(ok, rec["ok_steps"] + 1, 0), rec["ok_steps"])
    back = live & (rec["bad_t"] < BIG) & (rec["rec_t"] >= BIG) & (rec["ok_steps"] >= hold_steps)
    rec["rec_t"] = jnp.where(back, rec["ok_since"], rec["rec_t"])
    if believed:   # per spec: its step condition failed on the signals of the estimate the policy observes
      rec["seen"] = rec["seen"] | (live[:, None] & stepwise & (per_spec(believed_signals(nxt)) < 0.5))
    rec["override_s"] = rec["override_s"] + jnp.where(live, nxt.info["override_active"] * env.dt, 0.0)
    # the velocity setpoint's size (m/s; an attitude run's acceleration residual, action[..., 3:], left out)
    size = jnp.where(live & (nxt.info["override_active"] > 0), jnp.linalg.norm(action[..., :3], axis=-1), 0.0)
    rec["action_sum"] = rec["action_sum"] + size
    rec["action_max"] = jnp.maximum(rec["action_max"], size)
    new = tree_where(s.done > 0, s, nxt)
    if "traj" in rec:
      rec["traj"] = rec["traj"].at[t + 1].set(traj_row(new))
    return new, t + 1, rec

  state, t, rec = jax.lax.while_loop(cond, body, (state, jnp.zeros((), jnp.int32), rec0))
  ep = state.info["episode"]
  extra = {}
  if attacker is not None:   # the red-team rows' window: onset .. onset + time attacked (BIG when never attacked)
    a = rec["adv"]
    onset = jnp.where(red, a["onset"], onset)
    attack_end = jnp.where(red, jnp.where(a["started"], a["onset"] + a["used"], BIG), attack_end)
    extra["redteam_sensor"] = jnp.where(red & a["started"], a["target"], -1).astype(jnp.int32)
    extra["redteam_mask"] = jnp.where((red & a["started"])[:, None], a["mask"], 0.0)
  mission, truth = state.info["mission"], state.info["sim"]["truth"]
  last_wp = jax.vmap(missions_lib.final_waypoint)(mission)
  d = last_wp - truth.pos
  planar = (mission.land > 0.5) | (env.vehicle == "rover")
  final_dist = jnp.where(planar, jnp.linalg.norm(d[:, :2], axis=-1), jnp.linalg.norm(d, axis=-1))
  out = {"setting": setting_id, "mission": mission_idx, "world": wid,
         "violated": state.info["spec_robustness"] < 0,
         "complete": ep["complete"] > 0, "collision": ep["collision"] > 0, "crash": ep["crash"] > 0,
         "stall": ep["stall"] > 0, "nan": ep["nan"] > 0, "fence_breach": ep["fence_breach"] > 0,
         "attacked": ep["attacked"] > 0, "unfinished": state.done == 0, "t_end": state.info["time"],
         "final_dist": final_dist, "onset": onset, "attack_end": attack_end,
         "detected": (rec["first_alarm"] < BIG), "min_obstacle": ep["min_obstacle_distance"],
         "first_alarm": rec["first_alarm"], "det_t": rec["det_t"], "bad_t": rec["bad_t"],
         "rec_t": rec["rec_t"], "ok_since": rec["ok_since"], "override_s": rec["override_s"],
         "action_sum": rec["action_sum"], "action_max": rec["action_max"],
         "waypoints": mission.waypoints, "n_waypoints": mission.n_waypoints, "hazard_kind": hazard_kind,
         "hazard_t": hazard_t, **extra}
  if believed:
    out["seen"] = rec["seen"]
  return out, rec.get("traj"), t


def _static(env, policy, policy_params, settings, missions, max_s, n_traj, attacker=None, attacker_params=None,
            believed=True):
  """The static jit arguments of `_rollout` and the compile-cache key of that configuration."""
  if any(s.redteam for s in settings) and attacker is None:
    raise ValueError("a red-team setting needs an attack agent (rollout's attacker and attacker_params)")
  static = dict(env=env, policy=policy, settings=settings, n=int(missions), max_steps=int(round(max_s / env.dt)),
                n_traj=int(n_traj), attacker=attacker, believed=bool(believed))
  return static, tuple(static.items()) + (jax.tree.structure(policy_params), jax.tree.structure(attacker_params))


def rollout_key(job: dict) -> tuple:
  """The compile-cache key of one `precompile` job (a dict of `rollout`'s arguments): two jobs with equal keys share
  one compiled executable."""
  return _static(job["env"], job["policy"], job["policy_params"], _as_settings(job["settings"]), job["missions"],
                 job.get("max_s", 400.0), job.get("n_traj", 0), job.get("attacker"), job.get("attacker_params"),
                 job.get("believed", True))[1]


def precompile(jobs, *, workers: int = 0) -> dict:
  """Compile several rollouts at once, ahead of flying them, and cache them for `rollout`.

  jobs: list of dicts with the arguments of `rollout` (env, policy, policy_params, settings, missions, and optional
  max_s, n_traj, attacker, attacker_params, believed); configurations already compiled are skipped. XLA
  compilation releases the GIL, so `workers` threads (0: one per two host cores, at most one per job) overlap the
  compiles: on a 16-core GPU host the eight env configs of `evaluate.py --suite paper` compile together instead of
  one after another.
  Returns {job index: compile seconds of that job} and 'wall' (seconds for all of them)."""
  import concurrent.futures
  import os
  todo = []
  for i, j in enumerate(jobs):
    static, ck = _static(j["env"], j["policy"], j["policy_params"], _as_settings(j["settings"]), j["missions"],
                         j.get("max_s", 400.0), j.get("n_traj", 0), j.get("attacker"), j.get("attacker_params"),
                         j.get("believed", True))
    if ck not in _COMPILED and all(ck != c for _, c, _, _ in todo):
      todo.append((i, ck, static, (j["policy_params"], j.get("attacker_params"))))
  workers = workers or max(1, min(len(todo), (os.cpu_count() or 2) // 2))
  key = jax.random.PRNGKey(0)

  def one(item):
    i, ck, static, (params, a_params) = item
    t0 = time.perf_counter()
    fn = _rollout.lower(policy_params=params, attacker_params=a_params, key=key, **static).compile()
    return i, ck, fn, time.perf_counter() - t0

  out = {}
  t0 = time.perf_counter()
  if workers == 1:   # on the calling thread (e.g. the trainer's compile-ahead thread, ppo/ahead.py)
    done = map(one, todo)
  else:
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=workers)
    done = pool.map(one, todo)
  for i, ck, fn, dt in done:
    _COMPILED[ck] = fn
    out[i] = dt
  if workers > 1:
    pool.shutdown()
  out["wall"] = time.perf_counter() - t0
  return out


def rollout(env, policy, policy_params, settings, *, missions: int, seed: int = 10_000, max_s: float = 400.0,
            n_traj: int = 0, timing: dict | None = None, cache: bool = True, attacker=None, attacker_params=None,
            believed: bool = True):
  """Fly `missions` missions per setting with policy(params, obs [B, n]) -> action [B, 3] (hashable: a static
  argument). attacker (hashable, static; with its attacker_params): the attack agent of the red-team settings
  (Setting.redteam), e.g. specguard_jax.ppo.redteam.RedteamAgent: init(b) -> its per-row state [b, ...];
  act(params, state, agent state, action [b, 3]) -> (AttackSchedule [b] of this step, next agent state).
  Returns (records dict of numpy arrays [n_settings * missions, ...] (module docstring), trajectories or None:
  {'rows' [T, K, 12] (TRAJ_FIELDS), 'index' [K] record rows, 'setting' [K], 'mission' [K], 'waypoints' [K, W, 3],
  'n_waypoints' [K]} with K = n_settings * min(n_traj, missions), steps run).
  timing (optional dict) gets compile_s and run_s. cache: keep the compiled executable for the next call with the
  same static configuration (clear_cache() frees them); False: compile for this call only (an executable `precompile`
  made for it is used and dropped). believed: record 'seen' (the estimate's view of each spec, metrics.blind; one
  more map query per step)."""
  settings = _as_settings(settings)
  static, ck = _static(env, policy, policy_params, settings, missions, max_s, n_traj, attacker, attacker_params,
                       believed)
  key = jax.random.PRNGKey(seed)
  t0 = time.perf_counter()
  fn = _COMPILED.get(ck) if cache else _COMPILED.pop(ck, None)   # cache=False: a precompiled one serves once
  if fn is None:   # ahead-of-time compile so compile and flight times are reported apart
    fn = _rollout.lower(policy_params=policy_params, attacker_params=attacker_params, key=key, **static).compile()
    if cache:
      _COMPILED[ck] = fn
  t1 = time.perf_counter()
  out, traj, t = jax.block_until_ready(fn(policy_params=policy_params, attacker_params=attacker_params, key=key))
  if timing is not None:
    timing.update(compile_s=t1 - t0, run_s=time.perf_counter() - t1)
  out, traj, t = jax.device_get((out, traj, t))
  out = {k: np.asarray(v) for k, v in out.items()}
  if traj is not None:
    k = min(int(n_traj), int(missions))
    idx = np.asarray([s * int(missions) + j for s in range(len(settings)) for j in range(k)])
    traj = {"rows": np.asarray(traj)[: int(t) + 1], "index": idx, "setting": out["setting"][idx],
            "mission": out["mission"][idx], "waypoints": out.pop("waypoints")[idx],
            "n_waypoints": out.pop("n_waypoints")[idx]}
  else:
    out.pop("waypoints"), out.pop("n_waypoints")
  return out, traj, int(t)


def evaluate(env, policy, policy_params, *, missions: int = 1000, settings=None, seed: int = 10_000,
             max_s: float = 400.0) -> dict:
  """Held-out summary of one controller (no twins: used by the trainer). Returns {setting name: metrics} with
  missions, svr (share of missions with any spec violated or a crash/collision), critical (a critical spec of the
  table violated), rsr (specguard_jax.metrics: the paper's recovery success: complete, within 5 m of the last
  waypoint, no crash/collision/stall), complete, collision, crash, stall, fence_breach, attacked, unfinished,
  detected, violations_per_spec; plus '_steps'."""
  settings = _as_settings(settings or default_settings())
  rec, _, t = rollout(env, policy, policy_params, settings, missions=missions, seed=seed, max_s=max_s, cache=False,
                      believed=False)
  crit = np.asarray(env.spec_table.critical, bool)
  res = {}
  for i, s in enumerate(settings):
    r = metrics.select(rec, rec["setting"] == i)
    out = {"missions": int(len(r["complete"])), "svr": float(np.mean(metrics.violation(r))),
           "critical": float(np.mean(np.any(r["violated"][:, crit], -1))) if crit.any() else 0.0,
           "rsr": float(np.mean(metrics.recovered(r)))}
    for k in ("complete", "collision", "crash", "stall", "fence_breach", "attacked", "unfinished"):
      out[k] = float(np.mean(r[k]))
    if env.config.detector != "none":
      out["detected"] = float(np.mean(r["detected"]))
    out["violations_per_spec"] = dict(zip(env.spec_names, np.mean(r["violated"], 0).round(4).tolist()))
    res[s.name] = out
  res["_steps"] = t
  return res
