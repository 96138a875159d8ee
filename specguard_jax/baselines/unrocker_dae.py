"""State-level denoising-autoencoder baseline 'unrocker_dae' (a DAE in front of the original controller; the former
stand-in for UnRocker, which now denoises the IMU readings: baselines/unrocker.py).

What it is here: a denoising autoencoder (specguard_jax.estimation.dae: MLP encoder -> bottleneck -> decoder,
residual output) maps the autopilot's attacked state x'_t [15] (position, velocity, acceleration, Euler angles, body
rate: estimation.recon.INPUT_NAMES, from the EKF and the readings it fused) to the clean one. While the residual
detector's alarm is up, the navigator and the original autopilot fly on the DAE's position, velocity and attitude
(the EKF itself keeps running on the attacked readings); otherwise on the EKF. Chosen over denoising the raw
readings before the EKF: the DAE then sees one consistent state vector (the readings are multi-rate, with stale
samples between updates), it is the DAE the paper's appendix compares with, and the denoised state reaches the
controller directly, as in UnRocker.

Training pairs: attack-free autopilot flights (common.flights), attacked offline with random Table 3 attacks on
every sensor (overt and stealthy) and replayed through a fresh EKF (as experiments/state_estimation.py); inputs x'_t of
that EKF, targets the true x'_t; attacked ticks plus 20 % of clean ones. All missions x attacks replay in one
vmapped, jitted scan (`training_pairs`); the DAE trains on the first 4/5 of the missions and its held-out denoising
error (against the attacked input's own error) is stored in the cache's meta.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp

from specguard_jax import attacks as attacks_lib
from specguard_jax import controllers
from specguard_jax import ekf as ekf_lib
from specguard_jax.baselines import common
from specguard_jax.baselines.common import adam_fit
from specguard_jax.estimation import dae as dae_lib
from specguard_jax.estimation.dae import load_dae
from specguard_jax.estimation import recon


COMBOS = tuple((s, p) for s in attacks_lib.SENSOR_NAMES for p in attacks_lib.PROFILES)


@functools.partial(jax.jit, static_argnames=("ekf_cfg", "dt", "stride"))
def training_pairs(ekf_cfg, dt: float, tr, key, stride: int = 1, clean_frac: float = 0.2):
  """Attacked inputs of flights tr (common.flights, leaves [B, T, ...]), all missions and attacks in one scan over
  the ticks (each tick: the B x C attacked readings and EKF updates, vmapped): per mission one random attack per
  (sensor, profile) of COMBOS (C = 12), onset uniform in 20-60 % of the flight, lasting to its end, applied to the
  recorded readings and replayed through a fresh EKF from the recorded initial state (only x'_t leaves the scan, not
  the covariance or the attacked readings). Returns (x_attacked [B, C, T', 15], x_true [B, T', 15], weight
  [B, C, T']) at ticks 0, stride, 2 stride, ... (T' = T // stride): weight 1 on attacked ticks and on a random
  clean_frac of the clean ones, 0 elsewhere and where x is not finite."""
  time = tr["time"]
  t_end = time[0, -1]
  b, t = time.shape
  n = t // stride

  def schedules(k):   # [C] schedules of one mission
    out = []
    for i, (sensor, profile) in enumerate(COMBOS):
      ka, ko = jax.random.split(jax.random.fold_in(k, i))
      sch = attacks_lib.sample_attack(attacks_lib.AttackConfig(sensors=(sensor,), profiles=(profile,)), ka, t_end)
      onset = jax.random.uniform(ko, (), minval=0.2 * t_end, maxval=0.6 * t_end)
      out.append(sch.replace(onset=onset, duration=t_end))
    return jax.tree.map(lambda *a: jnp.stack(a), *out)

  k_sch, k_clean = jax.random.split(key)
  sch = jax.vmap(schedules)(jax.random.split(k_sch, b))                                       # [B, C]
  ekf0 = jax.tree.map(lambda a: jnp.repeat(a[:, None], len(COMBOS), 1), tr["ekf0"])          # [B, C]
  attack = jax.vmap(jax.vmap(attacks_lib.apply_attack, (None, 0, None)))                     # [B] x [B, C] -> [B, C]
  update = jax.vmap(jax.vmap(lambda s, r: ekf_lib.ekf_step(ekf_cfg, s, r, dt)))
  inputs = jax.vmap(jax.vmap(recon.input_vector))

  def tick(ekf, xs):
    rd, tm = xs
    rd = attack(rd, sch, tm)
    ekf = update(ekf, rd)
    return ekf, inputs(ekf, rd)

  def chunk(ekf, xs):   # stride ticks; x'_t of the first leaves
    ekf, x = jax.lax.scan(tick, ekf, xs)
    return ekf, x[0]

  by_time = jax.tree.map(lambda a: jnp.swapaxes(a[:, :n * stride], 0, 1).reshape((n, stride, b) + a.shape[2:]),
                         (tr["readings"], time))
  _, x = jax.lax.scan(chunk, ekf0, by_time)                                                  # [T', B, C, 15]
  x = jnp.moveaxis(x, 0, 2)
  y = jax.vmap(jax.vmap(recon.true_input_vector))(tr["truth"])[:, :n * stride:stride]
  attacked = time[:, None, :n * stride:stride] >= sch.onset[:, :, None]
  keep = attacked | (jax.random.uniform(k_clean, attacked.shape) < clean_frac)
  return x, y, (keep & jnp.all(jnp.isfinite(x), -1)).astype(jnp.float32)


# x'_t layout (recon.INPUT_NAMES): world-frame horizontal pairs of position, velocity, acceleration; Euler yaw
_XY_PAIRS = ((0, 1), (3, 4), (6, 7))
_YAW = 9 + 2
SHIFT_M = 200.0


def _augment(x, y, key):
  """Turn each (attacked, true) pair's world by a random angle about z and shift it horizontally by up to SHIFT_M m
  (both members alike): the EKF, the attacks and the DAE's job do not depend on where or which way a mission flies,
  so the DAE must not key on the training missions' absolute positions or headings."""
  k_a, k_d = jax.random.split(key)
  a = jax.random.uniform(k_a, (x.shape[0],), minval=-jnp.pi, maxval=jnp.pi)
  d = jnp.zeros_like(x).at[:, 0:2].set(jax.random.uniform(k_d, (x.shape[0], 2), minval=-SHIFT_M, maxval=SHIFT_M))
  turn = lambda v: common.turn_about_z(v, a, _XY_PAIRS, _YAW) + d   # noqa: E731
  return turn(x), turn(y)


def _error(x_hat, y):
  """x_hat - y [..., 15] with the yaw difference wrapped (the deployed attitude is periodic in the Euler angles)."""
  e = x_hat - y
  return e.at[..., _YAW].set(common.wrap_angle(e[..., _YAW]))


@functools.partial(jax.jit, static_argnames=("cfg", "n_train"))
def fit_dae(cfg: dae_lib.DAEConfig, x, y, w, key, n_train: int):
  """Fit the DAE on training_pairs (x [B, C, T, 15], y [B, T, 15], w [B, C, T]) of the first n_train missions:
  Adam (cosine decay) on the standardised MSE (estimation.dae.train_dae's loss, yaw error wrapped) of turned and
  shifted minibatches (_augment). Returns (DAEParams, losses [steps], held-out dict on the other missions' weighted
  pairs: 'loss' / 'loss_identity' (standardised MSE of the DAE / of the attacked input itself), 'pos_rmse_m',
  'vel_rmse_m_s', 'euler_rmse_deg' and their '_identity' twins)."""
  _, c, t, n = x.shape
  yt = y[:n_train]
  wf = w[:n_train].reshape(-1)
  wt = jnp.sum(w[:n_train], 1)[..., None]          # [B, T, 1] how often truth (b, t) is a target
  mean = jnp.sum(yt * wt, (0, 1)) / jnp.sum(wf)
  std = jnp.sqrt(jnp.sum((yt - mean) ** 2 * wt, (0, 1)) / jnp.sum(wf)) + 1e-3
  net = dae_lib.DAENet(cfg.hidden, cfg.bottleneck, n)
  k_init, k_fit = jax.random.split(key)
  p0 = net.init(k_init, jnp.zeros((1, n)))
  xf = jnp.nan_to_num(x[:n_train].reshape(-1, n))
  yf = yt.reshape(-1, n)

  def loss_fn(p, idx, k):
    xb, yb = _augment(xf[idx], yf[(idx // (c * t)) * t + idx % t], k)   # row (b, c, t) pairs with truth (b, t)
    x_hat = net.apply(p, (xb - mean) / std) * std + mean
    return jnp.mean((_error(x_hat, yb) / std) ** 2)

  p, losses = adam_fit(loss_fn, p0, wf, cfg.steps, cfg.batch, k_fit, cfg.lr)
  params = dae_lib.DAEParams(net=p, mean=mean, std=std)
  xv, yv, wv = jnp.nan_to_num(x[n_train:]), y[n_train:, None], w[n_train:]
  wsum = jnp.maximum(jnp.sum(wv), 1.0)
  wmean = lambda a: jnp.sum(a * wv) / wsum   # noqa: E731
  out = {}
  for name, xe in (("", dae_lib.dae_apply(cfg, params, xv)), ("_identity", xv)):
    e = _error(xe, yv)
    out["loss" + name] = wmean(jnp.mean((e / std) ** 2, -1))
    out["pos_rmse_m" + name] = jnp.sqrt(wmean(jnp.sum(e[..., 0:3] ** 2, -1)))
    out["vel_rmse_m_s" + name] = jnp.sqrt(wmean(jnp.sum(e[..., 3:6] ** 2, -1)))
    out["euler_rmse_deg" + name] = jnp.degrees(jnp.sqrt(wmean(jnp.sum(e[..., 9:12] ** 2, -1))))
  return params, losses, out


ENV_OVERRIDES = (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
                 ("reconstruction", False), ("recovery_estimator", "dae"))


def build(ctx):
  """Controller 'unrocker_dae': train (or load from ctx.cache_dir) the DAE; deploy it in the loop (module doc)."""
  path = common.cache_path(ctx, "unrocker_dae", "msgpack")
  if not os.path.exists(path):
    b = common.budget(ctx.train_budget)
    env, tr = common.flights(ctx.vehicle, tuple(ctx.worlds), ctx.train_budget, ctx.seed)
    key = jax.random.fold_in(jax.random.PRNGKey(ctx.seed), 0xDAE)
    x, y, w = training_pairs(env.ekf_cfg, env.config.tick_dt, tr, key, stride=b.pair_stride)
    n_missions = x.shape[0]
    n_train = n_missions - max(1, n_missions // 5) if n_missions > 1 else 1
    cfg = dae_lib.DAEConfig(steps=b.fit_steps, batch=b.batch)
    params, losses, held = fit_dae(cfg, x, y, w, jax.random.fold_in(key, 1), n_train)
    held = {k: float(f"{float(v):.4g}") for k, v in held.items()}
    common.save_tree(path, params, {"baseline": "unrocker_dae", "vehicle": ctx.vehicle, "budget": ctx.train_budget,
                                    "seed": ctx.seed, "hidden": list(cfg.hidden), "bottleneck": cfg.bottleneck,
                                    "pairs": int(jnp.sum(w[:n_train] > 0)), "train_missions": n_train,
                                    "train_loss": float(jnp.mean(losses[-50:])),
                                    "loss_curve": common.loss_curve(losses),
                                    **{f"heldout_{k}": v for k, v in held.items()}})
  load_dae(path)
  return controllers.Controller("unrocker_dae", ENV_OVERRIDES + (("recovery_model", os.path.abspath(path)),),
                                controllers.zero_policy, None,
                                "state DAE: while the alarm is up the autopilot flies on a denoising autoencoder's "
                                "estimate of its attacked state; original controller")
