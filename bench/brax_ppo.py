"""Brax's own PPO (`brax.training.agents.ppo.train.train`) on our env: the reference for training throughput.

  python bench/brax_ppo.py --vehicle drone --envs N --steps S [--unroll 20 --minibatches 8 --epochs 4]
      [--episode-length 1000] [--evals 5] [--eval-envs 128] [--no-evals] [--hidden 256 256 256 256] [--json OUT]

Batch: one PPO update collects `--envs` x `--unroll` env steps (Brax batch_size = envs / minibatches, one unroll per
env per update), then runs `--epochs` passes of `--minibatches` SGD steps over it (Brax num_updates_per_batch).
Prints one line: env steps, steps/s (env steps per second of training, rollout + updates, compile and evals
excluded), compile/startup time, wall time, final eval reward.

Throughput comes from Brax's own accounting: `train()` times each training epoch (a `pmap`-ed scan over training
steps, blocked until ready) into `training/walltime`; the first epoch carries the compile, so
sps = (steps after epoch 1) / (training walltime after epoch 1). At least 2 training epochs (num_evals >= 3) are
needed for that; evals (when run) are outside those timings.

Wrapping (`brax_wrap`, passed as `wrap_env_fn`): Brax's default `envs.training.wrap` runs mechanically on our env but
its AutoResetWrapper restores a cached first pipeline_state/obs and leaves `State.info` (EKF, navigator, mission,
world, episode clock) as the finished episode left it, so after its first episode an env would be truncated on every
step (see envs/base.py). We use VmapWrapper -> `_StepCap` (Brax's episode_length cap, keeping the env's own
time-limit truncation) -> `envs.wrappers.AutoReset` (pool of fresh missions/worlds) -> `_EpisodeStats` (Brax's
steps / episode_done / episode_metrics bookkeeping, outside the reset so a finished episode's figures survive it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State, Wrapper

if __package__ in (None, "") and __name__ == "__main__":
  sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

_EP_KEYS = ("steps", "episode_done", "episode_metrics")


def install_jax_shims():
  """Brax 0.14 calls jax.device_put_replicated / device_put_sharded, removed in JAX 0.10: single-host stand-ins
  (stack along a new leading device axis). Set only where missing."""
  # The stacked arrays go through an identity pmap over Brax's axis name so that they carry the sharding of
  # ppo.train's own pmap outputs (a mesh named after the pmap axis): otherwise its pmap-ed training epoch sees a new
  # input sharding on its second call (its inputs are then its own outputs) and compiles a second time.
  if not hasattr(jax, "device_put_replicated"):
    jax.device_put_replicated = lambda x, ds: _as_pmap_output(
        jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(ds)), x), ds)
  if not hasattr(jax, "device_put_sharded"):
    jax.device_put_sharded = lambda xs, ds: _as_pmap_output(jax.tree.map(lambda *a: jnp.stack(a), *xs), ds)


def _as_pmap_output(tree, devices):
  from brax.training.agents.ppo import train as ppo
  axis = getattr(ppo, "_PMAP_AXIS_NAME", "i")
  return jax.pmap(lambda t: t, axis_name=axis, devices=list(devices))(tree)


class _StepCap(Wrapper):
  """Brax's episode_length cap on a batched env: done after `episode_length` steps; info['truncation'] = 1 where the
  cap (or the env's own time limit) ended a non-terminated episode. The counter lives in info['cap_steps'] and is
  reset by the auto-reset outside (the pool's fresh states carry 0)."""

  def __init__(self, env, episode_length: int):
    super().__init__(env)
    self.episode_length = int(episode_length)

  def reset(self, rng):
    state = self.env.reset(rng)
    return state.replace(info=dict(state.info, cap_steps=jnp.zeros(rng.shape[:-1], jnp.int32)))

  def step(self, state, action):
    out = self.env.step(state, action)
    n = state.info["cap_steps"] + 1
    cap = n >= self.episode_length
    done = jnp.where(cap, 1.0, out.done).astype(out.done.dtype)
    trunc = jnp.where(cap & (out.done == 0), 1.0, out.info["truncation"]).astype(out.info["truncation"].dtype)
    return out.replace(done=done, info=dict(out.info, cap_steps=n, truncation=trunc))


class _EpisodeStats(Wrapper):
  """What Brax's EpisodeWrapper + AutoResetWrapper leave in info for `ppo.train` and its Evaluator: 'steps' (this
  episode's length so far, the finished one's on its done step), 'episode_done' (= done) and 'episode_metrics'
  (sum_reward, length and each State.metrics entry summed over the episode). Kept outside the auto-reset (which
  needs equal pytrees for the finished and the fresh state) and stripped before stepping it."""

  def reset(self, rng):
    state = self.env.reset(rng)
    z = jnp.zeros(rng.shape[:-1])
    em = {"sum_reward": z, "length": z, **{k: z for k in state.metrics}}
    return state.replace(info=dict(state.info, steps=z, episode_done=z, episode_metrics=em))

  def step(self, state, action):
    info = state.info
    keep = 1.0 - info["episode_done"]
    inner = {k: v for k, v in info.items() if k not in _EP_KEYS}
    out = self.env.step(state.replace(info=inner), action)
    em = info["episode_metrics"]
    new_em = {"sum_reward": em["sum_reward"] * keep + out.reward, "length": em["length"] * keep + 1.0}
    for k, v in out.metrics.items():
      new_em[k] = em[k] * keep + v
    steps = info["steps"] * keep + 1.0
    return out.replace(info=dict(out.info, steps=steps, episode_done=out.done, episode_metrics=new_em))


class _NullEnv(Env):
  """Stand-in eval env when evals are off: Brax builds (and jit-resets) its Evaluator regardless; this spares the
  compile of our env's reset at the eval batch. Never stepped."""

  def __init__(self, obs_size, act_size):
    self._o, self._a = obs_size, act_size

  def reset(self, rng):
    return State(pipeline_state=None, obs=jnp.zeros(self._o), reward=jnp.zeros(()), done=jnp.zeros(()), metrics={},
                 info={"steps": jnp.zeros(())})

  def step(self, state, action):
    return state

  @property
  def observation_size(self):
    return self._o

  @property
  def action_size(self):
    return self._a

  @property
  def backend(self):
    return "null"


def brax_wrap(env, episode_length: int = 1000, action_repeat: int = 1, randomization_fn=None):
  """`wrap_env_fn` for `ppo.train`: VmapWrapper -> _StepCap -> envs.wrappers.AutoReset -> _EpisodeStats."""
  from brax.envs.wrappers.training import VmapWrapper

  from envs.wrappers import AutoReset
  if isinstance(env, _NullEnv):
    return VmapWrapper(env)
  if action_repeat != 1 or randomization_fn is not None:
    raise ValueError("brax_wrap supports action_repeat=1 and no randomization_fn (the env randomises itself)")
  return _EpisodeStats(AutoReset(_StepCap(VmapWrapper(env), episode_length)))


def run_brax_ppo(env, *, num_envs: int, num_timesteps: int, unroll_length: int, batch_size: int,
                 num_minibatches: int, num_updates_per_batch: int, episode_length: int, seed: int = 0,
                 hidden=(256, 256, 256, 256), num_evals: int = 5, run_evals: bool = True, num_eval_envs: int = 128,
                 learning_rate: float = 3e-4, entropy_cost: float = 1e-3, discounting: float = 0.99,
                 normalize_observations: bool = True, log=None, **train_kwargs) -> dict:
  """Train Brax's PPO on `env` (an unwrapped brax Env, e.g. envs.make(...)) and time it.

  Per training step Brax collects batch_size * num_minibatches trajectories of unroll_length steps (num_envs
  parallel envs, (batch_size * num_minibatches) / num_envs unrolls each) and runs num_updates_per_batch passes of
  num_minibatches SGD steps. Policy and value MLPs have hidden layers `hidden`. `num_evals` - 1 training epochs
  (>= 2: the first carries the compile); with run_evals an eval of num_eval_envs episodes follows each epoch (and
  one precedes training). Extra keyword arguments go to `ppo.train`. `log`: optional callable(str) for progress.

  Returns {'env_steps', 'wall_s' (whole train() call), 'compile_s' (startup + compile: wall time to the end of
  the first epoch less evals and that epoch's steady-state share), 'sps' (env steps/s of training, rollout and
  updates, compile and evals excluded), 'final_reward' (last eval's mean episode reward; NaN without evals),
  'train_s' (timed training after epoch 1), 'eval_s', 'train_epochs', 'steps_per_update'}.
  """
  install_jax_shims()
  from brax.training.agents.ppo import networks as ppo_networks
  from brax.training.agents.ppo import train as ppo

  if num_evals < 3:
    raise ValueError("num_evals must be >= 3 (>= 2 training epochs: the first one carries the compile)")
  if (batch_size * num_minibatches) % num_envs:
    raise ValueError("batch_size * num_minibatches must be a multiple of num_envs")
  hidden = tuple(int(h) for h in hidden)
  factory = lambda obs_size, act_size, preprocess_observations_fn: ppo_networks.make_ppo_networks(
      obs_size, act_size, preprocess_observations_fn=preprocess_observations_fn,
      policy_hidden_layer_sizes=hidden, value_hidden_layer_sizes=hidden)
  calls = []  # (t since start, step, metrics) per epoch end

  def progress(step, metrics):
    calls.append((time.perf_counter() - t0, int(step), dict(metrics)))
    if log is not None:
      m = calls[-1][2]
      log(f"brax ppo: {step} env steps, t={calls[-1][0]:.1f} s, epoch sps {float(m.get('training/sps', 0)):.0f}"
          + (f", eval reward {float(m['eval/episode_reward']):.3f}" if "eval/episode_reward" in m else ""))

  eval_env = None if run_evals else _NullEnv(env.observation_size, env.action_size)
  t0 = time.perf_counter()
  ppo.train(env, num_timesteps=num_timesteps, num_envs=num_envs, episode_length=episode_length,
            wrap_env_fn=brax_wrap, unroll_length=unroll_length, batch_size=batch_size,
            num_minibatches=num_minibatches, num_updates_per_batch=num_updates_per_batch,
            learning_rate=learning_rate, entropy_cost=entropy_cost, discounting=discounting,
            normalize_observations=normalize_observations, network_factory=factory, seed=seed,
            num_evals=num_evals, run_evals=run_evals, eval_env=eval_env,
            num_eval_envs=num_eval_envs if run_evals else 1, progress_fn=progress, **train_kwargs)
  wall = time.perf_counter() - t0

  epochs = [c for c in calls if "training/walltime" in c[2]]
  if len(epochs) < 2:
    raise RuntimeError(f"expected >= 2 training epochs from ppo.train, got {len(epochs)}")
  (t1, s1, m1), (_, sN, mN) = epochs[0], epochs[-1]
  train_s = float(mN["training/walltime"]) - float(m1["training/walltime"])
  sps = (sN - s1) / train_s
  eval_before_1 = float(m1.get("eval/walltime", 0.0))
  compile_s = max(0.0, t1 - eval_before_1 - s1 / sps)
  final = float(mN["eval/episode_reward"]) if "eval/episode_reward" in mN else math.nan
  return {"env_steps": sN, "wall_s": wall, "compile_s": compile_s, "sps": sps, "final_reward": final,
          "train_s": train_s, "eval_s": float(mN.get("eval/walltime", 0.0)), "train_epochs": len(epochs),
          "steps_per_update": batch_size * num_minibatches * unroll_length}


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  p.add_argument("--envs", type=int, default=4096)
  p.add_argument("--steps", type=int, default=10_000_000, help="env steps to train (rounded up to whole updates)")
  p.add_argument("--unroll", type=int, default=20)
  p.add_argument("--minibatches", type=int, default=8)
  p.add_argument("--epochs", type=int, default=4, help="SGD passes over each batch (Brax num_updates_per_batch)")
  p.add_argument("--episode-length", type=int, default=1000, help="Brax's episode cap in env steps")
  p.add_argument("--evals", type=int, default=5, help="Brax num_evals (>= 3): num_evals - 1 timed epochs")
  p.add_argument("--eval-envs", type=int, default=128)
  p.add_argument("--no-evals", action="store_true", help="no evals (final_reward NaN)")
  p.add_argument("--hidden", type=int, nargs="+", default=[256, 256, 256, 256])
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--ekf-kernel", choices=("auto", "xla", "lanes"), default="auto",
                 help="the EKF tick: lanes (one GPU kernel), xla, or auto (lanes where supported)")
  p.add_argument("--verbose", action="store_true", help="one line per epoch on stderr")
  p.add_argument("--json", default=None)
  a = p.parse_args(argv)
  if a.envs % a.minibatches:
    p.error(f"--envs {a.envs} must be a multiple of --minibatches {a.minibatches}")
  import envs
  from specguard_jax.ppo.iteration import trainer_env_options
  env = envs.make(a.vehicle, control_mode="override", override_frame="body", ekf_kernel=a.ekf_kernel,
                  **trainer_env_options())   # the trainer's phase-1 env (iteration.make_env)
  log = (lambda s: print(s, file=sys.stderr, flush=True)) if a.verbose else None
  r = run_brax_ppo(env, num_envs=a.envs, num_timesteps=a.steps, unroll_length=a.unroll,
                   batch_size=a.envs // a.minibatches, num_minibatches=a.minibatches,
                   num_updates_per_batch=a.epochs, episode_length=a.episode_length, seed=a.seed,
                   hidden=a.hidden, num_evals=a.evals, run_evals=not a.no_evals, num_eval_envs=a.eval_envs, log=log)
  r.update(vehicle=a.vehicle, ekf_kernel=a.ekf_kernel, envs=a.envs, unroll=a.unroll, minibatches=a.minibatches,
           sgd_epochs=a.epochs, hidden=list(a.hidden), backend=jax.default_backend(), trainer="brax.training.agents.ppo")
  print(f"brax-ppo {a.vehicle} {jax.default_backend()}: {a.envs} envs, unroll {a.unroll}, {a.minibatches} minibatches"
        f" x {a.epochs} epochs: {r['env_steps']} env steps, {r['sps']:.0f} env steps/s (updates included, compile"
        f" excluded), compile {r['compile_s']:.1f} s, wall {r['wall_s']:.1f} s, final eval reward"
        f" {r['final_reward']:.3f}", flush=True)
  if a.json:
    with open(a.json, "w") as f:
      json.dump({k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()}, f, indent=1)


if __name__ == "__main__":
  main()
