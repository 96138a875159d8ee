"""Controllers under evaluation: a registry of named builders (evaluate.py --controllers a,b,...).

A `Controller` says how the deployment env is configured (`env_overrides`, EnvConfig fields applied on top of the
evaluation's base config: worlds, attacks and mission sizes stay the evaluation's) and what flies it
(`policy(params, obs [B, n_obs]) -> velocity setpoint [B, 3]` m/s, a hashable static argument of the jitted rollout).
Controllers with equal `env_overrides` and `policy` share one compiled rollout.

Built in:
  no_protection       the autopilot alone (control_mode 'autopilot', no detector, zero policy).
  specguard_rc / _pc  the trained SpecGuard policy of a train.py run dir (its policy.msgpack and config.json: the
                      run's deployment env, as ppo.iteration.eval_env); rc needs a run trained with variant rc, pc
                      one trained with pc (BuildContext.run_dir for the variant asked, see `run_for`).
  delorean            the "without recovery policy" ablation = DeLorean: residual detector, selective state
                      reconstruction, reactive mode with a zero residual policy: the autopilot flies on the
                      reconstructed state (the reconstruction mode: evaluate.py --recon, default "fused").
  delorean_paper      the same with the paper's reconstruction (EnvConfig.recon_mode "paper": the fitted model
                      rolled forward open loop from the checkpoint), whatever --recon says.
  delorean_oracle     the same on a perfect reconstruction (recon_mode "oracle": the truth while the alarm is up), a
                      bound: what no reconstruction can fix (detection delay, before the alarm, after the hand-back).
  fallback            DeLorean plus the rule-based, uncertainty-aware fallback (no learning, EnvConfig.recovery_rule
                      'fallback', specguard_jax.autopilot.fallback): while the alarm is up the navigator's setpoint
                      slows down with the reconstruction's position uncertainty, widens obstacle clearance and holds
                      once the uncertainty exceeds the collision spec's margin.
  specguard_no_recon  ablation: the run's policy with state reconstruction off.
Other packages register more (`specguard_jax.baselines`, imported lazily by `available()` / `build()`).
A builder that cannot build (e.g. its training run is missing) raises `NotAvailable(reason)`: the report lists the
controller as "not run" with that reason.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
from typing import Any, Callable

import jax.numpy as jnp

from envs import observation as obs_lib
from envs.worlds import DEFAULT_WORLDS  # noqa: F401 (evaluate.py's default worlds)
from specguard_jax import export
from specguard_jax.ppo import config as config_lib
from specguard_jax.ppo.iteration import DeterministicPolicy


class NotAvailable(Exception):
  """A controller cannot be built in this context (missing training run, ...); str(e) is the reason."""


@dataclasses.dataclass(frozen=True)
class Controller:
  """A controller under evaluation: how the deployment env is configured and what flies it."""
  name: str                  # report key: 'no_protection', 'specguard_rc', 'specguard_pc', 'delorean', 'ssr', ...
  env_overrides: tuple       # ((EnvConfig field, value), ...) on top of the evaluation's base env config
  policy: Callable           # hashable: policy(params, obs [B, n_obs]) -> velocity setpoint [B, 3] (m/s)
  params: Any = dataclasses.field(default=None, compare=False, hash=False)   # pytree for policy
  description: str = ""

  def overrides(self) -> dict:
    return dict(self.env_overrides)


@dataclasses.dataclass(frozen=True)
class BuildContext:
  """What a builder may use. run_dir: the SpecGuard training run under evaluation (train.py output), if any;
  runs: extra named runs (evaluate.py --runs name=DIR), e.g. 'specguard_pc', 'binary', 'suburban'; cache_dir: where
  baselines store/load what they train; train_budget: 'ci' (tiny, CPU) | 'full' (GPU-sized)."""
  vehicle: str = "drone"
  run_dir: str | None = None
  cache_dir: str = "baselines"
  seed: int = 0
  worlds: tuple = DEFAULT_WORLDS
  train_budget: str = "ci"
  runs: tuple = ()           # ((name, dir), ...)

  def run(self, name: str) -> str | None:
    return dict(self.runs).get(name)


_REGISTRY: dict[str, tuple[Callable[[BuildContext], Controller], str]] = {}
_CHECKS: dict[str, Callable[[BuildContext], Any]] = {}
_LOADED_EXTRAS = False


def register(name: str, builder: Callable[[BuildContext], Controller], description: str = "",
             check: Callable[[BuildContext], Any] | None = None) -> None:
  """Register (or replace) a controller builder under `name`. check(ctx): raises NotAvailable when the controller
  cannot be built in ctx, cheaply (reading files only, no training, no env); `check()` runs it."""
  if not name or not name.replace("_", "").isalnum():
    raise ValueError(f"controller name must be alphanumeric/underscore, got {name!r}")
  _REGISTRY[name] = (builder, description)
  _CHECKS.pop(name, None)
  if check is not None:
    _CHECKS[name] = check


def _load_extras() -> None:
  global _LOADED_EXTRAS
  if _LOADED_EXTRAS:
    return
  _LOADED_EXTRAS = True
  if importlib.util.find_spec("specguard_jax.baselines") is not None:
    importlib.import_module("specguard_jax.baselines")


def available() -> list[str]:
  """Registered controller names (built-ins first, then specguard_jax.baselines' if that package exists)."""
  _load_extras()
  return list(_REGISTRY)


def describe(name: str) -> str:
  _load_extras()
  return _REGISTRY[name][1] if name in _REGISTRY else ""


def build(name: str, ctx: BuildContext) -> Controller:
  """The controller `name` in context ctx. Unknown name -> ValueError; NotAvailable when it cannot be built."""
  names = available()
  if name not in names:
    raise ValueError(f"unknown controller {name!r}; choose from {', '.join(names)}")
  c = _REGISTRY[name][0](ctx)
  if c.name != name:
    c = dataclasses.replace(c, name=name)
  return c


def check(name: str, ctx: BuildContext) -> None:
  """Raises NotAvailable (its reason) when controller `name` cannot be built in ctx, as far as its registered cheap
  check tells (evaluate.py runs it up front for the controllers asked for by name); no check: assumed buildable."""
  if name not in available():
    raise ValueError(f"unknown controller {name!r}; choose from {', '.join(available())}")
  if name in _CHECKS:
    _CHECKS[name](ctx)


def zero_policy(params, obs):
  """'Fly the autopilot's own setpoint': a zero velocity setpoint (or zero residual) [B, 3]."""
  del params
  return jnp.zeros((obs.shape[0], 3), jnp.float32)


# ---------------------------------------------------------------------------------------------------------------
# SpecGuard runs


def load_run_config(run_dir: str):
  """TrainConfig of a train.py run dir (config.json); NotAvailable when the run is missing or unreadable.
  Its EKF kernel choice (ekf_kernel, "lanes" on Hopper GPUs) is dropped: a training speed setting for the same
  filter, which evaluation does not use, so that a GPU-trained run evaluates on any machine."""
  path = os.path.join(run_dir, "config.json")
  if not os.path.isfile(path):
    raise NotAvailable(f"no training run at {run_dir} (config.json missing)")
  try:
    return config_lib.load_config_file(path, run=True).with_env(ekf_kernel="xla").validate()
  except ValueError as e:
    msg = " ".join(str(e).split())
    raise NotAvailable(msg if path in msg else f"{path}: {msg}") from None


def run_overrides(cfg, *, reconstruction: bool | None = None) -> tuple:
  """EnvConfig overrides of a run's deployment env (these fields of ppo.config.env_config(cfg, "eval"), without
  worlds/reward: the evaluation picks the worlds; the reward does not change what is flown). reconstruction False
  (the no-reconstruction ablation) also drops a recovery rule, which reads the reconstruction's uncertainty."""
  ev = config_lib.env_config(cfg, "eval")
  rec = ev.reconstruction if reconstruction is None else reconstruction
  rule = ev.recovery_rule if rec else "none"
  return (("control_mode", ev.control_mode), ("override_frame", ev.override_frame),
          ("override_residual", bool(ev.override_residual)), ("override_attitude", bool(ev.override_attitude)),
          ("detector", ev.detector),
          ("detector_delay", float(ev.detector_delay)), ("reconstruction", bool(rec)),
          ("override_phases", ev.override_phases), ("recovery_rule", rule))


def load_run_policy(run_dir: str):
  """(DeterministicPolicy, params {'policy','mean','std'}, TrainConfig) of a train.py run dir."""
  cfg = load_run_config(run_dir)
  try:
    policy, params, norm, speeds, clip = export.load_policy(run_dir)
  except ValueError as e:
    raise NotAvailable(str(e)) from None
  fn = DeterministicPolicy(policy, policy.kind, tuple(float(s) for s in speeds),
                           float(clip) if clip is not None else 1e9)
  p = {"policy": params, "mean": jnp.asarray(norm["mean"]), "std": jnp.asarray(norm["std"])}
  return fn, p, cfg


def run_for(ctx: BuildContext, variant: str) -> str:
  """The run dir of SpecGuard `variant` ('rc' | 'pc'): --runs specguard_<variant>=DIR, else --run if its config has
  that variant; NotAvailable otherwise."""
  named = ctx.run(f"specguard_{variant}")
  if named:
    return named
  if not ctx.run_dir:
    raise NotAvailable(f"no SpecGuard-{variant.upper()} run given (--run DIR or --runs specguard_{variant}=DIR)")
  cfg = load_run_config(ctx.run_dir)
  if cfg.variant != variant:
    raise NotAvailable(f"{ctx.run_dir} is a SpecGuard-{cfg.variant.upper()} run; give a {variant.upper()} run with "
                       f"--runs specguard_{variant}=DIR")
  return ctx.run_dir


def obs_overrides(run_dir: str) -> tuple:
  """EnvConfig overrides that build the observation a run's policy was trained on: its policy_config.json's layout
  (envs.observation), the 24-input paper layout where none is recorded. NotAvailable (one line) for a layout this
  version does not know or whose size differs from what the env would build."""
  try:
    desc = export.load_obs_layout(run_dir)
  except ValueError as e:
    raise NotAvailable(str(e)) from None
  if desc is None:
    return (("obs_layout", "paper24"),)
  name, sectors, history = desc["name"], obs_lib.sectors_of(desc), obs_lib.history_of(desc)
  if name not in obs_lib.LAYOUTS or obs_lib.describe(name, max(sectors, 1), history)["fields"] != desc["fields"]:
    raise NotAvailable(f"{run_dir}: the policy was trained on observation layout {name!r} version "
                       f"{desc['version']} ({sum(n for _, n in desc['fields'])} inputs), which this version does not "
                       f"build (layouts: {', '.join(obs_lib.LAYOUTS)}, version {obs_lib.LAYOUT_VERSION})")
  return ((("obs_layout", name),) + ((("proximity_sectors", sectors),) if sectors else ())
          + ((("obs_history", history),) if history > 1 else ()))


def deployment_overrides(cfg, run_dir: str, *, reconstruction: bool | None = None) -> tuple:
  """EnvConfig overrides of the env a train.py run's policy flies in: its deployment settings (run_overrides) and
  the observation it was trained on (obs_overrides, with the proximity range its layout reads). Every controller
  that flies a run's policy (SpecGuard, FTC-RL) builds its env from these, so its inputs match the policy's."""
  overrides = run_overrides(cfg, reconstruction=reconstruction) + obs_overrides(run_dir)
  if dict(overrides)["obs_layout"] in ("recovery", "context"):
    overrides += (("proximity_range", float(cfg.env.proximity_range)),)
  return overrides


def specguard_from_run(name: str, run_dir: str, *, reconstruction: bool | None = None,
                       description: str = "") -> Controller:
  """Controller flying a train.py run's policy in its deployment env (with the observation layout it was trained
  on)."""
  fn, p, cfg = load_run_policy(run_dir)
  overrides = deployment_overrides(cfg, run_dir, reconstruction=reconstruction)
  return Controller(name, overrides, fn, p, description or f"SpecGuard-{cfg.variant.upper()} from {run_dir}")


def _check_vehicle(ctx: BuildContext, run_dir: str) -> None:
  cfg = load_run_config(run_dir)
  if cfg.vehicle != ctx.vehicle:
    raise NotAvailable(f"{run_dir} was trained for the {cfg.vehicle}, evaluating the {ctx.vehicle}")


def _specguard(variant: str):
  def builder(ctx: BuildContext) -> Controller:
    d = run_for(ctx, variant)
    _check_vehicle(ctx, d)
    return specguard_from_run(f"specguard_{variant}", d)
  return builder


def _no_protection(ctx: BuildContext) -> Controller:
  del ctx
  return Controller("no_protection", (("control_mode", "autopilot"), ("detector", "none"),
                                      ("reconstruction", False)), zero_policy, None,
                    "the autopilot alone: no detector, no reconstruction, no recovery policy")


def _delorean(ctx: BuildContext) -> Controller:
  del ctx
  return Controller("delorean", (("control_mode", "reactive"), ("override_frame", "body"),
                                 ("override_residual", True), ("detector", "residual"), ("detector_delay", 0.0),
                                 ("reconstruction", True)), zero_policy, None,
                    "DeLorean / SpecGuard without the recovery policy: residual detector + selective state "
                    "reconstruction, the autopilot flies on the reconstructed state")


def _delorean_paper(ctx: BuildContext) -> Controller:
  c = _delorean(ctx)
  return dataclasses.replace(c, name="delorean_paper", env_overrides=c.env_overrides + (("recon_mode", "paper"),),
                             description="DeLorean with the paper's reconstruction: the fitted model rolled forward "
                                         "open loop from the last trusted checkpoint for the compromised components")


def _delorean_oracle(ctx: BuildContext) -> Controller:
  c = _delorean(ctx)
  return dataclasses.replace(c, name="delorean_oracle", env_overrides=c.env_overrides + (("recon_mode", "oracle"),),
                             description="DeLorean on a perfect reconstruction (recon_mode oracle: the truth while "
                                         "the alarm is up): a bound on what reconstruction can give the autopilot")


def _fallback(ctx: BuildContext) -> Controller:
  d = _delorean(ctx)
  return Controller("fallback", d.env_overrides + (("recovery_rule", "fallback"),), zero_policy, None,
                    "DeLorean + the rule-based fallback: while the alarm is up, slow down in proportion to the "
                    "reconstruction's position uncertainty over the spec margin, widen obstacle clearance, hold "
                    "when it exceeds the margin")


def _no_recon(ctx: BuildContext) -> Controller:
  d = ctx.run("specguard_no_recon")
  if d:   # a run trained without reconstruction (train.py --no-reconstruction)
    _check_vehicle(ctx, d)
    return specguard_from_run("specguard_no_recon", d, reconstruction=False,
                              description=f"SpecGuard trained and flown without state reconstruction ({d})")
  if not ctx.run_dir:
    raise NotAvailable("no SpecGuard run given (--run DIR)")
  _check_vehicle(ctx, ctx.run_dir)
  return specguard_from_run("specguard_no_recon", ctx.run_dir, reconstruction=False,
                            description=f"SpecGuard policy of {ctx.run_dir} flown with reconstruction off")


def _binary(ctx: BuildContext) -> Controller:
  d = ctx.run("binary")
  if not d:
    raise NotAvailable("no binary-reward run given (--runs binary=DIR, train.py --reward binary)")
  _check_vehicle(ctx, d)
  return specguard_from_run("specguard_binary", d, description=f"SpecGuard trained with the binary reward ({d})")


def _capped(ctx: BuildContext) -> Controller:
  d = ctx.run("capped")
  if not d:
    raise NotAvailable("no capped-reward run given (--runs capped=DIR, train.py --reward capped)")
  _check_vehicle(ctx, d)
  return specguard_from_run("specguard_capped", d,
                            description=f"SpecGuard trained with the capped compliance reward ({d})")


# The SpecGuard builders only read their run's files (config.json, policy.msgpack): each is its own cheap check.
register("no_protection", _no_protection, "the autopilot alone")
register("specguard_rc", _specguard("rc"), "SpecGuard Reactive Control (train.py run, variant rc)",
         check=_specguard("rc"))
register("specguard_pc", _specguard("pc"), "SpecGuard Proactive Control (train.py run, variant pc)",
         check=_specguard("pc"))
register("delorean", _delorean, "DeLorean = SpecGuard without the recovery policy (ablation)")
register("delorean_paper", _delorean_paper, "DeLorean with the paper's open-loop reconstruction (recon_mode paper)")
register("delorean_oracle", _delorean_oracle, "DeLorean on the truth while the alarm is up (recon_mode oracle)")


register("fallback", _fallback, "DeLorean + a rule-based, uncertainty-aware fallback (no learning)")
register("specguard_no_recon", _no_recon, "SpecGuard without state reconstruction (ablation)", check=_no_recon)
register("specguard_binary", _binary, "SpecGuard trained with the binary reward (ablation)", check=_binary)
register("specguard_capped", _capped, "SpecGuard trained with the capped compliance reward (ablation)", check=_capped)
