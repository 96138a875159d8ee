"""Shared pieces of the baseline builders: training budgets, attack-free flight recording, artifact cache.

`flights(vehicle, worlds, budget, seed)` flies attack-free autopilot missions (batched, one jitted lax.scan over
autopilot ticks, like estimation.traces.record) and records per tick what the baselines train on: truth, readings,
EKF, controls of the previous tick, navigator phase, the navigator's velocity setpoint (recomputed with
autopilot.navigator.nav_step from the tick's inputs: exactly what the autopilot was given) and the policy
observation. Memoised per process: SSR, UnRocker and PID-Piper share one recording.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

BUDGETS = ("ci", "full")


@dataclasses.dataclass(frozen=True)
class Budget:
  """missions x seconds of attack-free flights; fit_steps: supervised (Adam) steps for the learned models."""
  missions: int
  seconds: float
  fit_steps: int
  batch: int


def budget(name: str) -> Budget:
  if name == "ci":
    return Budget(missions=6, seconds=30.0, fit_steps=1500, batch=256)
  if name == "full":
    return Budget(missions=512, seconds=90.0, fit_steps=20000, batch=4096)
  raise ValueError(f"unknown train_budget {name!r}; choose one of {', '.join(BUDGETS)}")


def cache_path(ctx, name: str, ext: str) -> str:
  """<cache_dir>/<name>_<vehicle>_<budget>_s<seed>.<ext> (ext '' -> a directory)."""
  base = os.path.join(ctx.cache_dir, f"{name}_{ctx.vehicle}_{ctx.train_budget}_s{ctx.seed}")
  return base + (f".{ext}" if ext else "")


def save_tree(path: str, tree, meta: dict) -> None:
  """msgpack of {'meta': json string, 'tree': pytree of arrays}, written atomically."""
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  blob = flax.serialization.msgpack_serialize({"meta": json.dumps(meta),
                                               "tree": flax.serialization.to_state_dict(
                                                   jax.tree.map(np.asarray, tree))})
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    f.write(blob)
  os.replace(tmp, path)


def load_tree(path: str, template=None):
  """(tree, meta) from save_tree's file; restored into `template`'s structure when given. Missing, corrupt or
  mismatched file -> one-line ValueError naming it."""
  try:
    with open(path, "rb") as f:
      d = flax.serialization.msgpack_restore(f.read())
    meta = json.loads(d["meta"])
    tree = d["tree"]
    if template is not None:
      tree = flax.serialization.from_state_dict(template, tree)
      bad = [(a.shape, b.shape) for a, b in zip(jax.tree.leaves(template), jax.tree.leaves(tree))
             if np.shape(a) != np.shape(b)]
      if bad or len(jax.tree.leaves(template)) != len(jax.tree.leaves(tree)):
        raise ValueError(f"shapes {bad[:2]} do not match")
  except Exception as e:  # noqa: BLE001 - msgpack/flax raise many unrelated types on corrupt input
    raise ValueError(f"corrupt baseline cache {path}: {' '.join(f'{type(e).__name__}: {e}'.split())[:200]} "
                     f"(delete it to retrain)") from None
  return tree, meta


def make_env(vehicle: str, worlds: tuple, seconds: float, **kw):
  import envs
  from envs.missions import MissionConfig
  mcfg = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      min_duration_s=seconds + 10.0, max_duration_s=seconds + 60.0)
  return envs.make(vehicle, worlds=tuple(worlds), mission=mcfg, **kw)


@functools.partial(jax.jit, static_argnames=("env", "n_ticks"))
def _record(env, keys, n_ticks: int):
  from specguard_jax.autopilot import navigator as nav_lib
  from specguard_jax.estimation import traces
  state = jax.vmap(env.reset)(keys)

  def one(state, key):
    info = state.info
    mission, world = info["mission"], info["world"]

    def tick(carry, k):
      data, sim = carry
      u_prev = traces.vehicle_controls(env.vehicle, sim)
      obs = env._observation(world, mission, sim)     # what a policy deciding at this tick would see
      landed = env._vehicle_landed(sim)
      data2, sim2 = env._tick(data, sim, mission, world, jnp.zeros(3), jnp.zeros((), bool), k, None)
      _, vel_nav, _ = nav_lib.nav_step(env._nav_params(), sim["nav"], mission, sim2["ekf"].pos, landed,
                                       env.config.tick_dt)
      out = {"truth": sim["truth"], "readings": sim2["readings"], "ekf": sim2["ekf"], "ekf_prev": sim["ekf"],
             "controls": u_prev, "time": sim2["nav"].time, "phase": sim2["nav"].phase, "vel_nav": vel_nav,
             "obs": obs}
      return (data2, sim2), out

    _, tr = jax.lax.scan(tick, (state.pipeline_state, info["sim"]), jax.random.split(key, n_ticks))
    return tr

  return jax.vmap(one)(state, jax.vmap(lambda k: jax.random.fold_in(k, 7))(keys))


@functools.lru_cache(maxsize=4)
def flights(vehicle: str, worlds: tuple, budget_name: str, seed: int):
  """(env, trace dict with leaves [B, T, ...]) of budget(budget_name).missions attack-free flights (see module doc)."""
  b = budget(budget_name)
  env = make_env(vehicle, worlds, b.seconds)
  keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), 0xB45E), b.missions)
  tr = _record(env, keys, int(round(b.seconds / env.config.tick_dt)))
  return env, jax.block_until_ready(tr)


def fit_mlp(x, y, w, hidden: tuple, steps: int, batch: int, key, lr: float = 1e-3):
  """Supervised MLP (flax + optax Adam, cosine decay) on standardised inputs: minimises sum_j w (f(x) - y)^2 / sum w.
  x [N, n], y [N, m], w [N] >= 0. Returns params {'net', 'x_mean', 'x_std', 'y_scale'} for `mlp_apply`."""
  import optax
  x_mean, x_std = jnp.mean(x, 0), jnp.std(x, 0) + 1e-3
  y_scale = jnp.std(y, 0) + 1e-3
  net = _MLP(tuple(hidden), y.shape[-1])
  k_init, k_b = jax.random.split(key)
  p = net.init(k_init, jnp.zeros((1, x.shape[-1])))
  opt = optax.adam(optax.cosine_decay_schedule(lr, steps, 0.05))
  xs, ys = (x - x_mean) / x_std, y / y_scale
  probs = w / jnp.sum(w)

  def body(carry, k):
    p, st = carry
    idx = jax.random.choice(k, xs.shape[0], (batch,), p=probs)
    loss, g = jax.value_and_grad(lambda p: jnp.mean((net.apply(p, xs[idx]) - ys[idx]) ** 2))(p)
    upd, st = opt.update(g, st, p)
    return (optax.apply_updates(p, upd), st), loss

  (p, _), losses = jax.lax.scan(body, (p, opt.init(p)), jax.random.split(k_b, steps))
  return {"net": p, "x_mean": x_mean, "x_std": x_std, "y_scale": y_scale}, losses


fit_mlp = jax.jit(fit_mlp, static_argnames=("hidden", "steps", "batch"))


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
