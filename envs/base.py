"""Vehicle-agnostic RAV environment: world + mission per episode, sensors -> EKF -> navigator -> autopilot -> MJX.

One env step is `ticks_per_step` autopilot ticks of `tick_dt` s (default 5 x 0.02 s = 0.1 s, a 10 Hz policy over a
50 Hz autopilot and physics), run with `lax.scan`. Per tick:

  true state --sensors--> SensorReadings --(attack hook)--> EKF --> navigator (+ optional velocity-setpoint override)
  --> autopilot --> actuators --> mjx.step --> true state

After the ticks the monitored signals (specguard_jax/signals.py) are computed from the TRUE state, termination and
truncation are decided, and the observation is built from the EKF estimate. Subclasses (envs/drone.py,
envs/rover.py) provide the physics and the autopilot of their vehicle through the `_vehicle_*` hooks.

The env is a `brax.envs.base.Env`: reset/step are jittable and vmappable and Brax's VmapWrapper / EpisodeWrapper work.
Brax's AutoResetWrapper does NOT fit (it restores a cached first state, so every episode would replay the same
mission and world, and it ignores `State.info`, where our episode state lives): use `envs.wrappers.AutoReset`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np
import jax.numpy as jnp
import mujoco
from brax.envs.base import Env, State
from flax import struct
from mujoco import mjx

from envs import missions as missions_lib
from envs import observation as obs_lib
from envs import worlds as worlds_lib
from specguard_jax import assets
from specguard_jax import attacks as attacks_lib
from specguard_jax import checks
from specguard_jax import detection as detection_lib
from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes
from specguard_jax import math3d
from specguard_jax import rewards as rewards_lib
from specguard_jax import sensors as sensors_lib
from specguard_jax import specs as specs_lib
from specguard_jax.autopilot import fallback as fallback_lib
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.estimation import hooks as estimator_hooks
from specguard_jax.estimation import model_file
from specguard_jax.estimation import recon as recon_lib
from specguard_jax.estimation import traces as traces_lib
from specguard_jax.types import (CONTROL_MODES, DETECTORS, RECON_MODES, RESIDUAL_DETECTORS, REWARDS, SENSOR_NAMES,
                                SensorReadings, TrueState)

ASSETS = assets.ASSETS_DIR   # the shipped MJCF models and JSON (specguard_jax.assets)
OBS_SIZE = 24   # entries of the paper24 observation layout (envs.observation); the env's: observation_size
PROXIMITY_STREAM = 0x0B5   # fold_in tag of the range sensors' noise key
ORACLE_STREAM = 0x0AC     # fold_in tag of detector "mixed"'s per-episode draw
OVERRIDE_FRAMES = ("world", "body")
OVERRIDE_PHASES = ("cruise_loiter", "all")
RECOVERY_ESTIMATORS = ("none", "software_sensors", "dae", "imu_denoise", "ffc", "ftc")  # prior-work baselines
RECOVERY_RULES = ("none", "fallback")   # rule-based setpoint changes while the alarm is up (autopilot/fallback.py)
PAPER_LAG_S = 1.0   # s; least checkpoint lag of the paper-mode reconstruction (EnvConfig.recon_mode, _recon_config)


@struct.dataclass
class PhysicsState:
  """The part of an `mjx.Data` that one physics tick hands the next: `State.pipeline_state` of these envs.

  time: [] s.  qpos: [nq] (drone: position m, quaternion w x y z; rover: x m, y m, yaw rad).  qvel: [nv] (m/s, rad/s).
  act: [na] actuator states.  qacc_warmstart: [nv] the constraint solver's warm start (m/s^2, rad/s^2).
  history: MuJoCo's delay buffers.  plugin_state: plugin states (both empty for our assets).

  `mjx.step` recomputes every other field of `mjx.Data` (kinematics, inertia, contacts, constraint rows, forces,
  qacc) from these and the inputs a vehicle sets each tick (ctrl, qfrc_applied) before reading it, so carrying them
  through the tick loop, the rollout and the auto-reset's selects only moved memory: 84 arrays, 1,972 bytes per drone
  against 80 here (`RAVEnv.physics_data` rebuilds a full `mjx.Data`).
  """

  time: jax.Array
  qpos: jax.Array
  qvel: jax.Array
  act: jax.Array
  qacc_warmstart: jax.Array
  history: jax.Array
  plugin_state: jax.Array

  @classmethod
  def of(cls, data: mjx.Data) -> "PhysicsState":
    return cls(**{f.name: getattr(data, f.name) for f in dataclasses.fields(cls)})


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """Static env configuration (hashable; changing it recompiles).

  world: preset name (envs.worlds.PRESETS).  worlds: optional tuple of preset names; when given, each episode draws
  its world uniformly from them (training across operating environments) and `world` is ignored.  tick_dt: autopilot/physics period (s).  ticks_per_step: ticks per env step.
  max_episode_s: hard cap on an episode (s); the per-mission limit is 2 x nominal duration + 30 s, below this cap.
  stall_s: no progress (1 m closer to the target) for this long -> stall.  control_mode: 'autopilot' (action ignored)
  or 'override' (the action is a velocity setpoint that replaces the navigator's in the override_phases; SpecGuard-PC) or
  'reactive' (the override applies only while the detector's alarm is up; SpecGuard-RC: the recovery switch hands
  control back to the autopilot when the alarm clears).  detector: attack detector run every tick on the attacked
  readings and the EKF ('residual' or 'oracle'); its alarm/diagnosis are in info['alarm'] / info['diagnosis'].
  override_frame: 'world' (ENU) or 'body' (x/y rotated by the estimated yaw, as in the paper's appendix).
  override_residual: the override is added to the navigator's mission-following setpoint instead of replacing it.
  domain_randomization: per-episode wind, gusts, thrust/drive gain, drag, friction, mass.
  clearance: obstacle/fence clearance from the mission path used by world generation (m).
  """
  world: str = "suburban_residential"
  worlds: tuple = ()
  tick_dt: float = 0.02
  ticks_per_step: int = 5
  max_episode_s: float = missions_lib.DEFAULT_EPISODE_CAP_S   # 400 s
  stall_s: float = 20.0
  control_mode: str = "autopilot"
  override_frame: str = "world"
  domain_randomization: bool = True
  clearance: float = 9.0
  mission: Any = None  # envs.missions.MissionConfig; None -> the vehicle's preset
  specs: Any = None    # specguard_jax.specs.SpecTable; None -> the vehicle's table (drone S1-S12, rover S1,2,5-8,12)
  # 'compliance' (sigmoid shaping, paper Sec. 4.3) | 'capped' (1 while a spec holds, the sigmoid only where it is
  # violated: specguard_jax.rewards.reward) | 'binary' (ablation baseline) | 'survival' (the FTC baseline)
  reward: str = "compliance"
  reward_normalize: bool = True   # divide the sum over specs by the sum of weights (paper Algorithm 1)
  critical_weight: float = 1.0    # weight of the critical specs S1, S2, S12 in the sum
  attack: Any = None  # specguard_jax.attacks.AttackConfig: a random attack per episode; None -> no attack
  detector: str = "none"        # 'none' | 'residual' (CUSUM detector + diagnosis) | 'oracle' (true attack, delayed)
                                # | 'mixed' (per episode: the oracle with probability oracle_share, else residual)
  detector_delay: float = 0.0   # oracle detection delay (s)
  oracle_share: float = 0.25    # detector 'mixed': share of episodes whose alarm and diagnosis are the oracle's
  detector_config: Any = None   # specguard_jax.detection.DetectorConfig; None -> the vehicle's calibrated preset
  override_residual: bool = False  # True: the action is ADDED to the navigator's setpoint (residual control)
  # True: the action [6] carries, after the velocity setpoint [3], a residual [3] on the acceleration setpoint (m/s^2,
  # override_frame) that the velocity controller hands the attitude loop (attitude + collective thrust), in effect
  # where the velocity override is (control_mode, override_phases). Vehicles with an attitude loop only (the drone).
  override_attitude: bool = False
  reconstruction: bool = False  # selective state reconstruction while the alarm is up (needs a detector)
  dynamics_model: str = ""      # JSON of the fitted dynamics (estimation.model_file); "" -> assets/dynamics_<vehicle>
  # How the reconstruction estimates the compromised components (estimation.recon.ReconConfig.mode): "fused" a
  # closed-loop shadow EKF on the uncompromised sensors; "paper" the fitted model rolled forward open loop from a
  # checkpoint at least the detector's delay old (the paper's / DeLorean's; `_recon_config`); "oracle" the truth while
  # the reconstruction is active (fused underneath; a bound, not a method: recon.oracle_outputs).
  recon_mode: str = "fused"
  # Prior-work baselines (specguard_jax.baselines, docs/BASELINES.md), active while the detector's alarm is up:
  # 'software_sensors' (SSR: model-predicted readings replace the compromised sensor's before the autopilot's EKF) |
  # 'dae' (the autopilot flies on a denoising autoencoder's state estimate) | 'imu_denoise' (UnRocker: the EKF fuses
  # temporally denoised IMU readings) | 'ffc' (PID-Piper: a learned feed-forward controller's acceleration setpoint
  # replaces the velocity PID's at the attitude loop) | 'ftc' (FTC: a fault-tolerant attitude envelope); the last two
  # drone only (specguard_jax.estimation.hooks). recovery_model: the file the estimator loads (SSR: its
  # specific-force model, 'dae': its DAE, 'ffc': its FFC; msgpack files the baseline builders write).
  recovery_estimator: str = "none"
  recovery_model: str = ""
  # 'fallback': while the alarm is up the navigator's horizontal setpoint slows down in proportion to the
  # reconstruction's position uncertainty, widens the obstacle clearance and holds once the uncertainty exceeds the
  # collision spec's margin (specguard_jax.autopilot.fallback; needs reconstruction=True). 'none': unchanged.
  recovery_rule: str = "none"
  # How the EKFs (the autopilot's and, with reconstruction, the shadow filter's) run their tick: "xla" the XLA filter;
  # "lanes" one Mosaic GPU kernel per tick for the whole vmapped batch (specguard_jax/ekf_lanes.py; NVIDIA Hopper or
  # newer; a vmapped env's batch must be on one device: the trainer shard_maps the step, ppo/iteration.group_step;
  # P kept packed, ekf_init(p_layout="packed")), the same filter to float32 rounding and several times quicker;
  # "auto" the kernel where the device and jax support it, else XLA (ekf_lanes.resolve_ekf_kernel). Default "xla":
  # evaluation, calibration and fitting run the reference filter; the trainer's env asks for "auto"
  # (ppo.config.TRAIN_ENV), a training speed setting.
  ekf_kernel: str = "xla"
  # After a step whose physics went NaN, the env falls back to the previous (finite) data and sim. False: they are
  # left as the physics made them, for an env under envs.wrappers.AutoReset (the trainer's), which replaces every
  # finished env's whole state with a fresh one anyway; obs, reward, signals, STL monitor and episode record are
  # sanitised either way. Saves one select over the whole state per step.
  nan_fallback: bool = True
  # The EKFs' per-channel records (EKFState innov, test_ratio, accepted, fresh: the autopilot's and the reconstruction's
  # shadow filter's), which only the residual detector reads. False: not updated (ekf.ekf_step(records=False); held at
  # their reset values), the trainer's env unless it trains with the residual detector (ppo/iteration.make_env): three
  # [11]-float selects and a write fewer per filter and tick.
  ekf_records: bool = True
  # The GPS-free ticks of a step unrolled (lax.scan(unroll=True)) instead of a loop (on the CPU, which has no GPS
  # grouping, every tick): XLA then copies no loop-carried leaves between those ticks. A few percent off a GPU env step
  # for more compile per env variant (bench/env_step_ab.py, docs/PERFORMANCE.md): worth it for long runs, not for the
  # default one (train.py --unroll-ticks).
  unroll_ticks: bool = False
  # A user's own mission and vehicle (envs.mission_files, specguard_jax.specs.vehicle_params): mission_file, a QGC
  # .plan / WPL file every episode flies (its geoFence replaces the generated world's fences, its rally points go to
  # the world; "" generated missions); mission_max_waypoints, the most waypoints that file may have (the waypoint
  # array has the file's own length: no padding to this limit); params_file, a PX4 .params / ArduPilot .parm file
  # that sets the spec table's parameters, the missions' speed and acceptance radius and the home-centred fence.
  mission_file: str = ""
  mission_max_waypoints: int = 1000
  params_file: str = ""
  # The policy's observation (envs.observation): "paper24" the paper's x'_t and mission context from the estimate (24
  # inputs); "recovery" adds the alarm, the diagnosed-sensor mask, the time since the alarm, the estimate's 1-sigma
  # and a ring of `proximity_sectors` range sensors (noisy, capped at `proximity_range` m) on the true geometry;
  # "context" adds the navigator's mission phase (one-hot).
  obs_layout: str = "paper24"
  # Mission phases in which the policy's setpoint applies (while control_mode lets it act): "cruise_loiter" (the
  # waypoint legs and the loiter, as the paper's velocity override) or "all" (take-off, cruise, loiter, descent and
  # landing too: where gyro, accelerometer and barometer attacks cause their failures).
  override_phases: str = "cruise_loiter"
  proximity_sectors: int = 8
  proximity_range: float = 20.0
  # Frames in the observation: the current one and the obs_history - 1 before it, newest first (envs.observation;
  # 1 = the current frame only).
  obs_history: int = 1

  def validate(self):
    check_env_values(self)
    ekf_lanes.resolve_ekf_kernel(self.ekf_kernel)
    for w in (self.world,) + tuple(self.worlds):
      if w not in worlds_lib.PRESETS:
        raise ValueError(f"unknown world {w!r}; choose one of {', '.join(worlds_lib.PRESETS)}")
    if self.control_mode not in CONTROL_MODES:
      raise ValueError(f"unknown control_mode {self.control_mode!r}; choose one of {CONTROL_MODES}")
    if self.override_frame not in OVERRIDE_FRAMES:
      raise ValueError(f"unknown override_frame {self.override_frame!r}; choose one of {OVERRIDE_FRAMES}")
    if self.detector not in DETECTORS:
      raise ValueError(f"unknown detector {self.detector!r}; choose one of {DETECTORS}")
    if self.control_mode == "reactive" and self.detector == "none":
      raise ValueError("control_mode='reactive' needs a detector ('residual' or 'oracle')")
    if self.detector in RESIDUAL_DETECTORS and not self.ekf_records:
      raise ValueError(f"detector={self.detector!r} reads the EKF's test ratios: it needs ekf_records=True")
    if self.reconstruction and self.detector == "none":
      raise ValueError("reconstruction=True needs a detector ('residual' or 'oracle') to say when and what to rebuild")
    if self.recon_mode not in RECON_MODES:
      raise ValueError(f"unknown recon_mode {self.recon_mode!r}; choose one of {RECON_MODES}")
    if self.reward not in REWARDS:
      raise ValueError(f"unknown reward {self.reward!r}; choose one of {REWARDS}")
    if self.recovery_estimator not in RECOVERY_ESTIMATORS:
      raise ValueError(f"unknown recovery_estimator {self.recovery_estimator!r}; choose one of {RECOVERY_ESTIMATORS}")
    if self.recovery_estimator != "none" and (self.detector == "none" or self.reconstruction):
      raise ValueError(f"recovery_estimator={self.recovery_estimator!r} needs a detector and reconstruction=False")
    if self.recovery_rule not in RECOVERY_RULES:
      raise ValueError(f"unknown recovery_rule {self.recovery_rule!r}; choose one of {RECOVERY_RULES}")
    if self.recovery_rule != "none" and not self.reconstruction:
      raise ValueError(f"recovery_rule={self.recovery_rule!r} reads the reconstruction's uncertainty: it needs "
                       "reconstruction=True")
    if self.tick_dt <= 0 or self.ticks_per_step < 1:
      raise ValueError("tick_dt must be > 0 and ticks_per_step >= 1")
    if self.override_phases not in OVERRIDE_PHASES:
      raise ValueError(f"unknown override_phases {self.override_phases!r}; choose one of {', '.join(OVERRIDE_PHASES)}")
    if self.obs_layout not in obs_lib.LAYOUTS:
      raise ValueError(f"unknown obs_layout {self.obs_layout!r}; choose one of {', '.join(obs_lib.LAYOUTS)}")


def override_in_phase(override_phases: str, nav_phase):
  """Whether the policy's setpoint may act in navigator phase nav_phase (EnvConfig.override_phases): "all" every
  flight phase (not DONE), "cruise_loiter" CRUISE and LOITER. Bool array of nav_phase's shape."""
  if override_phases == "all":
    return nav_phase != nav_lib.DONE
  return (nav_phase == nav_lib.CRUISE) | (nav_phase == nav_lib.LOITER)


def tree_where(cond, a, b):
  """Select pytree a where cond else b (cond broadcast against each leaf's leading axes)."""
  def sel(x, y):
    c = jnp.reshape(cond, cond.shape + (1,) * (x.ndim - cond.ndim))
    return jnp.where(c, x, y)
  return jax.tree.map(sel, a, b)


def check_env_values(cfg: EnvConfig, prefix: str = "") -> None:
  """Ranges and types of EnvConfig's numeric, flag and list fields (one-line ValueError naming prefix + the field, the
  value and what is allowed); EnvConfig.validate runs it first, TrainConfig.validate with prefix 'env.'."""
  checks.sequence(f"{prefix}worlds", cfg.worlds)
  for name in ("tick_dt", "max_episode_s", "stall_s"):
    checks.number(prefix + name, getattr(cfg, name), 0, lo_open=True)
  checks.integer(f"{prefix}ticks_per_step", cfg.ticks_per_step, 1)
  checks.integer(f"{prefix}mission_max_waypoints", cfg.mission_max_waypoints, 1)
  for name in ("mission_file", "params_file"):
    if not isinstance(getattr(cfg, name), str):
      raise ValueError(f"{prefix}{name} must be a file path (a string), got {getattr(cfg, name)!r}")
  checks.integer(f"{prefix}proximity_sectors", cfg.proximity_sectors, 1, 64)
  checks.integer(f"{prefix}obs_history", cfg.obs_history, 1, 16)
  checks.number(f"{prefix}proximity_range", cfg.proximity_range, 0, 1e3, lo_open=True)
  for name in ("clearance", "critical_weight", "detector_delay"):
    checks.number(prefix + name, getattr(cfg, name), 0)
  checks.number(f"{prefix}oracle_share", cfg.oracle_share, 0, 1)
  for name in ("domain_randomization", "reward_normalize", "override_residual", "override_attitude", "reconstruction",
               "nan_fallback", "ekf_records", "unroll_ticks"):
    checks.one_of(prefix + name, getattr(cfg, name), (True, False))


def check_physics_options(mj_model: mujoco.MjModel, name: str) -> None:
  """Refuses a model whose joint damping would be lost to its disabled implicit Euler damping.

  The assets turn the Euler integrator's implicit damping off (in MJX it refactors M every physics step whatever the
  damping values) because they have no joint damping; a model that adds some must turn it back on.
  """
  if (mj_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP) and np.any(mj_model.dof_damping):
    raise ValueError(f"{name}: joint damping needs the implicit Euler damping, remove eulerdamp=\"disable\"")


class RAVEnv(Env):
  """Base class; see module docstring. Subclasses set `vehicle`, `asset`, `radius` and implement the hooks."""

  vehicle: str = ""
  asset: str = ""
  radius: float = 0.5  # collision radius of the vehicle (m): obstacle_distance below this is a collision
  attitude_loop: bool = False   # whether _vehicle_tick takes an acceleration-setpoint residual (override_attitude)

  def __init__(self, config: EnvConfig | None = None, **overrides):
    config = dataclasses.replace(config or EnvConfig(), **overrides)
    config.validate()
    if config.override_attitude and not self.attitude_loop:
      raise ValueError(f"override_attitude: the {self.vehicle} has no attitude loop to take an acceleration residual")
    self.config = config
    self.mj_model = mujoco.MjModel.from_xml_path(assets.asset_path(self.asset))
    self.mj_model.opt.timestep = config.tick_dt
    check_physics_options(self.mj_model, self.asset)
    # On this process's own device: put_model's default, jax.devices()[0], is process 0's in a multi-process run, and
    # a compiled function closing over an array on another process's device fails to trace there.
    self.mjx_model = mjx.put_model(self.mj_model, device=jax.local_devices()[0])
    # mjx.step's input for a PhysicsState: this Data with the carried fields and the tick's inputs replaced
    # (`physics_data`); the model's defaults for the other inputs (mocap, eq_active, xfrc_applied, userdata).
    self._data_template = mjx.make_data(self.mjx_model, device=jax.local_devices()[0])
    names = tuple(config.worlds) or (config.world,)
    self.world_ids = tuple(worlds_lib.PRESET_NAMES.index(w) for w in names)
    self.mission_cfg = config.mission or self._default_mission_config()
    self.sensor_cfg, self.ekf_cfg = self._default_estimation_configs()
    sensors_lib.check_rates(self.sensor_cfg, config.tick_dt)
    self.dt = config.tick_dt * config.ticks_per_step
    # Reset samples the sensors once (the EKF's initial readings), so an env step starts on sensor tick
    # 1 + n * ticks_per_step. When the GPS period divides ticks_per_step, the GPS is fresh on the same tick index j of
    # every step for every env, (1 + j) % period == 0, and the other ticks' EKF update leaves its rows out statically
    # (ekf_step(stale=("gps",)), `_tick_loop`; tests/test_env.py checks the schedule on rollouts with auto-resets).
    # Off on the CPU, where the env is compiled for tests and smoke runs and the second tick variant only adds
    # compile time.
    gps_period = int(round(1.0 / (config.tick_dt * self.sensor_cfg.gps_rate)))
    self._gps_period = (gps_period if gps_period > 1 and config.ticks_per_step % gps_period == 0
                        and jax.default_backend() != "cpu" else None)
    self._ekf_kernel = ekf_lanes.resolve_ekf_kernel(config.ekf_kernel)   # the autopilot EKF's: "xla" or "lanes"
    self._shadow_kernel = self._ekf_kernel    # ... and the reconstruction's shadow EKF's (bench/autoreset_cost.py
                                              # --phase2 sets it apart to measure its share)
    self.det_cfg = None if config.detector == "none" else config.detector_config or (
        detection_lib.DetectorConfig.drone() if self.vehicle == "drone" else detection_lib.DetectorConfig.rover())
    self.spec_table = config.specs or self._default_specs()
    self.plan, self.geofence, self.fence_alt_max = None, None, None
    if config.params_file or config.mission_file:
      self._load_user_files()
    self.spec_eval = specs_lib.compile_specs(self.spec_table, self.dt)
    self.reward_fn = rewards_lib.RewardFn.create(self.spec_table)
    self.recovery = None
    if config.recovery_estimator != "none":   # prior-work baseline estimator (specguard_jax.estimation.hooks)
      self.recovery = estimator_hooks.make(self, config.recovery_estimator, config.recovery_model)
    if config.reconstruction:
      n_u = 4 if self.vehicle == "drone" else 2
      self.dyn_params = model_file.load_params(config.dynamics_model or model_file.default_path(self.vehicle), n_u)
      self.recon_cfg = self._recon_config(n_u)
    if config.recovery_rule == "fallback":   # the collision spec's margin (S1) and the minimum-speed spec's bound (S7)
      self.fallback_cfg = fallback_lib.FallbackConfig(margin=self.spec_table.threshold(self.spec_table["S1"]),
                                                      min_speed=self.spec_table.threshold(self.spec_table["S7"]))

  def _load_user_files(self):
    """EnvConfig.params_file and mission_file: the spec table's parameters, the missions' speed and acceptance
    radius, the home fence (specs.vehicle_params), then the plan (envs.mission_files.load_plan) and the geofence the
    episodes fly in (envs.geofence: the plan's zones and the home fence). A bad file raises a one-line ValueError."""
    from envs import geofence as geofence_lib
    from envs import mission_files
    from specguard_jax.specs import vehicle_params
    cfg = self.config
    home_fence = geofence_lib.empty_geofence()
    if cfg.params_file:
      vs = vehicle_params.load_vehicle_settings(cfg.params_file, self.vehicle)
      names = set(self.spec_table.params)
      self.spec_table = specs_lib.with_params(self.spec_table, {n: v for n, v in vs.spec_overrides if n in names})
      over = {}
      if vs.cruise_speed is not None:
        over["cruise_speed"] = (vs.cruise_speed, vs.cruise_speed)
      if vs.acceptance_radius is not None:
        over["acceptance_radius"] = vs.acceptance_radius
      self.mission_cfg = dataclasses.replace(self.mission_cfg, **over)
      home_fence = geofence_lib.make_geofence(max_radius=vs.fence_radius, any_inclusion=self.vehicle == "drone")
      self.fence_alt_max = vs.fence_alt_max or None
    fence = home_fence
    if cfg.mission_file:
      self.plan = mission_files.load_plan(cfg.mission_file, self.vehicle, self.mission_cfg,
                                          max_episode_s=cfg.max_episode_s, max_waypoints=cfg.mission_max_waypoints)
      fence = geofence_lib.merge(self.plan.geofence, home_fence)
    self.geofence = fence if fence.active else None

  def sample_mission(self, rng: jax.Array):
    """The mission an episode flies: the plan of EnvConfig.mission_file, else one generated from mission_cfg."""
    if self.plan is not None:
      return self.plan.mission
    return missions_lib.generate_mission(self.mission_cfg, rng)

  def _recon_config(self, n_u: int):
    """The reconstruction's ReconConfig. Paper mode: the checkpoint must predate the attack's effect on the estimate,
    since nothing corrects the model's roll-out from it, so its lag covers the detector's delay: the oracle's
    configured delay (detector_delay), or the residual detector's diagnosis windows (DetectorConfig.diag_window_s /
    xcheck_window_s: it has no fixed delay; its median overt-attack delays are well under these windows, a stealthy
    ramp's can be longer and then reaches the checkpoint); at least PAPER_LAG_S; checked by recon.check_lag.
    Fused mode: the defaults (its shadow filter corrects what a short lag lets through)."""
    cfg = recon_lib.ReconConfig(n_controls=n_u, ekf=self.ekf_cfg, mode=self.config.recon_mode)
    if cfg.mode != "paper":
      return cfg
    residual = max(self.det_cfg.diag_window_s, self.det_cfg.xcheck_window_s)
    delay = {"oracle": self.config.detector_delay, "residual": residual,
             "mixed": max(residual, self.config.detector_delay)}[self.config.detector]
    lag = int(np.ceil(max(PAPER_LAG_S, delay) / self.config.tick_dt - 1e-6))
    calib = int(round(cfg.paper_calib_s / self.config.tick_dt))   # entries before the checkpoint, for calibration
    cfg = dataclasses.replace(cfg, lag=lag, window=max(cfg.window, lag + 1 + calib))
    recon_lib.check_lag(cfg, delay, self.config.tick_dt)
    return cfg

  def _default_specs(self):
    return specs_lib.drone_specs() if self.vehicle == "drone" else specs_lib.rover_specs()

  @property
  def spec_names(self):
    return self.spec_table.names

  def physics_data(self, phys: PhysicsState, **inputs) -> mjx.Data:
    """A full mjx.Data for mjx.step from `phys` and this tick's inputs (ctrl, qfrc_applied: arrays by name); derived
    fields (xpos, cdof, efc_*, qacc, ...) are left at make_data's zeros: mjx.step computes them before reading them.
    Works per env and under vmap."""
    fields = {f.name: getattr(phys, f.name) for f in dataclasses.fields(PhysicsState)}
    return self._data_template.replace(**fields, **inputs)

  # ---------------------------------------------------------------- Env API
  @property
  def observation_size(self) -> int:
    return obs_lib.size(self.config.obs_layout, self.config.proximity_sectors, self.config.obs_history)

  @property
  def action_size(self) -> int:
    """[3] velocity setpoint (m/s), or [6] with the acceleration-setpoint residual (m/s^2, override_attitude)."""
    return 6 if self.config.override_attitude else 3

  @property
  def backend(self) -> str:
    return "mjx"

  def reset(self, rng: jax.Array) -> State:
    return self.reset_in_world(rng, None)

  def reset_in_world(self, rng: jax.Array, world_id=None, mission=None, attack=None) -> State:
    """Reset in world preset `world_id` (int, may be traced; None: the config's world, or a random one of
    `config.worlds`), flying `mission` if given (e.g. loaded from a QGroundControl file) else a generated one,
    under `attack` (an AttackSchedule, e.g. attacks.schedule_for(...)) if given, else one drawn from
    `config.attack` (no attack when that is None)."""
    k_mission, k_world, k_dr, k_phys, k_sens, k_run, k_pick = jax.random.split(rng, 7)
    if mission is None:
      mission = self.sample_mission(k_mission)
    if world_id is None:
      ids = jnp.asarray(self.world_ids, jnp.int32)
      world_id = ids[0] if len(self.world_ids) == 1 else jax.random.choice(k_pick, ids)
    if attack is None:
      attack = (attacks_lib.no_attack() if self.config.attack is None else
                attacks_lib.sample_attack(self.config.attack, jax.random.fold_in(k_pick, 1),
                                          mission.nominal_duration))
    state = self._reset_with(mission, world_id, k_world, k_dr, k_phys, k_sens, k_run)
    return state.replace(info=dict(state.info, attack=attack, attack_active=jnp.zeros(())))

  def reset_to_mission(self, mission, rng: jax.Array) -> State:
    """Reset flying a given mission; world generated around it."""
    return self.reset_in_world(rng, None, mission)

  def _reset_with(self, mission, world_id, k_world, k_dr, k_phys, k_sens, k_run) -> State:
    world = worlds_lib.generate_world(jnp.asarray(world_id, jnp.int32), mission, k_world,
                                      clearance=self.config.clearance)
    if self.plan is not None or self.geofence is not None or self.fence_alt_max is not None:   # the user's files
      world = worlds_lib.with_geofence(
        world, self.geofence if self.geofence is not None else world.geofence, self.fence_alt_max,
        replace_fences=self.plan is not None and self.plan.has_fence,
        rally_points=self.plan.rally_points if self.plan is not None else None)
    dr = self._sample_domain(world, k_dr)
    data, truth = self._vehicle_init(mission, dr, k_phys)
    phys = PhysicsState.of(data)
    # The nearest obstacle's distance at the true position, which the magnetometer's local disturbance needs
    # (sim["obstacle_distance"]; `step` refreshes it from its collision queries).
    d_obs = jnp.minimum(worlds_lib.obstacle_sdf(world, self._query_pos(truth.pos)), 1e3)
    sens_state = sensors_lib.init_sensors(self.sensor_cfg, truth, k_sens, surface=world.surface,
                                          obstacle_distance=d_obs)
    k_sens2, k_run = jax.random.split(k_run)
    sens_state, readings = sensors_lib.sense(self.sensor_cfg, sens_state, truth, k_sens2, self.config.tick_dt,
                                             obstacle_distance=d_obs)
    # P in the layout of the EKF's kernel
    ekf = ekf_lib.ekf_init(self.ekf_cfg, readings, p_layout="packed" if self._ekf_kernel == "lanes" else "square")
    nav = nav_lib.nav_init(mission)
    sim = {
        "truth": truth, "sensors": sens_state, "readings": readings, "ekf": ekf, "nav": nav,
        "ctrl": self._vehicle_control_init(), "dr": dr, "gust": jnp.zeros(3),
        "vehicle": self._vehicle_extra_init(), "obstacle_distance": d_obs,
    }
    if self.config.detector != "none":
      sim["det"] = detection_lib.detector_init(self.det_cfg)
    if self.config.detector == "mixed":   # this episode's detector: the oracle (True) or the residual one
      sim["det_oracle"] = jax.random.uniform(jax.random.fold_in(k_run, ORACLE_STREAM)) < self.config.oracle_share
    if self.config.reconstruction:
      sim["recon"] = recon_lib.recon_init(self.recon_cfg, ekf)
      sim["x_rec"] = recon_lib.input_vector(ekf, readings)
    if self.recovery is not None:
      sim["baseline"] = self.recovery.init(ekf, readings)
    signals = self._signals(world, mission, truth, nav)
    episode = {
        "collision": jnp.zeros(()), "crash": jnp.zeros(()), "fence_breach": jnp.zeros(()),
        "stall": jnp.zeros(()), "complete": jnp.zeros(()), "nan": jnp.zeros(()),
        "best_dist": self._goal_distance(mission, truth, nav), "last_progress": jnp.zeros(()), "progress_key": jnp.zeros((), jnp.int32),
        "closest": self._goal_distance(mission, truth, nav),
        "min_obstacle_distance": signals["obstacle_distance"], "min_fence_margin": signals["fence_margin"],
        "attacked": jnp.zeros(()),
    }
    if self.config.detector != "none":
      episode["detected"] = jnp.zeros(())
    info = {
        "sim": sim, "mission": mission, "world": world, "signals": signals, "episode": episode, "rng": k_run,
        "truncation": jnp.zeros(()), "override_active": jnp.zeros(()), "time": jnp.zeros(()),
    }
    if self.config.detector != "none":
      info["alarm"], info["diagnosis"] = jnp.zeros(()), -jnp.ones((), jnp.int32)
    monitor, spec_rob, _ = self.spec_eval.monitor_update(self.spec_eval.monitor_init(), signals)
    info["spec_monitor"] = monitor
    info["spec_robustness"] = spec_rob
    info["spec_reward"] = self.reward_fn(signals, binary=self.config.reward == "binary",
                                         capped=self.config.reward == "capped")[1]
    obs = obs_lib.with_history(self._observation(world, mission, sim, key=k_run), None, self.config.obs_history)
    metrics = {k: jnp.zeros(()) for k in ("collision", "crash", "fence_breach", "stall", "complete", "nan", "progress")}
    return State(pipeline_state=phys, obs=obs, reward=jnp.zeros(()), done=jnp.zeros(()), metrics=metrics,
                 info=info)

  def min_truncated_episode_steps(self) -> int:
    """The fewest env steps an episode can last when it ends truncated: truncation is t >= the mission's limit,
    min(max_episode_s, 2 x nominal duration + 30 s) >= min(max_episode_s, 30 s), with t = steps x dt (one step of
    slack for float32 time). The trainer uses it to bound how often one env can be truncated within a rollout
    (ppo/iteration.py, `bootstrap_values`): a subclass that truncates earlier must override it."""
    return max(1, int(np.floor(min(self.config.max_episode_s, 30.0) / self.dt)) - 1)

  def step(self, state: State, action: jax.Array) -> State:
    info = state.info
    mission, world, sim0 = info["mission"], info["world"], info["sim"]
    rng, k_ticks = jax.random.split(info["rng"])
    override_vel = self._override_velocity(action, sim0)
    override_acc = self._override_accel(action, sim0) if self.config.override_attitude else None
    override = self._override_active(sim0)
    attack = info["attack"]

    def tick(carry, key, gps_due):
      phys, sim = carry
      phys, sim = self._tick(phys, sim, mission, world, override_vel, override, key, attack, gps_due=gps_due,
                             override_acc=override_acc)
      return (phys, sim), sim["truth"].pos

    keys = jax.random.split(k_ticks, self.config.ticks_per_step)
    (phys, sim), tick_pos = self._tick_loop(tick, (state.pipeline_state, sim0), keys)
    truth, nav = sim["truth"], sim["nav"]
    finite = jnp.all(jnp.isfinite(phys.qpos)) & jnp.all(jnp.isfinite(phys.qvel))
    # The observation's position (an estimate; nan_fallback: the previous step's where the physics is not finite).
    est_pos = self._estimated_position(sim)
    if self.config.nan_fallback:
      est_pos = jnp.where(finite, est_pos, self._estimated_position(sim0))
    # The step's obstacle queries in one pass over the world's obstacles (worlds.obstacle_queries): the distance at
    # every tick's true position [ticks_per_step] (collision; the last tick's is the signals' obstacle distance) and
    # the nearest obstacle's distance and direction at the estimate (the observation).
    with jax.named_scope("collision"):
      d_obs, d_est, g_est = worlds_lib.obstacle_queries(world, jax.vmap(self._query_pos)(tick_pos),
                                                        self._query_pos(est_pos))
      min_obs = jnp.minimum(jnp.min(d_obs), 1e3)
    # The magnetometer's distance to structures for the next step's ticks: this step's last tick's, already at hand,
    # at most one step (0.1 s, < 1.2 m at cruise speed) stale; an SDF per tick (or per magnetometer sample) would
    # add a pass over the world's obstacles to every tick for a disturbance that varies over metres.
    sim = dict(sim, obstacle_distance=jnp.minimum(d_obs[-1], 1e3))

    # NaN physics never leaves the env: the signals (STL monitor, episode record) fall back to the previous step's.
    signals = tree_where(finite, self._signals(world, mission, truth, nav, obstacle=d_obs[-1]), info["signals"])
    min_obs = jnp.where(finite, min_obs, 1e3)
    ep = dict(info["episode"])
    t = info["time"] + self.dt
    # ---- termination ----
    nan = ~finite
    collision = (min_obs < self.radius) & finite
    crash = self._vehicle_crashed(sim, signals) & finite
    complete = (nav.phase == nav_lib.DONE) & finite & ~collision & ~crash
    # Stall: no 1 m of progress towards the current target within stall_s (loiter and done excluded).
    key = nav.target * 8 + nav.phase
    new_key = key != ep["progress_key"]
    goal_dist = self._goal_distance(mission, truth, nav)
    improved = goal_dist < ep["best_dist"] - 1.0
    best = jnp.where(new_key | improved, goal_dist, ep["best_dist"])
    last_prog = jnp.where(new_key | improved, t, ep["last_progress"])
    moving_phase = (nav.phase != nav_lib.LOITER) & (nav.phase != nav_lib.DONE)
    # Progress (m): how much closer to the current goal than ever before in this leg the true vehicle came in this
    # step (0 on the step the goal changes, and while it is no closer than its closest yet). Summed over a leg it is
    # the leg's start distance minus its closest approach however the leg is flown: pay for it
    # (TrainConfig.progress_reward) cannot be farmed by moving away and back, and earlier progress is worth more only
    # through the discount.
    closest = jnp.where(finite, jnp.minimum(ep["closest"], goal_dist), ep["closest"])
    progress = jnp.where(new_key, 0.0, ep["closest"] - closest)
    closest = jnp.where(new_key & finite, goal_dist, closest)
    stall = moving_phase & (t - last_prog > self.config.stall_s) & finite
    fence_breach = (signals["fence_margin"] < 0.0) & finite
    terminated = nan | collision | crash | complete | stall
    limit = jnp.minimum(self.config.max_episode_s, 2.0 * mission.nominal_duration + 30.0)
    truncated = (t >= limit) & ~terminated

    ep.update(
        collision=jnp.maximum(ep["collision"], collision), crash=jnp.maximum(ep["crash"], crash),
        fence_breach=jnp.maximum(ep["fence_breach"], fence_breach), stall=jnp.maximum(ep["stall"], stall),
        complete=jnp.maximum(ep["complete"], complete), nan=jnp.maximum(ep["nan"], nan),
        best_dist=best, last_progress=last_prog, progress_key=key.astype(jnp.int32), closest=closest,
        min_obstacle_distance=jnp.minimum(ep["min_obstacle_distance"], min_obs),
        min_fence_margin=jnp.minimum(ep["min_fence_margin"], signals["fence_margin"]))
    ep = {k: v.astype(info["episode"][k].dtype) for k, v in ep.items()}

    # ... and neither does its state (nan_fallback: the previous finite one; else AutoReset replaces it), zero reward,
    # episode ends.
    if self.config.nan_fallback:
      phys = tree_where(finite, phys, state.pipeline_state)
      sim = tree_where(finite, sim, sim0)
    obs = self._observation(world, mission, sim, obstacle=(d_est, g_est), key=k_ticks)
    obs = obs_lib.with_history(jnp.where(jnp.isfinite(obs), obs, 0.0), state.obs, self.config.obs_history)
    # Online STL monitor: robustness of each spec over the episode so far (its final value = offline robustness).
    with jax.named_scope("stl_reward"):
      monitor, spec_rob, _ = self.spec_eval.monitor_update(info["spec_monitor"], signals)
      reward, per_spec = self.reward_fn(signals, normalize=self.config.reward_normalize,
                                        critical_weight=self.config.critical_weight,
                                        binary=self.config.reward == "binary",
                                        capped=self.config.reward == "capped")
    if self.config.reward == "survival":   # FTC baseline: 1 per step in flight, 0 on the step it crashes
      reward = rewards_lib.survival_reward(collision | crash | nan)
    reward = jnp.where(finite, reward, 0.0)
    done = (terminated | truncated).astype(jnp.float32)
    metrics = {"collision": collision.astype(jnp.float32), "crash": crash.astype(jnp.float32),
               "fence_breach": fence_breach.astype(jnp.float32), "stall": stall.astype(jnp.float32),
               "complete": complete.astype(jnp.float32), "nan": nan.astype(jnp.float32),
               "progress": progress.astype(jnp.float32)}
    ep["attacked"] = jnp.maximum(ep["attacked"], attacks_lib.attack_active(attack, t).astype(jnp.float32))
    if self.config.detector != "none":
      ep["detected"] = jnp.maximum(ep["detected"], sim["det"].alarm.astype(jnp.float32))
    new_info = dict(info, sim=sim, signals=signals, episode=ep, rng=rng, time=t, spec_monitor=monitor,
                    attack_active=attacks_lib.attack_active(attack, t).astype(jnp.float32),
                    spec_robustness=spec_rob, spec_reward=per_spec,
                    truncation=truncated.astype(jnp.float32), override_active=override.astype(jnp.float32))
    if self.config.detector != "none":
      new_info.update(alarm=sim["det"].alarm.astype(jnp.float32), diagnosis=sim["det"].diagnosis)
    return state.replace(pipeline_state=phys, obs=obs, reward=reward, done=done, metrics=metrics, info=new_info)

  # ---------------------------------------------------------------- one autopilot tick
  def _tick_loop(self, tick, carry, keys):
    """The env step's ticks: tick(carry, key, gps_due) -> (carry, true position [3]) over keys [T, ...] -> (carry,
    positions [T, 3]). Without a GPS schedule (`_gps_period` None: on the CPU) a scan of full ticks. With one (period
    p), the ticks go in groups of p: a scan of the p - 1 ticks whose EKF leaves the GPS rows out, then the tick that can
    carry a GPS sample, each static: no lax.cond in the loop (on the GPU a cond's outputs, P included, are copied into
    the loop's carry). EnvConfig.unroll_ticks unrolls the scans."""
    p, unroll = self._gps_period, self.config.unroll_ticks
    if p is None:
      return jax.lax.scan(lambda c, k: tick(c, k, None), carry, keys, unroll=unroll)

    def group(carry, keys_g):   # keys_g [p, ...]
      carry, pos = jax.lax.scan(lambda c, k: tick(c, k, False), carry, keys_g[:p - 1], unroll=unroll)
      carry, last = tick(carry, keys_g[p - 1], True)
      return carry, jnp.concatenate([pos, last[None]])

    carry, pos = jax.lax.scan(group, carry, keys.reshape((-1, p) + keys.shape[1:]))
    return carry, pos.reshape((-1, 3))

  def _tick(self, phys, sim, mission, world, override_vel, override, key, attack=None, gps_due=None,
            override_acc=None):
    """One autopilot tick. gps_due: whether this tick can carry a GPS sample, for every env (`_tick_loop`'s schedule;
    a Python bool, or an unbatched traced bool), or None (any tick can: the full EKF update). override_acc: the
    policy's acceleration-setpoint residual [3] (world m/s^2; override_attitude), or None."""
    cfg = self.config
    k_sense, k_gust = jax.random.split(key)
    with jax.named_scope("sensors"):
      sens_state, readings = sensors_lib.sense(self.sensor_cfg, sim["sensors"], sim["truth"], k_sense, cfg.tick_dt,
                                               obstacle_distance=sim["obstacle_distance"])
      clean = readings   # before the attack: what the oracle reconstruction hands the autopilot
      readings = self._attack(readings, sim, attack)
    rd_ekf = readings
    if self.recovery is not None:   # baseline hook (SSR): readings the autopilot's EKF fuses
      sim, rd_ekf = self.recovery.pre_ekf(sim, readings)
    with jax.named_scope("ekf"):
      ekf = self._ekf_update(sim["ekf"], rd_ekf, gps_due)
    with jax.named_scope("detector"):
      if cfg.detector in RESIDUAL_DETECTORS:   # actuation of the previous tick produced these readings
        hold = sim["recon"].suspect if cfg.reconstruction else False  # compromised sensor still off the reconstruction
        det = detection_lib.detector_update(self.det_cfg, sim["det"], readings, ekf, self._actuation(sim),
                                            cfg.tick_dt, hold)
        if cfg.detector == "mixed":   # an oracle episode's state is the oracle's throughout
          det = tree_where(sim["det_oracle"], detection_lib.oracle_update(sim["det"], attack, sim["nav"].time,
                                                                          cfg.tick_dt, cfg.detector_delay), det)
        sim = dict(sim, det=det)
      elif cfg.detector == "oracle":
        sim = dict(sim, det=detection_lib.oracle_update(sim["det"], attack, sim["nav"].time, cfg.tick_dt,
                                                        cfg.detector_delay))
    est, rd_ctrl = ekf, readings
    if cfg.reconstruction:  # DeLorean: mission logic and autopilot run on the reconstructed state while under attack
      u_prev = traces_lib.vehicle_controls(self.vehicle, sim)
      handback = sim["recon"].active & ~(sim["det"].alarm > 0)
      # A GPS blamed by the residual detector: the shadow restarts from its GPS-free dead reckoning.
      anchor = (jnp.concatenate([sim["det"].dr[0], sim["det"].aid_vel]) if cfg.detector in RESIDUAL_DETECTORS
                else None)
      if cfg.detector == "mixed":   # the oracle's episodes have no dead reckoning (recon_tick skips a NaN anchor)
        anchor = jnp.where(sim["det_oracle"], jnp.nan, anchor)
      with jax.named_scope("reconstruction"):
        rec, x_rec, est, rd_ctrl = recon_lib.recon_tick(self.recon_cfg, self.dyn_params, sim["recon"], ekf, readings,
                                                       u_prev, sim["det"].mask, sim["det"].alarm, cfg.tick_dt,
                                                       anchor, gps_due, kernel=self._shadow_kernel,
                                                       records=cfg.ekf_records)
      if cfg.recon_mode == "oracle":   # the bound: the truth while the reconstruction is active
        est, rd_ctrl, x_rec = recon_lib.oracle_outputs(rec.active, est, rd_ctrl, x_rec, sim["truth"], clean)
      # Recovery switch: the autopilot's EKF resumes from the reconstructed state, not from what it fused under attack.
      ekf = tree_where(handback, est, ekf)
      sim = dict(sim, recon=rec, x_rec=x_rec)
    if self.recovery is not None:   # baseline hook (UnRocker): the estimate the navigator and autopilot fly on
      sim, est = self.recovery.post_ekf(sim, est, readings)
    landed = self._vehicle_landed(sim)
    with jax.named_scope("navigator"):
      nav, vel_nav, leg_dir = nav_lib.nav_step(self._nav_params(), sim["nav"], mission, est.pos, landed, cfg.tick_dt)
    if cfg.recovery_rule == "fallback":   # the navigator's setpoint as the fallback rule changes it under an alarm
      d_est, g_est = worlds_lib.obstacle_sdf_and_grad(world, self._query_pos(est.pos))
      vel_nav = fallback_lib.apply(self.fallback_cfg, vel_nav, fallback_lib.position_sigma(sim["recon"]), d_est,
                                   g_est, sim["det"].alarm > 0, est.pos, world.rally_points)
    use_override = override & override_in_phase(cfg.override_phases, nav.phase)
    vel_sp = jnp.where(use_override, override_vel + (vel_nav if cfg.override_residual else 0.0), vel_nav)
    acc_residual = None if override_acc is None else jnp.where(use_override, override_acc, 0.0)
    gust = self._gust_step(sim["gust"], sim["dr"], k_gust)
    sim = dict(sim, sensors=sens_state, readings=rd_ctrl, ekf=est, nav=nav, gust=gust)
    with jax.named_scope("autopilot"):   # the vehicle's controller; its mjx.step is scoped "physics"
      phys, sim = self._vehicle_tick(phys, sim, mission, vel_sp, leg_dir, acc_residual)
    return phys, dict(sim, readings=readings, ekf=ekf)

  def _ekf_update(self, ekf, readings, gps_due):
    """The autopilot's EKF tick. gps_due False: no env can have a fresh GPS sample, and the GPS rows are left out of
    the fusion (ekf.on_gps_schedule). None: the full tick."""
    return ekf_lib.on_gps_schedule(lambda stale: ekf_lanes.ekf_step(self.ekf_cfg, ekf, readings, self.config.tick_dt,
                                                                    stale=stale, kernel=self._ekf_kernel,
                                                                    records=self.config.ekf_records), gps_due)

  def _attack(self, readings: SensorReadings, sim, attack) -> SensorReadings:
    """Sensor attacks enter here, between the sensors and the EKF: y_a(t) = y(t) + b(t) (specguard_jax.attacks)."""
    if attack is None:
      return readings
    return attacks_lib.apply_attack(readings, attack, sim["nav"].time)

  def _gust_step(self, gust, dr, key):
    """Ornstein-Uhlenbeck wind gust (m/s), correlation time 2 s, stationary std dr['gust_std']."""
    tau = 2.0
    a = jnp.exp(-self.config.tick_dt / tau)
    return a * gust + jnp.sqrt(1 - a * a) * dr["gust_std"] * jax.random.normal(key, (3,)) * jnp.array([1, 1, 0.3])

  def _sample_domain(self, world, key):
    """Per-episode domain randomisation (SpecGuard Sec. 5.2: wind, thrust, drag, friction) + mass."""
    ks = jax.random.split(key, 6)
    on = 1.0 if self.config.domain_randomization else 0.0
    u = lambda k, lo, hi: 1.0 + on * jax.random.uniform(k, (), minval=lo, maxval=hi)
    return {
        "mass_scale": u(ks[0], -0.1, 0.1), "thrust_gain": u(ks[1], -0.08, 0.08), "drag_scale": u(ks[2], -0.3, 0.3),
        "friction": u(ks[3], -0.2, 0.2),
        "wind": world.wind_mean * on, "gust_std": world.gust_std * on,
    }

  # ---------------------------------------------------------------- signals and observation
  def _query_pos(self, pos):
    """Position used for world queries (rovers query at ground level)."""
    return pos

  def _signals(self, world, mission, truth: TrueState, nav, obstacle=None) -> dict:
    """The monitored signals of specguard_jax/signals.py from the TRUE state. dict name -> [] float32.
    obstacle: the obstacle distance at the true position if already at hand (worlds.world_queries)."""
    pos = self._query_pos(truth.pos)
    phase = nav.phase
    landing = ((phase == nav_lib.DESCENT) | (phase == nav_lib.DONE)) & (mission.land > 0)
    # While landing the leg is last waypoint -> landing point (envs.missions.mission_leg, target >= n).
    q = worlds_lib.world_queries(world, mission, pos, jnp.where(landing, mission.n_waypoints, nav.target), obstacle)
    vel = truth.vel
    speed_xy = math3d.norm(vel[:2])
    alt = truth.pos[2] - self._ground_offset()
    last = mission.n_waypoints - 1
    wp = mission.waypoints
    near_target = math3d.norm((wp[nav.target] - truth.pos)[:2]) < self._nav_params().turn_zone * \
        mission.acceptance_radius
    near_start = math3d.norm((nav.leg_start - truth.pos)[:2]) < self._nav_params().turn_zone * \
        mission.acceptance_radius
    corner_ahead = near_target & (nav.target < last) & (nav.target != mission.loiter_wp)
    corner_behind = near_start & (nav.target > 0)
    cruise = phase == nav_lib.CRUISE
    in_turn = cruise & (corner_ahead | corner_behind)
    tko_window = (phase == nav_lib.TAKEOFF) & (alt >= 1.5) & (alt <= mission.takeoff_alt - 3.0)
    f = lambda b: b.astype(jnp.float32)
    slack = jnp.where(phase == nav_lib.DONE, 1e3, mission.deadline[nav.target] - nav.time)
    loiter_dev = jnp.where(phase == nav_lib.LOITER, math3d.norm((wp[nav.target] - truth.pos)[:2]), 0.0)
    s = {
        "obstacle_distance": q["obstacle_distance"], "path_deviation": q["path_deviation"], "altitude": alt,
        "dist_wp": q["dist_wp"], "dist_final": q["dist_final"], "wp_slack": slack,
        "fence_margin": q["fence_margin"], "fence_h": q["fence_h"], "fence_v": q["fence_v"],
        "loiter_deviation": loiter_dev, "speed_xy": speed_xy, "speed_z": vel[2],
        "descent_speed": jnp.maximum(0.0, -vel[2]),
        "in_takeoff": f(tko_window), "in_cruise": f(cruise & ~in_turn), "in_turn": f(in_turn),
        "in_loiter": f(phase == nav_lib.LOITER),
        "in_descent": f((phase == nav_lib.DESCENT) & (alt > self._nav_params().land_alt2)),
        "in_landing": f((phase == nav_lib.DESCENT) & (alt <= self._nav_params().land_alt2)),
        "time": nav.time,
    }
    return {k: jnp.asarray(v, jnp.float32) for k, v in s.items()}

  def believed_signals(self, state) -> dict:
    """The monitored signals computed from the estimate the policy observes (the reconstruction's x'_t while it is
    configured, else the EKF's: position and velocity) instead of the true state, against the same map, mission
    and navigator: what a controller acting on that estimate can see of each spec (outside landing, the
    observation's obstacle distance, fence margin and path deviation are these). The navigator may fly on another
    estimate: fused reconstruction's full shadow state under a misdiagnosis, a denoising baseline's output
    (recovery_estimator). dict name -> [] float32, as _signals."""
    sim = state.info["sim"]
    if self.config.reconstruction:   # x_rec equals the EKF's estimate while the alarm is down
      vel = sim["x_rec"][3:6]
    else:
      vel = sim["ekf"].vel
    believed = sim["truth"].replace(pos=self._estimated_position(sim), vel=vel)
    return self._signals(state.info["world"], state.info["mission"], believed, sim["nav"])

  def _goal_distance(self, mission, truth, nav):
    """Distance (m) to what the navigator is heading for: take-off point, target waypoint or landing point."""
    wp = mission.waypoints[nav.target]
    goal = jnp.where(nav.phase == nav_lib.TAKEOFF, math3d.with_component(mission.home, 2, mission.takeoff_alt), wp)
    goal = jnp.where(nav.phase == nav_lib.DESCENT, math3d.with_component(wp, 2, 0.0), goal)
    return math3d.norm(self._query_pos(goal) - self._query_pos(truth.pos))

  def _estimated_position(self, sim) -> jax.Array:
    """[3] the position the observation is built from: the EKF's, or the reconstructed one (phase 2), m."""
    return sim["x_rec"][0:3] if self.config.reconstruction else sim["ekf"].pos

  def _observation(self, world, mission, sim, obstacle=None, key=None) -> jax.Array:
    """One frame of the policy input [obs_lib.frame_size] in the layout `config.obs_layout` (envs.observation; the
    observation is this frame and, with config.obs_history > 1, the frames before it). Its first 24 entries
    from the ESTIMATED state (so attacks reach them): the paper's x'_t (position relative to the target waypoint,
    velocity, acceleration, Euler angles) + mission context: direction of the next leg [3], unit direction to the
    nearest obstacle [3], obstacle distance, fence margin, path deviation, altitude, horizontal speed, waypoint slack
    (s). obstacle: (distance [], gradient [3]) of the obstacles' SDF at the estimated position if already at hand
    (worlds.obstacle_queries), else computed here. key: this step's PRNG key (the range sensors' noise, drawn from
    a key folded out of it so the other random streams do not change with the layout)."""
    ekf, nav, readings = sim["ekf"], sim["nav"], sim["readings"]
    pos = self._estimated_position(sim)
    if self.config.reconstruction:   # x'_t as reconstructed (equals the EKF's while the alarm is down)
      x = sim["x_rec"]
      vel, acc, euler = x[3:6], x[6:9], x[9:12]
    else:
      vel, euler = ekf.vel, ekf_lib.ekf_euler(ekf)
      acc = math3d.matvec(math3d.quat_to_rot(ekf.quat), readings.accel - ekf.accel_bias) + jnp.array([0.0, 0.0, -9.81])
    wp = mission.waypoints
    target = wp[nav.target]
    nxt = wp[jnp.minimum(nav.target + 1, mission.n_waypoints - 1)]
    leg_next = nxt - target
    leg_next = leg_next / (math3d.norm(leg_next) + 1e-6)
    qpos = self._query_pos(pos)
    d_obs, g_obs = worlds_lib.obstacle_sdf_and_grad(world, qpos) if obstacle is None else obstacle
    q = worlds_lib.world_queries(world, mission, qpos, nav.target, d_obs)
    obs = jnp.concatenate([
        pos - target, vel, acc, euler, leg_next, -g_obs,
        jnp.stack([jnp.minimum(d_obs, 50.0), jnp.clip(q["fence_margin"], -50.0, 50.0), q["path_deviation"],
                   pos[2] - self._ground_offset(), math3d.norm(vel[:2]),
                   jnp.clip(mission.deadline[nav.target] - nav.time, -100.0, 300.0)])])
    if self.config.obs_layout in ("recovery", "context"):
      obs = jnp.concatenate([obs, self._recovery_context(world, sim, key)])
    if self.config.obs_layout == "context":
      obs = jnp.concatenate([obs, obs_lib.phase_one_hot(nav.phase)])
    return obs.astype(jnp.float32)

  def _recovery_context(self, world, sim, key) -> jax.Array:
    """The `recovery` layout's entries after the first 24 (envs.observation.recovery_context)."""
    cfg = self.config
    if "det" in sim:
      det = sim["det"]
      alarm, diagnosed, since = det.alarm, det.mask, det.time_since_alarm
    else:
      alarm, diagnosed, since = jnp.zeros(()), jnp.zeros(len(SENSOR_NAMES)), jnp.zeros(())
    std = recon_lib.recon_std(sim["recon"]) if cfg.reconstruction else ekf_lib.std_groups(sim["ekf"].P)
    truth = sim["truth"]
    ranges = worlds_lib.proximity_ranges(world, self._query_pos(truth.pos), math3d.quat_to_euler(truth.quat)[2],
                                         cfg.proximity_sectors, cfg.proximity_range)
    key = jax.random.PRNGKey(0) if key is None else key
    ranges = obs_lib.noisy_ranges(ranges, jax.random.fold_in(key, PROXIMITY_STREAM), cfg.proximity_range,
                                  obs_lib.RangeSensorConfig())
    return obs_lib.recovery_context(alarm, diagnosed, since, std, ranges)

  def _override_velocity(self, action, sim):
    """Action [:3] (m/s) -> world velocity setpoint, rotated by the estimated yaw in the 'body' frame."""
    return self._override_to_world(jnp.asarray(action, jnp.float32)[:3], sim)

  def _override_accel(self, action, sim):
    """Action [3:6] (m/s^2) -> world acceleration-setpoint residual, rotated as the velocity part is."""
    return self._override_to_world(jnp.asarray(action, jnp.float32)[3:6], sim)

  def _override_to_world(self, a, sim):
    """A yaw-frame vector [3] of the override -> world frame ('body' frame: rotated by the estimated yaw)."""
    if self.config.override_frame == "body":
      est = sim["recon"].shadow if self.config.reconstruction else sim["ekf"]
      yaw = ekf_lib.ekf_euler(est)[2]
      xy = math3d.matvec(math3d.yaw_rot2(yaw), a[:2])
      a = jnp.concatenate([xy, a[2:3]])
    return jnp.nan_to_num(a)

  def _override_active(self, sim):
    """Whether the policy's velocity setpoint replaces the navigator's during this env step."""
    if self.config.control_mode == "reactive":
      return sim["det"].alarm
    return jnp.asarray(self.config.control_mode == "override")

  def _actuation(self, sim):
    """The actuator commands the detector's vehicle model expects (see specguard_jax.detection)."""
    raise NotImplementedError

  def _model(self, dr):
    """The MJX model with this episode's mass (and inertia) scale on the vehicle body (body 1)."""
    m = self.mjx_model
    s = dr["mass_scale"]
    return m.replace(body_mass=m.body_mass.at[1].multiply(s), body_inertia=m.body_inertia.at[1].multiply(s))

  # ---------------------------------------------------------------- vehicle hooks
  def _default_mission_config(self):
    raise NotImplementedError

  def _default_estimation_configs(self):
    raise NotImplementedError

  def _nav_params(self) -> nav_lib.NavParams:
    raise NotImplementedError

  def _ground_offset(self) -> float:
    """Height of the body origin above the ground when standing (m)."""
    return 0.0

  def _vehicle_init(self, mission, dr, key):
    raise NotImplementedError

  def _vehicle_control_init(self):
    raise NotImplementedError

  def _vehicle_extra_init(self):
    return {}

  def _vehicle_landed(self, sim):
    return jnp.zeros((), bool)

  def _vehicle_crashed(self, sim, signals):
    return jnp.zeros((), bool)

  def _vehicle_tick(self, phys: PhysicsState, sim, mission, vel_sp, leg_dir, acc_residual=None):
    """One tick of the vehicle's controller and physics: (PhysicsState after the tick, sim with truth, ctrl, vehicle).
    Steps `mjx.step(self._model(dr), self.physics_data(phys, ctrl=..., ...))` and returns `PhysicsState.of(data)`.
    acc_residual: world m/s^2 [3] added to the acceleration setpoint (vehicles with `attitude_loop`), or None."""
    raise NotImplementedError

