"""The paper's reconstruction (ReconConfig.mode "paper"): the compromised components are the fitted model integrated
open loop from the checkpoint, so on a constant-acceleration trajectory through a constructed model (specific force
constant in the body frame, no angular dynamics) the reconstructed position is the analytic integral, a model bias b
shows as the error b tau^2 / 2 (tau: time since the checkpoint), the uncompromised components stay the EKF's, and the
checkpoint lag covers the detector's delay."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from specguard_jax import ekf as ekf_lib
from specguard_jax.estimation import dynamics as dyn
from specguard_jax.estimation import recon
from specguard_jax.types import SENSOR_NAMES, SensorReadings

DT = 0.02
N_PRE, N_ALARM = 80, 150           # ticks before the alarm (a full ring), ticks with it up; then one hand-back tick
P0, V0 = np.array([1.0, -2.0, 10.0]), np.array([2.0, 0.5, -0.3])
A_TRUE = np.array([0.5, -0.2, 0.3])   # m/s^2, world acceleration of the true trajectory
BIAS = np.array([0.2, -0.1, 0.05])    # m/s^2, the biased model's specific-force error


def _model(acc):
  """DynParams whose specific force is the constant acc - g in the body frame (its bias column), no angular terms."""
  w_lin = np.zeros((3, 18), np.float32)
  w_lin[:, -1] = np.asarray(acc) - np.asarray(dyn.G)
  z = jnp.zeros(3)
  return dyn.DynParams(w_lin=jnp.asarray(w_lin), w_ang=jnp.zeros((3, 18)), rms_lin=z + 0.1, rms_ang=z + 0.01)


def _readings(k):
  f = lambda x: jnp.asarray(x, jnp.float32)
  t = k * DT
  return SensorReadings(gps_pos=f(P0 + V0 * t + 0.5 * A_TRUE * t * t + 50.0 * (k >= N_PRE)),   # spoofed in the alarm
                        gps_vel=f(V0 + A_TRUE * t), gps_fresh=f(k % 5 == 0), gyro=f([0.0, 0.0, 0.0]),
                        accel=f(A_TRUE - np.asarray(dyn.G)), mag_yaw=f(0.0), mag_fresh=f(k % 2 == 0),
                        baro_alt=f(10.0), baro_fresh=f(k % 2 == 0), flow=f([0.0, 0.0]), flow_fresh=f(0.0),
                        odom_speed=f(0.0), odom_fresh=f(0.0))


def _truth(k):
  t = k * DT
  return P0 + V0 * t + 0.5 * A_TRUE * t * t, V0 + A_TRUE * t


@pytest.fixture(scope="module")
def runs():
  """{model name: per-tick (x_rec, x_meas, ReconState, trusted EKFState)} of the GPS blamed for N_ALARM ticks,
  the autopilot's EKF on the true trajectory (what the checkpoint records)."""
  cfg = recon.ReconConfig(n_controls=4, ekf=ekf_lib.EKFConfig.drone(), mode="paper", window=50, lag=10)
  raw = dataclasses.replace(cfg, paper_calibrate=False)
  e0 = ekf_lib.ekf_init(cfg.ekf, _readings(0)).replace(quat=jnp.array([1.0, 0.0, 0.0, 0.0]))   # level, yaw 0
  mask_gps = jnp.zeros(len(SENSOR_NAMES)).at[SENSOR_NAMES.index("gps")].set(1.0)
  u = jnp.full((4,), 3.7)
  out = {}
  for name, acc, c in (("exact", A_TRUE, cfg), ("biased", A_TRUE + BIAS, raw), ("calibrated", A_TRUE + BIAS, cfg)):
    params = _model(acc)

    @jax.jit
    def tick(st, k, alarm, c=c, params=params):
      pos, vel = _truth(k)
      e = e0.replace(pos=jnp.asarray(pos, jnp.float32), vel=jnp.asarray(vel, jnp.float32))
      rd = _readings(k)
      st, x, est, _ = recon.recon_tick(c, params, st, e, rd, u, jnp.where(alarm, mask_gps, 0.0), alarm, DT)
      return st, x, recon.input_vector(e, rd), est

    st = recon.recon_init(cfg, e0)
    rows = []
    for k in range(N_PRE + N_ALARM + 2):
      st, x, xm, est = tick(st, k, jnp.asarray(N_PRE <= k < N_PRE + N_ALARM))
      rows.append(jax.tree.map(np.asarray, (x, xm, st, est)))
    out[name] = rows
  return cfg, out


@pytest.mark.parametrize("name", ["exact", "calibrated"])
def test_exact_model_reconstructs_the_analytic_trajectory(runs, name):
  """The exact model, or the biased one with its offset identified on the trusted entries before the checkpoint."""
  cfg, out = runs
  rows = out[name]
  for k in range(N_PRE, N_PRE + N_ALARM):
    x, xm, st, _ = rows[k]
    pos, vel = _truth(k)
    np.testing.assert_allclose(x[:3], pos, atol=2e-3)        # the spoofed GPS (+50 m) is not used
    np.testing.assert_allclose(x[3:6], vel, atol=1e-3)
    np.testing.assert_allclose(x[6:], xm[6:], atol=1e-6)     # uncompromised components: the EKF's / readings'
  assert float(rows[N_PRE][2].ckpt_age) == pytest.approx((cfg.lag_ticks + 1) * DT)
  for k in range(N_PRE):   # alarm down: x'_t as measured
    np.testing.assert_array_equal(rows[k][0], rows[k][1])


def test_biased_model_drifts_as_its_double_integral(runs):
  _, out = runs
  rows = out["biased"]
  errs, taus = [], []
  for k in range(N_PRE, N_PRE + N_ALARM):
    x, _, st, _ = rows[k]
    pos, vel = _truth(k)
    tau = float(st.ckpt_age)
    np.testing.assert_allclose(x[:3] - pos, 0.5 * BIAS * tau ** 2, atol=3e-3)   # open loop: no sensor pulls it back
    np.testing.assert_allclose(x[3:6] - vel, BIAS * tau, atol=1e-3)
    errs.append(np.linalg.norm(x[:3] - pos))
    taus.append(tau)
  errs, taus = np.array(errs), np.array(taus)
  half = len(taus) // 2
  assert errs[-1] / errs[half] == pytest.approx((taus[-1] / taus[half]) ** 2, rel=0.02)   # ~ t^2


def test_uncertainty_grows_with_time_since_checkpoint(runs):
  _, out = runs
  rows = out["biased"]
  std = np.array([np.asarray(recon.recon_std(rows[k][2])) for k in range(N_PRE, N_PRE + N_ALARM)])
  assert np.all(np.diff(std[:, 0]) > 0) and np.all(np.diff(std[:, 1]) > 0)   # position, velocity
  # ... and covers the uncalibrated model's drift (a 0.2 m/s^2 bias: paper_accel_bias_sigma and the residuals)
  x, _, st, _ = rows[N_PRE + N_ALARM - 1]
  assert std[-1, 0] > np.abs(x[:3] - _truth(N_PRE + N_ALARM - 1)[0]).max()
  # alarm down again: the autopilot EKF's own uncertainty
  d = np.diag(np.asarray(rows[-1][2].shadow.P))
  np.testing.assert_allclose(np.asarray(recon.recon_std(rows[-1][2]))[0], np.sqrt(d[:3].mean()), rtol=1e-5)


def test_hand_back_gives_the_reconstruction_with_fresh_gating(runs):
  _, out = runs
  k = N_PRE + N_ALARM            # the alarm falls on this tick
  x, _, st, est = out["biased"][k]
  assert not bool(st.active)
  np.testing.assert_allclose(est.pos, x[:3])
  assert np.abs(est.pos - _truth(k)[0]).max() > 0.1            # still the model's position, for the re-sync
  assert float(est.gps_pos_age) == 0.0 and float(est.hgt_age) == 0.0
  assert np.diag(est.P)[0] > 10 * np.diag(out["biased"][N_PRE - 1][3].P)[0]   # its grown uncertainty


def test_checkpoint_lag_covers_the_detector_delay():
  cfg = recon.ReconConfig(mode="paper", window=50, lag=10)
  recon.check_lag(cfg, 0.2, DT)
  with pytest.raises(ValueError, match="lag"):
    recon.check_lag(cfg, 0.5, DT)
  with pytest.raises(ValueError, match="mode"):
    recon.ReconConfig(mode="open_loop")
  env = envs.make("drone", detector="oracle", detector_delay=2.5, reconstruction=True, recon_mode="paper")
  assert env.recon_cfg.mode == "paper" and env.recon_cfg.lag_ticks * env.config.tick_dt >= 2.5
  env = envs.make("drone", detector="residual", reconstruction=True, recon_mode="paper")
  assert env.recon_cfg.lag_ticks * env.config.tick_dt >= env.det_cfg.diag_window_s
  assert envs.make("drone", detector="residual", reconstruction=True).recon_cfg == recon.ReconConfig(
      n_controls=4, ekf=env.ekf_cfg)   # fused: the defaults
  with pytest.raises(ValueError, match="recon_mode"):
    envs.make("drone", detector="oracle", reconstruction=True, recon_mode="kalman")
