"""Shared pieces of the baseline builders: training budgets, attack-free flight recording, supervised fits, cache.

`flights(vehicle, worlds, budget, seed)` flies attack-free autopilot missions (all missions vmapped in one jitted
lax.scan over env steps, each an inner scan over its autopilot ticks) and records per tick what the baselines train
on: truth, readings, the EKF's nominal state (not its covariance: the recording stays small; the full initial EKF
state is kept for replays), controls of the previous tick, navigator phase, the navigator's velocity setpoint and
the plan's leg velocity (recomputed with autopilot.navigator.nav_step from the tick's inputs: exactly what the
autopilot was given); per env step the policy observation. Memoised per process: SSR, UnRocker and PID-Piper share
one recording (and its compile).
`adam_fit` is the one minibatch Adam loop of the learned baselines (PID-Piper's MLP, UnRocker's DAE).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import zlib

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.missions import MissionConfig
from specguard_jax.estimation.tree_file import load_tree, save_tree  # noqa: F401 (the caches: common.save_tree)

BUDGETS = ("ci", "full")


@dataclasses.dataclass(frozen=True)
class Budget:
  """Training size of the baselines that learn from attack-free flights (FTC: ftc.train_config).

  missions x seconds: the shared flight recording (SSR's ridge fit, UnRocker's pairs, PID-Piper's samples);
  fit_steps x batch: Adam minibatches of PID-Piper's MLP and UnRocker's DAE; pair_stride: UnRocker keeps every
  pair_stride-th tick of its attacked replays (neighbouring ticks are near duplicates)."""
  missions: int
  seconds: float
  fit_steps: int
  batch: int
  pair_stride: int = 1


def budget(name: str) -> Budget:
  if name == "ci":
    return Budget(missions=24, seconds=30.0, fit_steps=1500, batch=256, pair_stride=1)
  if name == "full":
    return Budget(missions=512, seconds=90.0, fit_steps=20000, batch=2048, pair_stride=5)
  raise ValueError(f"unknown train_budget {name!r}; choose one of {', '.join(BUDGETS)}")


def worlds_tag(worlds) -> str:
  """8 hex digits naming a tuple of training worlds (in order: the order sets which missions fly where)."""
  return f"{zlib.crc32(','.join(worlds).encode()):08x}"


def cache_path(ctx, name: str, ext: str) -> str:
  """<cache_dir>/<name>_<vehicle>_<budget>_s<seed>_w<worlds_tag>.<ext> (ext '' -> a directory): a baseline trained in
  other worlds is another cache, never reused by mistake."""
  base = os.path.join(ctx.cache_dir, f"{name}_{ctx.vehicle}_{ctx.train_budget}_s{ctx.seed}_w{worlds_tag(ctx.worlds)}")
  return base + (f".{ext}" if ext else "")


def make_env(vehicle: str, worlds: tuple, seconds: float, **kw):
  mcfg = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      min_duration_s=seconds + 10.0, max_duration_s=seconds + 60.0)
  return envs.make(vehicle, worlds=tuple(worlds), mission=mcfg, **kw)


EKF_FIELDS = ("pos", "vel", "quat", "gyro_bias", "accel_bias")


def _record(env, keys, n_steps: int):
  """Attack-free flights of len(keys) missions for n_steps env steps (module doc); per-tick leaves [B, T, ...]
  (T = n_steps * ticks_per_step), 'obs' [B, n_steps, 24] (policy observation at each env step's start), 'ekf0'
  the EKF state before the first tick [B, ...]."""
  fields = ("truth", "readings") + tuple(f"ekf.{f}" for f in EKF_FIELDS) + ("controls", "time", "phase", "vel_nav",
                                                                           "leg_vel")
  rec = envs.record(env, keys, n_steps * env.config.ticks_per_step, fields, step_fields=("obs",),
                    initial_fields=("ekf",))
  ekf = {f: rec.pop(f"ekf.{f}") for f in EKF_FIELDS}
  return dict(rec, ekf=ekf, ekf0=rec.pop("initial_ekf"))


@functools.lru_cache(maxsize=2)
def flights(vehicle: str, worlds: tuple, budget_name: str, seed: int):
  """(env, trace dict) of budget(budget_name).missions attack-free flights of budget.seconds (module doc): leaves
  [B, T, ...] per autopilot tick ('truth', 'readings', 'ekf' (nominal state: EKF_FIELDS), 'controls' of the previous
  tick, 'time', 'phase', 'vel_nav', 'leg_vel'), 'obs' [B, S, 24] per env step, 'ekf0' [B] the full EKF state
  before tick 0."""
  b = budget(budget_name)
  env = make_env(vehicle, worlds, b.seconds)
  keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), 0xB45E), b.missions)
  tr = _record(env, keys, int(round(b.seconds / (env.config.tick_dt * env.config.ticks_per_step))))
  return env, jax.block_until_ready(tr)


def adam_fit(loss_fn, params, mask, steps: int, batch: int, key, lr: float):
  """Minimise loss_fn(params, idx [batch] int32, key) with Adam (cosine decay to 5 % of lr) over `steps` minibatches
  of row indices drawn uniformly, with replacement, from the rows where mask [N] (bool or 0/1) is set (jittable; call
  inside jit; O(batch) per step: the selected rows are listed once). Returns (params, losses [steps])."""
  import optax
  opt = optax.adam(optax.cosine_decay_schedule(lr, steps, 0.05))
  on = jnp.asarray(mask) > 0
  rows = jnp.nonzero(on, size=on.shape[0], fill_value=0)[0].astype(jnp.int32)
  count = jnp.maximum(jnp.sum(on), 1)

  def body(carry, k):
    p, st = carry
    k_idx, k_loss = jax.random.split(k)
    idx = rows[jax.random.randint(k_idx, (batch,), 0, count)]
    loss, g = jax.value_and_grad(loss_fn)(p, idx, k_loss)
    upd, st = opt.update(g, st, p)
    return (optax.apply_updates(p, upd), st), loss

  (params, _), losses = jax.lax.scan(body, (params, opt.init(params)), jax.random.split(key, steps))
  return params, losses


def turn_about_z(v, angle, xy_pairs: tuple, yaw_index: int):
  """Rows of v [N, n] as seen in a world turned by angle [N] (rad) about z: each (i, j) of xy_pairs is a world-frame
  horizontal vector (rotated), v[:, yaw_index] an Euler yaw (shifted, wrapped to [-pi, pi)); the rest is unchanged."""
  c, s = jnp.cos(angle), jnp.sin(angle)
  for i, j in xy_pairs:
    vi, vj = v[:, i], v[:, j]
    v = v.at[:, i].set(c * vi - s * vj).at[:, j].set(s * vi + c * vj)
  if yaw_index is not None:
    v = v.at[:, yaw_index].set(wrap_angle(v[:, yaw_index] + angle))
  return v


def wrap_angle(a):
  return jnp.mod(a + jnp.pi, 2 * jnp.pi) - jnp.pi


def loss_curve(losses, points: int = 10) -> list:
  """Mean training loss over `points` equal chunks of the steps (cache meta: does the fit plateau?)."""
  a = np.asarray(losses, np.float64)
  return [float(f"{c.mean():.4g}") for c in np.array_split(a, min(points, len(a)))]


@functools.partial(jax.jit, static_argnames=("hidden", "steps", "batch", "augment"))
def fit_mlp(x, y, w, hidden: tuple, steps: int, batch: int, key, lr: float = 1e-3, augment=None):
  """Supervised MLP (flax + optax Adam, cosine decay) on standardised inputs: minimises the mean (f(x) - y)^2 over
  the rows where w is set. x [N, n], y [N, m], w [N] 0/1 mask; augment (hashable, optional): (x [b, n], y [b, m], key) -> (x, y) applied to each
  minibatch. Returns (params {'net', 'x_mean', 'x_std', 'y_scale'} for `mlp_apply`, losses [steps])."""
  x_mean, x_std = jnp.mean(x, 0), jnp.std(x, 0) + 1e-3
  y_scale = jnp.std(y, 0) + 1e-3
  net = _MLP(tuple(hidden), y.shape[-1])
  k_init, k_b = jax.random.split(key)
  p0 = net.init(k_init, jnp.zeros((1, x.shape[-1])))

  def loss_fn(p, idx, k):
    xb, yb = x[idx], y[idx]
    if augment is not None:
      xb, yb = augment(xb, yb, k)
    return jnp.mean((net.apply(p, (xb - x_mean) / x_std) - yb / y_scale) ** 2)

  p, losses = adam_fit(loss_fn, p0, w, steps, batch, k_b, lr)
  return {"net": p, "x_mean": x_mean, "x_std": x_std, "y_scale": y_scale}, losses


def mlp_apply(hidden: tuple, params, x):
  """x [..., n] -> [..., m] with fit_mlp's params."""
  net = _MLP(tuple(hidden), params["y_scale"].shape[-1])
  return net.apply(params["net"], (x - params["x_mean"]) / params["x_std"]) * params["y_scale"]


import flax.linen as nn  # noqa: E402


class _MLP(nn.Module):
  hidden: tuple
  n_out: int

  @nn.compact
  def __call__(self, x):
    for h in self.hidden:
      x = nn.tanh(nn.Dense(h)(x))
    return nn.Dense(self.n_out)(x)

def budget_summary(name: str) -> dict:
  """The sizes of budget `name` (experiments/build_baselines.py reports them)."""
  return dataclasses.asdict(budget(name))


def build_meta(ctx, name: str) -> dict:
  """What a built baseline's cache says about its training (msgpack meta; FTC-RL: summary + phase-2 return curve)."""
  if name != "ftc_rl":
    return load_tree(cache_path(ctx, name, "msgpack"))[1]
  run = cache_path(ctx, "ftc_rl", "")
  with open(os.path.join(run, "summary.json")) as f:
    s = json.load(f)
  curve = []
  with open(os.path.join(run, "metrics.jsonl")) as f:
    for line in f:
      r = json.loads(line)
      curve.append([r["phase"], r["env_steps"], round(r["return"], 3), round(r["svr"], 4), round(r["rsr"], 4)])
  stride = max(1, len(curve) // 20)
  return {"env_steps": s["env_steps"], "train_wall_s": s["train_wall_s"], "compile_s": s["compile_s"],
          "converged": s["converged"], "final_train_metrics": s["final_train_metrics"],
          "curve_phase_steps_return_svr_rsr": curve[::stride] + ([curve[-1]] if curve[-1:] != curve[::stride][-1:]
                                                                  else [])}
