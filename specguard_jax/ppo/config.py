"""TrainConfig: every knob of a SpecGuard training run (frozen; JSON-loadable; validated with one-line errors)."""

from __future__ import annotations

import dataclasses
import json

import jax

from envs.base import EnvConfig
from envs import worlds as worlds_lib
from envs.worlds import DEFAULT_WORLDS
from specguard_jax.types import REWARDS, SENSOR_NAMES, TRAIN_DETECTORS, VARIANTS, VEHICLES

MATMUL_PRECISIONS = ("default", "bf16")   # TrainConfig.matmul_precision
NETWORK_DTYPES = ("float32", "bfloat16")  # TrainConfig.network_dtype (the keys of networks.DTYPES)


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


TRAIN_ENV = EnvConfig(worlds=DEFAULT_WORLDS, override_frame="body", override_residual=True, detector="oracle",
                      detector_delay=0.5, reconstruction=True, nan_fallback=False, ekf_kernel="auto")
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
                               ekf_records=False)
  if phase == 2:
    return dataclasses.replace(env, control_mode=mode, ekf_records=env.ekf_records and env.detector == "residual")
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
  'oracle', the true attack window after env.detector_delay s with the true diagnosis, the issue's training
  detector, or 'residual', CUSUM), env.ekf_kernel / env.unroll_ticks (training speed options, see EnvConfig);
  env.control_mode comes from `variant` per phase.  eval_detector: the held-out evaluation's detector (deployment).

  variant: 'rc' (Reactive Control: autopilot flies, SpecGuard takes over while the detector's alarm is up) or 'pc'
  (Proactive Control: SpecGuard always flies).  action: 'gaussian' (continuous velocity setpoint, default: it trains
  better, see BENCHMARKS.md) or 'discrete' (the paper's 6 moves).
  alternate_iters: iterations one agent trains while the other is frozen (paper Algorithm 2).  converge_eps /
  converge_window: stop phase 2 early when the average returns of both agents change by less than eps (per
  iteration, averaged over the window of iterations).  completion_bonus: reward on mission completion in units of the
  maximal per-step reward, times 1 / (1 - gamma) when negative (-1 = the return of perfect compliance forever), so
  finishing the mission never looks worse than dawdling.
  """
  vehicle: str = "drone"
  variant: str = "rc"
  env: EnvConfig = TRAIN_ENV
  action: str = "gaussian"
  hidden: tuple = (256, 256, 256)
  activation: str = "tanh"
  speeds: tuple = (4.0, 4.0, 2.0)   # velocity-setpoint (correction) scale per axis (m/s), yaw frame
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
  attack_gamma: float = 0.0
  alternate_iters: int = 10
  converge_eps: float = 0.0
  converge_window: int = 20
  completion_bonus: float = -1.0
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

  def with_env(self, **kw) -> "TrainConfig":
    """This config with these fields of `env` replaced (e.g. cfg.with_env(worlds=("urban_park",)))."""
    return dataclasses.replace(self, env=dataclasses.replace(self.env, **kw))

  def validate(self):
    env = self.env
    if not isinstance(env, EnvConfig):
      raise ValueError(f"env must be an envs.base.EnvConfig, got {type(env).__name__}")
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
    if self.num_devices < 0 or self.env_groups < 0:
      raise ValueError("num_devices and env_groups must be >= 0 (0 = one per device / all devices)")
    if self.env_groups and self.num_envs % self.env_groups:
      raise ValueError(f"num_envs ({self.num_envs}) must be divisible by env_groups ({self.env_groups})")
    for name in ("num_envs", "unroll_length", "iters_per_call", "alternate_iters", "converge_window"):
      if getattr(self, name) < 1:
        raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
    if self.phase1_steps < 0 or self.phase2_steps < 0 or self.phase1_steps + self.phase2_steps == 0:
      raise ValueError("phase1_steps and phase2_steps must be >= 0 and not both 0")
    for agent, p in (("sg", self.sg), ("aa", self.aa)):
      if (self.num_envs * self.unroll_length) % p.num_minibatches:
        raise ValueError(f"num_envs * unroll_length ({self.num_envs * self.unroll_length}) must be divisible by "
                         f"{agent}.num_minibatches ({p.num_minibatches})")
      if p.max_rows_per_pass < 1:
        raise ValueError(f"{agent}.max_rows_per_pass must be >= 1, got {p.max_rows_per_pass}")
      if p.lr_schedule not in ("constant", "linear"):
        raise ValueError(f"unknown {agent}.lr_schedule {p.lr_schedule!r}; choose constant or linear")
      if not 0 < p.gamma <= 1 or not 0 <= p.gae_lambda <= 1:
        raise ValueError(f"{agent}.gamma must be in (0, 1] and gae_lambda in [0, 1]")
    if len(self.speeds) != 3 or min(self.speeds) < 0:
      raise ValueError("speeds must be 3 non-negative numbers (m/s)")
    for phase in (1, 2, "eval"):
      env_config(self, phase).validate()
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


def load_config_file(path: str, base: TrainConfig | None = None) -> TrainConfig:
  try:
    with open(path) as f:
      d = json.load(f)
  except (OSError, json.JSONDecodeError) as e:
    raise ValueError(f"cannot read config file {path}: {e}") from None
  if not isinstance(d, dict):
    raise ValueError(f"config file {path} must hold a JSON object")
  return from_dict(d, base)
