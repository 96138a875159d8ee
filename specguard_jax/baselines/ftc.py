"""FTC-RL baseline 'ftc_rl' (fault-tolerant RL recovery control trained only to avoid crashes, acting through the
velocity setpoint; the former FTC stand-in: 'ftc' now acts at the attitude loop, baselines/ftc_attitude.py).

Trained with OUR trainer (specguard_jax.ppo.runner.train, the same PPO, networks and attack agent as SpecGuard) with
reward='survival' (envs: 1 per step in flight, 0 on the crash/collision step; no spec terms; the completion bonus
keeps finishing the mission as good as flying on), variant 'rc' (the policy's residual velocity setpoint acts only
while the detector's alarm is up) and NO state reconstruction: it learns to keep flying on the attacked EKF state.
Phase 2 only (against the attack agent), at both budgets: like the original recovery-RL controller it learns under
attacks only. SpecGuard's phase 1 (no attacks) has nothing to teach a survival reward here: the autopilot alone
never crashes attack-free, so every policy that leaves it alone earns the same return, and the RC policy acts only
while the alarm is up, which phase 2 trains; skipping it also saves its ~50 s compile on the GPU.
Deployed like a SpecGuard-RC run without reconstruction: reactive mode, residual detector.

  'ci'  : 8 envs, 2 x 128 env steps on the CPU (a smoke-sized policy: the compile is most of its minutes)
  'full': 16,384 envs x 32-step unroll, 40 M phase-2 env steps on one GPU (under a minute of training, plus
          about as long again to compile); experiments/build_baselines.py prints
          the return curve (metrics.jsonl) to check it plateaus
"""

from __future__ import annotations

import dataclasses
import os

from specguard_jax import controllers
from specguard_jax.baselines import common
from specguard_jax.ppo import config as config_lib
from specguard_jax.ppo import runner

FULL_PHASE2_STEPS = 40_000_000


def train_config(ctx) -> config_lib.TrainConfig:
  common_kw = dict(vehicle=ctx.vehicle, variant="rc", seed=ctx.seed, eval_missions=0, eval_detector="residual")
  env_kw = dict(reward="survival", reconstruction=False, worlds=tuple(ctx.worlds))
  if ctx.train_budget == "ci":
    tiny = config_lib.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)
    return config_lib.TrainConfig(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=0,
                                  phase2_steps=256, hidden=(32, 32), sg=tiny, aa=tiny, checkpoint_every_s=1e9,
                                  **common_kw).with_env(**env_kw).validate()
  if ctx.train_budget == "full":
    sizes = dict(runner.default_sizes("gpu"), phase1_steps=0, phase2_steps=FULL_PHASE2_STEPS, eval_missions=0)
    return config_lib.TrainConfig(**{**sizes, **common_kw}).with_env(**env_kw).validate()
  common.budget(ctx.train_budget)   # raises the one-line error
  raise AssertionError


def build(ctx):
  """Controller 'ftc_rl': train (or load from ctx.cache_dir/ftc_rl_<vehicle>_<budget>_s<seed>_w<worlds tag>/)
  and deploy."""
  run_dir = common.cache_path(ctx, "ftc_rl", "")
  cfg = train_config(ctx)
  if not os.path.exists(os.path.join(run_dir, "summary.json")):
    resume = os.path.exists(os.path.join(run_dir, "config.json"))
    s = runner.train(cfg, run_dir, resume=resume, progress=ctx.train_budget == "full", export=True, log=print)
    if s.get("interrupted"):
      raise controllers.NotAvailable(f"FTC training in {run_dir} was interrupted; run again to resume")
  try:
    fn, p, run_cfg = controllers.load_run_policy(run_dir)
  except controllers.NotAvailable as e:
    raise ValueError(f"corrupt baseline cache {run_dir}: {e} (delete it to retrain)") from None
  if run_cfg.env.reward != "survival" or run_cfg.vehicle != ctx.vehicle:
    raise ValueError(f"corrupt baseline cache {run_dir}: holds a {run_cfg.vehicle} run with reward "
                     f"{run_cfg.env.reward!r}, not an FTC (survival) run (delete it to retrain)")
  # the run's observation layout too: the env's default layout is not the one train.py trains on
  over = controllers.deployment_overrides(dataclasses.replace(run_cfg, eval_detector="residual"), run_dir,
                                          reconstruction=False)
  return controllers.Controller("ftc_rl", over, fn, p,
                                "FTC-RL: RL recovery policy trained by our PPO only to survive (no specs), reactive, "
                                "no state reconstruction")
