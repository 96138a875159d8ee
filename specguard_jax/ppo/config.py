"""TrainConfig: every knob of a SpecGuard training run (frozen; JSON-loadable; validated with one-line errors)."""

from __future__ import annotations

import dataclasses
import json

import jax

from envs.base import EnvConfig, check_env_values
from envs import observation as obs_lib
from envs import worlds as worlds_lib
from envs.worlds import DEFAULT_WORLDS
from specguard_jax import checks
from specguard_jax.types import REWARDS, RESIDUAL_DETECTORS, SENSOR_NAMES, TRAIN_DETECTORS, VARIANTS, VEHICLES

MATMUL_PRECISIONS = ("default", "bf16")   # TrainConfig.matmul_precision
NETWORK_DTYPES = ("float32", "bfloat16")  # TrainConfig.network_dtype (the keys of networks.DTYPES)
ACTIVATIONS = ("tanh", "relu", "elu", "swish")   # TrainConfig.activation (the keys of networks.ACTIVATIONS)
MAX_NUM_ENVS = 64 << 20
"""TrainConfig.num_envs' upper bound: 1,048,576 envs per device fit in 80 GB of GPU memory (BENCHMARKS.md), times 64
devices; a larger count is a typo (a trillion envs would otherwise reach the compiler)."""
MAX_SEED = 2**32 - 1   # TrainConfig.seed: jax.random.PRNGKey's 32-bit seed range


def network_precision(name: str):
  """Context manager under which the agents' networks are traced (TrainConfig.matmul_precision): 'default' leaves
  JAX's default; 'bf16': bfloat16 matmul inputs, f32 accumulation and output."""
  import contextlib
  return contextlib.nullcontext() if name == "default" else jax.default_matmul_precision("BF16_BF16_F32")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
  """PPO hyperparameters of one agent. lr: Adam step size (linearly decayed to lr * lr_end_frac when
  lr_schedule='linear').  unroll_length: env steps per env per iteration.  minibatches x epochs per iteration."""
  lr: float = 3e-4
  lr_schedule: str = "constant"   # 'constant' | 'linear'
  lr_end_frac: float = 0.1
  gamma: float = 0.99
  gae_lambda: float = 0.95
  clip_eps: float = 0.2
  value_clip_eps: float = 0.0     # > 0: clipped value loss
  vf_coef: float = 0.5
  ent_coef: float = 0.003
  max_grad_norm: float = 0.5
  num_minibatches: int = 8
  update_epochs: int = 4
  normalize_advantage: bool = True
  # Most minibatch rows one device runs through the networks in one forward + backward pass. A larger minibatch is
  # cut into equal chunks whose gradients are summed (the same gradient up to float summation order), so the update's
  # activations stop growing with the env count: 1 << 20 leaves every run up to 262,144 envs per device with the
  # default unroll and minibatches one pass; 4 chunks at 1,048,576 envs.
  max_rows_per_pass: int = 1 << 20

  def validate(self, name: str = "ppo") -> "PPOConfig":
    """Ranges and types of every field (one-line ValueError naming `name`.field, the value and what is allowed)."""
    checks.number(f"{name}.lr", self.lr, 0, lo_open=True)
    checks.one_of(f"{name}.lr_schedule", self.lr_schedule, ("constant", "linear"))
    checks.number(f"{name}.lr_end_frac", self.lr_end_frac, 0, 1)
    checks.number(f"{name}.gamma", self.gamma, 0, 1, lo_open=True)
    checks.number(f"{name}.gae_lambda", self.gae_lambda, 0, 1)
    checks.number(f"{name}.clip_eps", self.clip_eps, 0, lo_open=True)
    for f in ("value_clip_eps", "vf_coef", "ent_coef"):
      checks.number(f"{name}.{f}", getattr(self, f), 0)
    checks.number(f"{name}.max_grad_norm", self.max_grad_norm, 0, lo_open=True)
    for f in ("num_minibatches", "update_epochs", "max_rows_per_pass"):
      checks.integer(f"{name}.{f}", getattr(self, f), 1)
    checks.one_of(f"{name}.normalize_advantage", self.normalize_advantage, (True, False))
    return self


TRAIN_ENV = EnvConfig(worlds=DEFAULT_WORLDS, override_frame="body", override_residual=True, detector="mixed",
                      detector_delay=0.5, reconstruction=True, nan_fallback=False, ekf_kernel="auto",
                      obs_layout="recovery", override_phases="all")
"""TrainConfig.env's default: the trainer's env settings (what `env_config` does not set per phase). No NaN fallback:
the trainer's AutoReset replaces a NaN-terminated env's whole state anyway (EnvConfig.nan_fallback)."""

# EnvConfig fields of the trainer's speed options, which the held-out evaluation's env leaves at EnvConfig's defaults
# (it is the deployment env: a training speed setting of the same filter and physics does not belong there).
_EVAL_ENV_DEFAULTS = {k: getattr(EnvConfig(), k) for k in ("ekf_kernel", "unroll_ticks", "nan_fallback", "ekf_records")}


def env_config(cfg: "TrainConfig", phase) -> EnvConfig:
  """The EnvConfig of one of a run's envs, all `dataclasses.replace` of cfg.env: phase 1 (compliance: SpecGuard
  overrides the navigator, no detector, no reconstruction), phase 2 (adversarial: the variant's control mode with
  the training detector cfg.env.detector) or "eval" (the held-out evaluation's deployment env: the variant's control
  mode with cfg.eval_detector and EnvConfig's defaults for the trainer's speed options). The training phases keep
  the EKFs' per-channel records only where their detector reads them (detector 'residual')."""
  env = cfg.env
  mode = "reactive" if cfg.variant == "rc" else "override"
  if phase == 1:
    return dataclasses.replace(env, control_mode="override", detector="none", detector_delay=0.0, reconstruction=False,
                               ekf_records=False, recovery_rule="none")   # a rule acts only under an alarm
  if phase == 2:
    return dataclasses.replace(env, control_mode=mode,
                               ekf_records=env.ekf_records and env.detector in RESIDUAL_DETECTORS)
  if phase == "eval":
    return dataclasses.replace(env, control_mode=mode, detector=cfg.eval_detector, **_EVAL_ENV_DEFAULTS)
  raise ValueError(f"unknown phase {phase!r}; choose 1, 2 or 'eval'")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """A training run. Sizes: num_envs parallel episodes, unroll_length steps each per iteration; phase budgets in env
  steps (phase1_steps without attacks, phase2_steps adversarial; 0 skips a phase).

  env: the env settings of every env of the run (envs.base.EnvConfig; default TRAIN_ENV), which `env_config`
  specialises per phase: env.worlds (each episode draws one), env.reward, env.override_residual (SpecGuard's velocity
  setpoint is a correction added to the mission navigator's setpoint, computed on the reconstructed state under
  attack; False = it replaces it: the paper's absolute moves, far slower to learn), env.reconstruction (state
  reconstruction in the loop in phase 2; False = the ablation), env.detector (the training detector of phase 2:
  'mixed', the default, each episode the oracle's with probability env.oracle_share else the residual detector's, so
  the policy meets the deployed detector's delays and misdiagnoses; 'oracle', the true attack window after
  env.detector_delay s with the true diagnosis; or 'residual', CUSUM), env.ekf_kernel / env.unroll_ticks (training
  speed options, see EnvConfig);
  env.control_mode comes from `variant` per phase.  eval_detector: the held-out evaluation's detector (deployment).

  variant: 'rc' (Reactive Control: autopilot flies, SpecGuard takes over while the detector's alarm is up) or 'pc'
  (Proactive Control: SpecGuard always flies).  action: 'gaussian' (continuous velocity setpoint, default: it trains
  better, see BENCHMARKS.md) or 'discrete' (the paper's 6 moves).  env.override_attitude (gaussian only): the policy
  also outputs a residual on the attitude + thrust (acceleration) setpoint, scaled by `accels`; `action_scales`.
  alternate_iters: iterations one agent trains while the other is frozen (paper Algorithm 2).  converge_eps /
  converge_window: stop phase 2 early (paper Algorithm 2; on by default, the phase-2 budget is the cap) when the
  average returns of both agents change by less than eps of their size per iteration, between the last two windows
  of converge_window iterations (runner.converged; 0 = off).  completion_bonus: reward on mission completion in units
  of the maximal per-step reward, times 1 / (1 - gamma) when negative (-1 = the return of perfect compliance
  forever), so finishing the mission never looks worse than dawdling.  action_cost: the SpecGuard agent's cost per
  step of a residual setpoint while it is in effect, action_cost * sum((setpoint / action_scales)^2) / 3 in reward
  units (0..action_cost per step for a velocity residual; residual actions only, not the paper's absolute moves; the
  attack agent's zero-sum reward and the logged returns exclude it): "leave a compliant autopilot alone" becomes
  the strict optimum where a spec reward is flat (the capped reward, docs/DESIGN.md "Reward incentives").
  violation_penalty: the SpecGuard agent's reward drops by violation_penalty / (1 - gamma) times the spec's weight
  (critical_weight for critical specs, 1 otherwise, 0 for monitored-only ones) on the step a spec's violation becomes
  certain (the online STL monitor's settled robustness turns negative: the step the mission becomes a violation in the
  SVR sense; 0 = off; 1 = a violation costs what a compliant episode is worth), so that no time saved pays for a
  violation (docs/DESIGN.md "Reward incentives").
  Unlike action_cost it is part of the game: the attack agent's zero-sum reward gains it and
  the logged returns (and so the convergence rule) include it.  stall_penalty: the SpecGuard agent's reward drops by
  stall_penalty / (1 - gamma) on the step an episode ends in a stall (no progress for env.stall_s: a failed mission in
  the RSR sense, which no spec charges; 0 = off; 1 = a stall costs what one violation costs at violation_penalty=1),
  so that hovering until the episode ends is no escape from the violation penalty; in the game like
  violation_penalty.  progress_reward: the SpecGuard agent's learning reward gains progress_reward per metre the
  true vehicle comes closer to its current goal (take-off altitude, waypoint, landing point) than ever before on
  that leg (the env's 'progress' metric): a leg pays its length once however it is flown, so the pay is
  time-neutral but for the discount, which makes progress now worth more than progress later; it reaches the
  present where the completion bonus and the stall charge, 20-100 s ahead, do not (0 = off; at 0.2 a cruise step
  of 0.5 m pays 0.1). Shaping, like action_cost: the attack agent's reward and the logged returns exclude it.
  attack_*: the attack agent's game (ppo/attacker.AttackerConfig): the sensors it may spoof, up to
  attack_max_sensors at once, its time budget per episode, no attack before attack_min_onset_s, and the reward
  weights (alpha the zero-sum term, beta stealth, gamma the location term: attacking near obstacles).
  campaign_share / campaigns: the share of phase-2 episodes that fly one of the evaluation's scripted campaigns
  (long: to the end of the mission, hazard-timed, GPS pairs) instead of the agent's attack (ppo/campaign_mix.py).
  """
  vehicle: str = "drone"
  variant: str = "rc"
  env: EnvConfig = TRAIN_ENV
  action: str = "gaussian"
  hidden: tuple = (256, 256, 256)
  activation: str = "tanh"
  speeds: tuple = (4.0, 4.0, 2.0)   # velocity-setpoint (correction) scale per axis (m/s), yaw frame
  accels: tuple = (3.0, 3.0, 3.0)   # acceleration residual scale per axis (m/s^2, yaw frame; env.override_attitude)
  init_log_std: float = -1.0        # initial log std of the Gaussian head
  num_envs: int = 256
  unroll_length: int = 32
  phase1_steps: int = 2_000_000
  phase2_steps: int = 2_000_000
  iters_per_call: int = 4
  seed: int = 0
  eval_detector: str = "residual"   # the detector of the held-out evaluation (deployment)
  attack_sensors: tuple = SENSOR_NAMES
  attack_max_duration_s: float = 40.0
  attack_alpha: float = 1.0
  attack_beta: float = 0.0
  attack_gamma: float = 0.1
  attack_max_sensors: int = 2
  attack_min_onset_s: float = 0.0
  campaign_share: float = 0.25
  campaigns: tuple = ("long", "hazard", "multi")
  alternate_iters: int = 10
  converge_eps: float = 1e-3
  converge_window: int = 20
  completion_bonus: float = -1.0
  action_cost: float = 0.0
  violation_penalty: float = 0.0
  stall_penalty: float = 0.0
  progress_reward: float = 0.0
  obs_clip: float = 10.0
  sg: PPOConfig = PPOConfig()
  aa: PPOConfig = PPOConfig(ent_coef=0.01)
  eval_missions: int = 0            # held-out missions per setting evaluated after training (0: none)
  checkpoint_every_s: float = 120.0
  max_nan_skips: int = 100
  num_devices: int = 0              # data-parallel devices (0: all of jax.devices(), every host's; ppo/distributed.py)
  env_groups: int = 0               # independent auto-reset env groups G (0: one per device); results depend on G
  # The agents' networks in training (acting, values, PPO update): 'default' (f32 matmuls, which XLA runs
  # as TF32 on NVIDIA GPUs) or 'bf16' (matmul inputs rounded to bfloat16, f32 accumulation and everything else f32:
  # jax.lax.DotAlgorithmPreset.BF16_BF16_F32). The env, the held-out evaluation and the ONNX export stay f32.
  matmul_precision: str = "default"
  # The agents' networks' compute dtype in training (networks.DTYPES): 'float32', or 'bfloat16' (matmuls, bias adds
  # and tanh in bf16, halving the activations' memory traffic; f32 parameters, optimizer, losses and outputs).
  # Evaluation and the ONNX export stay float32.
  network_dtype: str = "float32"

  @property
  def action_scales(self) -> tuple:
    """The scale of each of SpecGuard's setpoint outputs: speeds [3] (m/s), then accels [3] (m/s^2) where
    env.override_attitude (networks.to_setpoint: tanh(action) * action_scales)."""
    return tuple(self.speeds) + (tuple(self.accels) if self.env.override_attitude else ())

  @property
  def n_obs(self) -> int:
    """SpecGuard's observation size: its env's layout (envs.observation)."""
    return obs_lib.size(self.env.obs_layout, self.env.proximity_sectors, self.env.obs_history)

  def with_env(self, **kw) -> "TrainConfig":
    """This config with these fields of `env` replaced (e.g. cfg.with_env(worlds=("urban_park",)))."""
    return dataclasses.replace(self, env=dataclasses.replace(self.env, **kw))

  def validate(self):
    env = self.env
    if not isinstance(env, EnvConfig):
      raise ValueError(f"env must be an envs.base.EnvConfig, got {type(env).__name__}")
    self.check_values()
    if env.control_mode != EnvConfig.control_mode:
      raise ValueError(f"env.control_mode is set per phase from variant; leave it {EnvConfig.control_mode!r} "
                       f"(got {env.control_mode!r})")
    if self.vehicle not in VEHICLES:
      raise ValueError(f"unknown vehicle {self.vehicle!r}; choose one of {', '.join(VEHICLES)}")
    if self.variant not in VARIANTS:
      raise ValueError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
    bad = [w for w in env.worlds if w not in worlds_lib.PRESETS]
    if bad or not env.worlds:
      raise ValueError(f"unknown or no world(s) {bad}; choose from {', '.join(worlds_lib.PRESETS)}")
    if env.reward not in REWARDS:   # survival: the FTC baseline (baselines/ftc.py)
      raise ValueError(f"unknown reward {env.reward!r}; choose one of {', '.join(REWARDS)}")
    if self.action not in ("gaussian", "discrete"):
      raise ValueError(f"unknown action head {self.action!r}; choose gaussian or discrete")
    if env.override_attitude and self.action != "gaussian":
      raise ValueError("env.override_attitude needs action gaussian (the discrete head has velocity moves only)")
    if env.override_attitude and self.vehicle != "drone":
      raise ValueError(f"env.override_attitude: the {self.vehicle} has no attitude loop (drone only)")
    for name, d in (("env.detector", env.detector), ("eval_detector", self.eval_detector)):
      if d not in TRAIN_DETECTORS:
        raise ValueError(f"unknown {name} {d!r}; choose one of {', '.join(TRAIN_DETECTORS)}")
    bad = [s for s in self.attack_sensors if s not in SENSOR_NAMES]
    if bad or not self.attack_sensors:
      raise ValueError(f"unknown or no attack sensor(s) {bad}; choose from {', '.join(SENSOR_NAMES)}")
    if self.matmul_precision not in MATMUL_PRECISIONS:
      raise ValueError(f"unknown matmul_precision {self.matmul_precision!r}; choose one of "
                       f"{', '.join(MATMUL_PRECISIONS)}")
    if self.network_dtype not in NETWORK_DTYPES:
      raise ValueError(f"unknown network_dtype {self.network_dtype!r}; choose one of {', '.join(NETWORK_DTYPES)}")
    if self.env_groups and self.num_envs % self.env_groups:
      raise ValueError(f"num_envs ({self.num_envs}) must be divisible by env_groups ({self.env_groups})")
    if self.phase1_steps + self.phase2_steps == 0:
      raise ValueError("phase1_steps and phase2_steps must not both be 0")
    for agent, p in (("sg", self.sg), ("aa", self.aa)):
      if (self.num_envs * self.unroll_length) % p.num_minibatches:
        raise ValueError(f"num_envs * unroll_length ({self.num_envs * self.unroll_length}) must be divisible by "
                         f"{agent}.num_minibatches ({p.num_minibatches})")
    for phase in (1, 2, "eval"):
      env_config(self, phase).validate()
    return self

  def check_values(self) -> "TrainConfig":
    """Ranges and types of every field on its own, env's and the agents' included (one-line ValueError naming the
    key, the value and what is allowed): what `validate` checks first, before the checks that combine fields, and
    what a config file is checked for as it loads (load_config_file), so the error names the file."""
    if not isinstance(self.env, EnvConfig):
      raise ValueError(f"env must be an envs.base.EnvConfig, got {type(self.env).__name__}")
    check_env_values(self.env, "env.")
    checks.integer("num_envs", self.num_envs, 1, MAX_NUM_ENVS)
    for name in ("unroll_length", "iters_per_call", "alternate_iters", "converge_window"):
      checks.integer(name, getattr(self, name), 1)
    for name in ("phase1_steps", "phase2_steps", "eval_missions", "max_nan_skips", "num_devices", "env_groups"):
      checks.integer(name, getattr(self, name), 0)
    checks.integer("seed", self.seed, 0, MAX_SEED)
    checks.sequence("hidden", self.hidden, min_len=1)
    for i, h in enumerate(self.hidden):
      checks.integer(f"hidden[{i}]", h, 1)
    checks.one_of("activation", self.activation, ACTIVATIONS)
    checks.sequence("speeds", self.speeds, length=3)
    for i, v in enumerate(self.speeds):
      checks.number(f"speeds[{i}]", v, 0)
    checks.sequence("accels", self.accels, length=3)
    for i, v in enumerate(self.accels):
      checks.number(f"accels[{i}]", v, 0)
    checks.sequence("attack_sensors", self.attack_sensors)
    for name in ("init_log_std", "attack_alpha", "attack_beta", "attack_gamma", "completion_bonus"):
      checks.number(name, getattr(self, name))
    checks.number("action_cost", self.action_cost, 0)
    checks.number("violation_penalty", self.violation_penalty, 0)
    checks.number("stall_penalty", self.stall_penalty, 0)
    checks.number("progress_reward", self.progress_reward, 0)
    checks.number("attack_max_duration_s", self.attack_max_duration_s, 0, lo_open=True)
    checks.integer("attack_max_sensors", self.attack_max_sensors, 1, len(SENSOR_NAMES))
    checks.number("attack_min_onset_s", self.attack_min_onset_s, 0)
    checks.number("campaign_share", self.campaign_share, 0, 1)
    checks.sequence("campaigns", self.campaigns)
    bad = [c for c in self.campaigns if c not in ("long", "hazard", "multi")]
    if bad:
      raise ValueError(f"unknown training campaign(s) {bad}; choose from long, hazard, multi")
    checks.number("converge_eps", self.converge_eps, 0)
    checks.number("obs_clip", self.obs_clip, 0, lo_open=True)
    checks.number("checkpoint_every_s", self.checkpoint_every_s, 0, allow_inf=True)
    for name in ("sg", "aa"):
      if not isinstance(getattr(self, name), PPOConfig):
        raise ValueError(f"{name} must be a PPOConfig, got {type(getattr(self, name)).__name__}")
      getattr(self, name).validate(name)
    return self

  @property
  def steps_per_iter(self) -> int:
    return self.num_envs * self.unroll_length

  def to_dict(self) -> dict:
    return dataclasses.asdict(self)


RETIRED_KEYS = {"fused_mlp": (False, "the fused MLP kernel was removed: no faster than XLA in training, "
                                    "see BENCHMARKS.md")}
"""Keys older run directories' config.json may hold: {key: (the only value still accepted, why it went)}."""
_FUSED_EKF = {False: "xla", "xla": "xla", "lanes": "lanes", True: "auto", "triton": "auto"}
"""Older run directories' `fused_ekf` (the EKF kernel, since renamed ekf_kernel; the Triton kernel was removed) ->
ekf_kernel."""

FLAT_ENV_KEYS = {"worlds": "worlds", "reward": "reward", "residual": "override_residual",
                 "reconstruction": "reconstruction", "detector": "detector", "detector_delay": "detector_delay",
                 "fused_ekf": "ekf_kernel", "ekf_kernel": "ekf_kernel", "unroll_ticks": "unroll_ticks"}
"""Top-level keys of config files written before the env settings moved into TrainConfig.env: {old key: env field}
(an old run directory's config.json, a JSON --config or a --sweep key like detector=oracle,residual still load)."""

# Nested dataclass fields of TrainConfig (PPOConfig, EnvConfig): {key: what an error calls their settings}.
_NESTED = {"sg": "sg PPO", "aa": "aa PPO", "env": "env"}

# JSON values each annotation of TrainConfig / PPOConfig / EnvConfig accepts (an int field also takes an integral
# float: 1e8). "Any" fields of EnvConfig (mission, specs, attack, detector_config: objects) take only null.
_JSON_TYPES = {"bool": (bool,), "int": (int,), "float": (int, float), "str": (str,), "tuple": (list, tuple),
               "Any": (type(None),)}


def _typed(key: str, v, annotation: str):
  """v as the field's type, or a one-line ValueError naming the key (a string for a bool, say, reached jit before)."""
  ok = _JSON_TYPES.get(annotation)
  if ok is None:
    return v
  if annotation == "int" and isinstance(v, float) and v.is_integer():
    return int(v)
  if annotation == "Any" and v is not None:
    raise ValueError(f"config key {key!r} is an object a config file cannot set (only null), got {v!r}")
  if not isinstance(v, ok) or (isinstance(v, bool) and bool not in ok):
    raise ValueError(f"config key {key!r} must be {annotation.replace(' | ', ' or ')}, got {v!r}")
  if isinstance(v, list):
    return tuple(v)
  return float(v) if annotation == "float" else v


def _replace_typed(obj, d: dict, prefix: str):
  """obj (a frozen dataclass) with the fields in d replaced, each checked by `_typed` under key prefix.field."""
  what = _NESTED[prefix]
  if not isinstance(d, dict):
    raise ValueError(f"config key {prefix!r} must be an object of {what} settings, got {d!r}")
  types = {f.name: str(f.type) for f in dataclasses.fields(obj)}
  bad = sorted(set(d) - set(types))
  if bad:
    raise ValueError(f"unknown {what} key(s) {', '.join(bad)}; valid: {', '.join(sorted(types))}")
  return dataclasses.replace(obj, **{n: _typed(f"{prefix}.{n}", x, types[n]) for n, x in d.items()})


def from_dict(d: dict, base: TrainConfig | None = None) -> TrainConfig:
  """TrainConfig from a (possibly partial) dict, e.g. a JSON config file: nested objects for sg, aa (PPOConfig) and
  env (EnvConfig) replace only the fields they name; old top-level env keys (FLAT_ENV_KEYS) go into env; unknown keys
  and values of the wrong type are one-line errors, retired keys (RETIRED_KEYS) are skipped at their old default and
  refused otherwise."""
  base = base or TrainConfig()
  fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
  kw, flat_env = {}, {}
  for k, v in d.items():
    if k in RETIRED_KEYS:
      accepted, why = RETIRED_KEYS[k]
      if v != accepted:
        raise ValueError(f"config key {k!r} = {v!r} is no longer supported ({why}); remove it")
      continue
    if k == "fused_ekf":   # the EKF kernel before it was renamed ekf_kernel
      if "ekf_kernel" in d:
        raise ValueError("config keys 'fused_ekf' and 'ekf_kernel' both given; keep ekf_kernel")
      if not isinstance(v, (bool, str)) or v not in _FUSED_EKF:
        raise ValueError(f"config key 'fused_ekf' must be false, true, 'xla', 'lanes' or 'triton', got {v!r}")
      v = _FUSED_EKF[v]
    if k in FLAT_ENV_KEYS:
      flat_env[FLAT_ENV_KEYS[k]] = v
      continue
    if k not in fields:
      raise ValueError(f"unknown config key {k!r}; valid: {', '.join(sorted(fields))}")
    if k in _NESTED:
      v = _replace_typed(getattr(base, k), v, k)
    else:
      v = _typed(k, v, str(fields[k].type))
    kw[k] = v
  if flat_env:
    clash = sorted(k for k in flat_env if k in d.get("env", {}))
    if clash:
      raise ValueError(f"config key(s) {', '.join(clash)} given both at the top level and in env; keep env's")
    kw["env"] = _replace_typed(kw.get("env", base.env), flat_env, "env")
  return dataclasses.replace(base, **kw)


def nested(items: dict) -> dict:
  """{"env.clearance": 6, "seed": 1} -> {"env": {"clearance": 6}, "seed": 1}: dotted keys (train.py's flags, --set,
  --sweep) as from_dict's nested objects."""
  d = {}
  for k, v in items.items():
    head, dot, field = k.partition(".")
    if dot:
      sub = d.setdefault(head, {})
      if not isinstance(sub, dict):
        raise ValueError(f"config key {head!r} set both whole and as {k!r}")
      sub[field] = v
    else:
      d[k] = v
  return d


# EnvConfig fields a run directory's config.json may lack because the run was written before they existed, with the
# value every such run had (not today's default): a resumed or evaluated old run builds the env it was trained in.
LEGACY_RUN_ENV = {"obs_layout": "paper24", "override_phases": "cruise_loiter"}


def load_config_file(path: str, base: TrainConfig | None = None, *, run: bool = False) -> TrainConfig:
  """TrainConfig from a JSON file (a --config file or, run=True, a run directory's config.json, whose missing env
  fields of LEGACY_RUN_ENV take their legacy value) through `from_dict`; every problem (unreadable, not UTF-8, not
  JSON, nested too deeply, not an object, a bad key or value) is a one-line ValueError naming the file."""
  try:
    with open(path, encoding="utf-8") as f:
      d = json.load(f)
  except (OSError, ValueError) as e:   # ValueError: JSONDecodeError and UnicodeDecodeError
    raise ValueError(f"cannot read config file {path}: {' '.join(str(e).split())}") from None
  except RecursionError:
    raise ValueError(f"cannot read config file {path}: JSON nested too deeply") from None
  if not isinstance(d, dict):
    raise ValueError(f"config file {path} must hold a JSON object, got a JSON {type(d).__name__}")
  if run:
    env = d.get("env") if isinstance(d.get("env"), dict) else {}
    legacy = {k: v for k, v in LEGACY_RUN_ENV.items() if k not in env}
    base = base or TrainConfig()
    base = dataclasses.replace(base, env=dataclasses.replace(base.env, **legacy)) if legacy else base
  try:
    return from_dict(d, base).check_values()
  except ValueError as e:
    raise ValueError(f"config file {path}: {e}") from None
