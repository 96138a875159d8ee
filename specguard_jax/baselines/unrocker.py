"""UnRocker baseline (denoising autoencoder + original controller).

What it is here: a denoising autoencoder (specguard_jax.estimation.dae: MLP encoder -> bottleneck -> decoder,
residual output) maps the autopilot's attacked state x'_t [15] (position, velocity, acceleration, Euler angles, body
rate: estimation.recon.INPUT_NAMES, from the EKF and the readings it fused) to the clean one. While the residual
detector's alarm is up, the navigator and the original autopilot fly on the DAE's position, velocity and attitude
(the EKF itself keeps running on the attacked readings); otherwise on the EKF. Chosen over denoising the raw
readings before the EKF: the DAE then sees one consistent state vector (the readings are multi-rate, with stale
samples between updates), it is the DAE the paper's appendix compares with, and the denoised state reaches the
controller directly, as in UnRocker.

Training pairs: attack-free autopilot flights (common.flights), attacked offline with random Table 3 attacks on
every sensor (overt and stealthy) and replayed through a fresh EKF (as bench/state_estimation.py); inputs x'_t of
that EKF, targets the true x'_t; attacked ticks plus 20 % of clean ones.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax import math3d
from specguard_jax.baselines.hooks import Estimator
from specguard_jax.estimation import dae as dae_lib
from specguard_jax.estimation import recon


@dataclasses.dataclass(eq=False)
class DAEEstimator(Estimator):
  cfg: dae_lib.DAEConfig
  params: dae_lib.DAEParams

  @classmethod
  def create(cls, env, model_path: str = ""):
    del env
    if not model_path:
      raise ValueError("recovery_estimator='dae' needs recovery_model= a DAE file (specguard_jax.baselines.unrocker)")
    cfg, params = load_dae(model_path)
    return cls(cfg, params)

  def init(self, ekf, readings):
    return jnp.zeros(())

  def post_ekf(self, sim, est, readings):
    alarm = jnp.asarray(sim["det"].alarm) > 0
    x_hat = dae_lib.dae_apply(self.cfg, self.params, recon.input_vector(est, readings))
    den = est.replace(pos=x_hat[0:3], vel=x_hat[3:6], quat=math3d.euler_to_quat(x_hat[9:12]))
    return sim, jax.tree.map(lambda a, b: jnp.where(alarm, a, b), den, est)


def _template(cfg: dae_lib.DAEConfig):
  net = dae_lib._DAE(cfg.hidden, cfg.bottleneck, recon.N_INPUT)
  p = net.init(jax.random.PRNGKey(0), jnp.zeros((1, recon.N_INPUT)))
  return dae_lib.DAEParams(net=p, mean=jnp.zeros(recon.N_INPUT), std=jnp.ones(recon.N_INPUT))


def load_dae(path: str):
  """(DAEConfig, DAEParams) from a cache file written by build; one-line ValueError if corrupt."""
  from specguard_jax.baselines import common
  _, meta = common.load_tree(path)
  try:
    cfg = dae_lib.DAEConfig(hidden=tuple(meta["hidden"]), bottleneck=int(meta["bottleneck"]))
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f"corrupt baseline cache {path}: bad DAE config ({e})") from None
  tree, _ = common.load_tree(path, _template(cfg))
  return cfg, jax.tree.map(jnp.asarray, tree)


def training_pairs(env, tr, key, clean_frac: float = 0.2):
  """(x_attacked [N, 15], x_true [N, 15]) from flights tr (leaves [B, T, ...]): one random attack per mission and
  sensor/profile, onset 20-60 % into the flight."""
  from specguard_jax import attacks as attacks_lib
  from specguard_jax.estimation import traces
  dt = env.config.tick_dt
  t_end = float(tr["time"][0, -1])
  combos = [(s, p) for s in attacks_lib.SENSOR_NAMES for p in attacks_lib.PROFILES]

  @jax.jit
  def one(trb, k):
    xs, ys, ms = [], [], []
    for i, (s, p) in enumerate(combos):
      ka, ko = jax.random.split(jax.random.fold_in(k, i))
      sch = attacks_lib.sample_attack(attacks_lib.AttackConfig(sensors=(s,), profiles=(p,)), ka,
                                      jnp.asarray(t_end))
      onset = jax.random.uniform(ko, (), minval=0.2 * t_end, maxval=0.6 * t_end)
      sch = sch.replace(onset=onset, duration=jnp.asarray(t_end))
      rd = traces.attacked_readings(trb["readings"], sch, trb["time"])
      ek = traces.replay_ekf(env.ekf_cfg, jax.tree.map(lambda a: a[0], trb["ekf_prev"]), rd, dt)
      xs.append(jax.vmap(recon.input_vector)(ek, rd))
      ys.append(jax.vmap(recon.true_input_vector)(trb["truth"]))
      ms.append(trb["time"] >= onset)
    return jnp.stack(xs), jnp.stack(ys), jnp.stack(ms)

  b = tr["time"].shape[0]
  out = [one(jax.tree.map(lambda a: a[i], tr), jax.random.fold_in(key, i)) for i in range(b)]
  x, y, m = (np.concatenate([np.asarray(o[j]).reshape((-1,) + np.shape(o[j])[2:]) for o in out]) for j in range(3))
  keep = m | (np.random.default_rng(0).random(m.shape) < clean_frac)
  ok = keep & np.all(np.isfinite(x), -1)
  return x[ok], y[ok]


ENV_OVERRIDES = (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
                 ("reconstruction", False), ("recovery_estimator", "dae"))


def build(ctx):
  """Controller 'unrocker': train (or load from ctx.cache_dir) the DAE; deploy it in the loop (module doc)."""
  from specguard_jax import controllers
  from specguard_jax.baselines import common
  path = common.cache_path(ctx, "unrocker", "msgpack")
  if not os.path.exists(path):
    b = common.budget(ctx.train_budget)
    env, tr = common.flights(ctx.vehicle, tuple(ctx.worlds), ctx.train_budget, ctx.seed)
    key = jax.random.fold_in(jax.random.PRNGKey(ctx.seed), 0xDAE)
    x, y = training_pairs(env, tr, key)
    cfg = dae_lib.DAEConfig(steps=b.fit_steps, batch=min(b.batch, 1024))
    params, loss = dae_lib.train_dae(cfg, jnp.asarray(x), jnp.asarray(y), key)
    common.save_tree(path, params, {"baseline": "unrocker", "vehicle": ctx.vehicle, "budget": ctx.train_budget,
                                    "seed": ctx.seed, "hidden": list(cfg.hidden), "bottleneck": cfg.bottleneck,
                                    "pairs": int(x.shape[0]), "train_loss": float(loss)})
  load_dae(path)
  return controllers.Controller("unrocker", ENV_OVERRIDES + (("recovery_model", os.path.abspath(path)),),
                                controllers.zero_policy, None,
                                "UnRocker: while the alarm is up the autopilot flies on a denoising autoencoder's "
                                "estimate of its attacked state; original controller")
