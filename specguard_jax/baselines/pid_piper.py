"""PID-Piper baseline (Dash et al., DSN 2021): a feed-forward controller (FFC) trained to predict the autopilot's PID
output on attack-free flights, switched in by PID-Piper's own monitor when the FFC and the PID disagree.

The FFC (specguard_jax.estimation.ffc: an LSTM over the last WINDOW ticks of sensor readings, estimate and the plan's
leg velocity) predicts the PX4 velocity PID's output, the acceleration setpoint [3] that the attitude loop turns into
attitude and thrust; deployed with EnvConfig.recovery_estimator='ffc' (its output replaces the PID's at the attitude
loop while the monitor is up), no state reconstruction. Data: attack-free autopilot flights (common.flights); the
PID's output is replayed exactly from the recorded velocity setpoints and EKF velocities (`pid_outputs`). Trained on
the first 4/5 of the missions; the held-out RMSE against the spread of the PID's outputs is in the cache's meta, and
so is the monitor's calibration (`calibrate_monitor`). Drone only.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax import controllers
from specguard_jax import math3d
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.autopilot import px4
from specguard_jax.baselines import common
from specguard_jax.estimation import ffc as ffc_lib


INPUT_NOISE = 0.1   # standard deviations of the standardised inputs (fit_ffc)
STD_FLOOR = 0.1     # added to each input's standard deviation (fit_ffc)


@functools.partial(jax.jit, static_argnames=("p", "dt"))
def pid_outputs(p: px4.MulticopterParams, vel_sp, vel, dt: float):
  """The velocity PID's acceleration setpoints [B, T, 3] (m/s^2) replayed from the velocity setpoints vel_sp and the
  EKF velocities vel [B, T, 3] it was given, from a zero controller state (as at reset; armed throughout)."""
  def one(vs, v):
    def tick(cs, x):
      acc, cs = px4.velocity_control(p, cs, x[0], x[1], dt)
      return cs, acc
    return jax.lax.scan(tick, px4.MCControlState.zeros(), (vs, v))[1]
  return jax.vmap(one)(vel_sp, vel)


def samples(env, tr):
  """(features [B, T, N_FEAT], targets [B, T, 3] heading-frame PID outputs, yaw [B, T], mask [B, T] cruise/loiter,
  world PID outputs [B, T, 3]) of common.flights traces."""
  ekf = tr["ekf"]
  eul = jax.vmap(jax.vmap(math3d.quat_to_euler))(ekf["quat"])
  acc = pid_outputs(env.mc_params, tr["vel_nav"], ekf["vel"], float(env.config.tick_dt))
  rd = tr["readings"]
  ph = tr["phase"]
  feats = ffc_lib.tick_features(ffc_lib.plan_target(tr["leg_vel"], ph), ekf["vel"], eul, rd.gyro, rd.accel)
  targets = ffc_lib.heading_turn(acc, eul[..., 2])
  mask = (ph == nav_lib.CRUISE) | (ph == nav_lib.LOITER)
  return feats, targets, eul[..., 2], mask, acc


def windows(feats, rows):
  """Feature windows [N, WINDOW, N_FEAT] ending at the flat rows [N] of feats [B, T, n] (a mission's first tick
  repeated before its start, as the in-tick window starts)."""
  b, t, n = feats.shape
  m, i = rows // t, rows % t
  idx = jnp.maximum(i[:, None] - jnp.arange(ffc_lib.WINDOW - 1, -1, -1)[None], 0)
  return feats[m[:, None], idx]


@functools.partial(jax.jit, static_argnames=("steps", "batch"))
def fit_ffc(feats, targets, mask, key, steps: int, batch: int, lr: float = 2e-3, noise: float = INPUT_NOISE,
            std_floor: float = STD_FLOOR):
  """Fit the FFC on the missions of feats [B, T, n] / targets [B, T, 3] where mask [B, T]: Adam (common.adam_fit) on
  the standardised MSE, Gaussian noise of `noise` standard deviations added to each standardised input window (a
  regulariser: a few training missions are otherwise memorised). Each input's scale is its standard deviation plus
  std_floor (in its own unit: m/s, rad, rad/s, m/s^2), so an input that hardly varies in cruise (the vertical
  setpoint) cannot blow up on a mission that moves it. Returns (params for ffc.ffc_apply, losses)."""
  n = feats.shape[-1]
  w = mask.reshape(-1).astype(jnp.float32)
  ws = jnp.maximum(jnp.sum(w), 1.0)
  ff, yf = feats.reshape(-1, n), targets.reshape(-1, 3)
  x_mean = jnp.sum(ff * w[:, None], 0) / ws
  x_std = jnp.sqrt(jnp.sum((ff - x_mean) ** 2 * w[:, None], 0) / ws) + std_floor
  y_mean = jnp.sum(yf * w[:, None], 0) / ws
  y_std = jnp.sqrt(jnp.sum((yf - y_mean) ** 2 * w[:, None], 0) / ws) + 1e-3
  net = ffc_lib.FFCNet(ffc_lib.HIDDEN)
  k_init, k_fit = jax.random.split(key)
  p0 = net.init(k_init, jnp.zeros((1, ffc_lib.WINDOW, n)))

  def loss_fn(p, idx, k):
    x = (windows(feats, idx) - x_mean) / x_std
    x = x + noise * jax.random.normal(k, x.shape)
    return jnp.mean((net.apply(p, x) - (yf[idx] - y_mean) / y_std) ** 2)

  p, losses = common.adam_fit(loss_fn, p0, w, steps, batch, k_fit, lr)
  return {"net": p, "x_mean": x_mean, "x_std": x_std, "y_mean": y_mean, "y_std": y_std}, losses


@jax.jit
def predict(params, feats, yaw):
  """FFC outputs [B, T, 3] (world m/s^2) at every tick of feats [B, T, n], yaw [B, T]."""
  b, t, _ = feats.shape
  rows = jnp.arange(b * t)
  out = jax.lax.map(lambda r: ffc_lib.ffc_apply(params, windows(feats, r), yaw.reshape(-1)[r]),
                    rows.reshape(-1, t))
  return out.reshape(b, t, 3)


def calibrate_monitor(deviation, mask, quantile: float = 0.999, peak_quantile: float = 0.95,
                      factor: float = 2.0) -> ffc_lib.MonitorConfig:
  """PID-Piper's CUSUM from attack-free deviations |a_ffc - a_pid| [B, T] (m/s^2) in scope (mask): drift = their
  `quantile` (the 99th percentile let evaluation missions longer than the calibration flights switch the FFC in
  attack-free: 3 of 24 at `ci`); threshold = `factor` x the `peak_quantile` quantile of the largest sum each
  attack-free mission reaches, and at least 25 x drift (half a second of deviation twice the drift). A quantile of
  per-mission peaks, not their maximum: the maximum over missions grows with how many are flown (an extreme value),
  so the monitor would go deafer the more data calibrated it."""
  d = np.asarray(deviation, np.float64)
  m = np.asarray(mask, bool)
  drift = float(np.quantile(d[m], quantile))
  s, peaks = np.zeros(d.shape[0]), np.zeros(d.shape[0])
  for t in range(d.shape[1]):   # offline calibration: the CUSUM of every mission at once, numpy over ticks
    s = np.where(m[:, t], np.maximum(0.0, s + d[:, t] - drift), 0.0)
    peaks = np.maximum(peaks, s)
  peak = float(np.quantile(peaks, peak_quantile))
  return ffc_lib.MonitorConfig(drift=drift, threshold=max(factor * peak, 25.0 * drift))


def fit(env, tr, steps: int, batch: int, key):
  """(params, meta): train on the first 4/5 of the missions (at least one held out); held-out RMSE (m/s^2) against
  the spread of the PID's outputs, the loss curve and the monitor's calibration on all missions."""
  feats, targets, yaw, mask, acc = samples(env, tr)
  b = feats.shape[0]
  n_train = b - max(1, b // 5) if b > 1 else 1
  params, losses = fit_ffc(feats[:n_train], targets[:n_train], mask[:n_train], key, steps, batch)
  pred = np.asarray(predict(params, feats, yaw))
  acc, m = np.asarray(acc), np.asarray(mask)
  dev = np.linalg.norm(pred - acc, axis=-1)
  te = m[n_train:]
  err = dev[n_train:][te]
  spread = np.linalg.norm(acc[n_train:][te] - acc[n_train:][te].mean(0), axis=-1)
  mon = calibrate_monitor(dev, m)
  meta = {"heldout_rmse_m_s2": float(np.sqrt(np.mean(err ** 2))),
          "heldout_pid_rms_m_s2": float(np.sqrt(np.mean(spread ** 2))), "heldout_ticks": int(te.sum()),
          "train_ticks": int(m[:n_train].sum()), "final_loss": float(np.asarray(losses)[-50:].mean()),
          "loss_curve": common.loss_curve(losses), "monitor_drift": mon.drift, "monitor_threshold": mon.threshold,
          "window": ffc_lib.WINDOW, "hidden": ffc_lib.HIDDEN, "inputs": ffc_lib.INPUTS}
  return params, meta


def env_overrides(path: str) -> tuple:
  return (("control_mode", "autopilot"), ("detector", "residual"), ("detector_delay", 0.0),
          ("reconstruction", False), ("recovery_estimator", "ffc"), ("recovery_model", os.path.abspath(path)))


def build(ctx):
  """Controller 'pid_piper': fit (or load from ctx.cache_dir) the FFC; it flies while its monitor is up."""
  if ctx.vehicle != "drone":
    raise controllers.NotAvailable("PID-Piper acts at the multicopter's attitude loop: drone only")
  path = common.cache_path(ctx, "pid_piper", "msgpack")
  if not os.path.exists(path):
    b = common.budget(ctx.train_budget)
    env, tr = common.flights(ctx.vehicle, tuple(ctx.worlds), ctx.train_budget, ctx.seed)
    params, meta = fit(env, tr, b.fit_steps, b.batch, jax.random.fold_in(jax.random.PRNGKey(ctx.seed), 0xFFC))
    common.save_tree(path, params, {"baseline": "pid_piper", "vehicle": ctx.vehicle, "budget": ctx.train_budget,
                                    "seed": ctx.seed, **meta})
  _, meta = common.load_tree(path)
  ffc_lib.load_ffc(path)   # one-line ValueError on a corrupt cache
  return controllers.Controller("pid_piper", env_overrides(path), controllers.zero_policy, None,
                                f"PID-Piper: an LSTM feed-forward controller (held-out RMSE "
                                f"{meta.get('heldout_rmse_m_s2', float('nan')):.2f} m/s^2) replaces the velocity "
                                f"PID's acceleration setpoint while its CUSUM monitor is up")
