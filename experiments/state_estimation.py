"""Reproduce SpecGuard's appendix table "Effectiveness of State Reconstruction": MSE of position and attitude under
overt GPS and gyroscope attacks, for the EKF (sensor fusion), a denoising autoencoder (sensor denoising) and
selective state reconstruction (specguard_jax/estimation).

Protocol (open-loop replay): attack-free drone missions are flown by the autopilot in several worlds
(envs.record); attacks are then applied to the recorded sensor streams and replayed through a fresh EKF, the DAE
(fed that EKF's input vector) and the reconstruction (alarm = the attack window, i.e. an oracle detector without
delay; the diagnosis names the attacked sensor). All three are scored against the same true trajectory over the
attack window. Dynamics model and DAE are trained on separate missions (with their own random attacks for the DAE).
Attacks: overt, Table 3 magnitudes (GPS 1-50 m, gyro 0.5-9.47 rad/s, random direction), onset 10-14 s.
MSE: mean over attacked ticks and the 3 components; position in m^2, attitude (roll, pitch, yaw; wrapped) in deg^2.

  python experiments/state_estimation.py --missions 8            # CPU, small
  python experiments/state_estimation.py --missions 1024 --fit-missions 256   # GPU
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402
from envs import worlds as worlds_lib  # noqa: E402
from envs.missions import MissionConfig  # noqa: E402
from specguard_jax import attacks  # noqa: E402
from specguard_jax.estimation import dae as dae_lib  # noqa: E402
from specguard_jax.estimation import dynamics as dyn  # noqa: E402
from specguard_jax.estimation import recon, traces  # noqa: E402

DT = 0.02
SENSORS = ("gps", "gyro")


def sample_schedules(key, sensor, n, t_end):
  """n overt single-sensor attacks (batched AttackSchedule) with Table 3 magnitudes, onset 10-14 s, to t_end."""
  cfg = attacks.AttackConfig(sensors=(sensor,), profiles=("overt",))
  k1, k2 = jax.random.split(key)
  s = jax.vmap(lambda k: attacks.sample_attack(cfg, k, jnp.asarray(60.0)))(jax.random.split(k1, n))
  onset = jax.random.uniform(k2, (n,), minval=10.0, maxval=14.0)
  return s.replace(onset=onset, duration=t_end - onset)


def make_eval(env, cfg, params):
  @jax.jit
  def evaluate(tr, scheds):
    def one(t, sched):
      xe, xr, xt, alarm = recon.replay_under_attack(cfg, params, env.ekf_cfg, t, sched, DT)
      return xe, xr, xt, alarm, t["time"] - sched.onset
    return jax.vmap(one)(tr, scheds)
  return evaluate


def errors(x, xt):
  """(squared position error [.., 3] m^2, squared attitude error [.., 3] deg^2)."""
  dp = (x[..., :3] - xt[..., :3]) ** 2
  da = np.rad2deg(np.arctan2(np.sin(x[..., 9:12] - xt[..., 9:12]), np.cos(x[..., 9:12] - xt[..., 9:12]))) ** 2
  return dp, da


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--missions", type=int, default=8, help="test missions (per attacked sensor)")
  ap.add_argument("--fit-missions", type=int, default=8, help="missions for the dynamics fit and DAE training")
  ap.add_argument("--worlds", default="suburban_residential,urban_city_streets,urban_park,open_mountain",
                  help="comma-separated world preset names")
  ap.add_argument("--seconds", type=float, default=40.0, help="recorded flight per mission (s)")
  ap.add_argument("--dae-steps", type=int, default=3000)
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--json", default="", help="write results here")
  a = ap.parse_args(argv)
  worlds = a.worlds.split(",")
  bad = [w for w in worlds if w not in worlds_lib.PRESET_NAMES]
  if bad:
    ap.error(f"unknown world(s) {', '.join(bad)}; choose from {', '.join(worlds_lib.PRESET_NAMES)}")
  wid = [worlds_lib.PRESET_NAMES.index(w) for w in worlds]
  env = envs.make("drone", mission=MissionConfig.drone(min_duration_s=a.seconds + 10.0, max_duration_s=a.seconds + 60))
  n_ticks = int(round(a.seconds / DT))
  key = jax.random.PRNGKey(a.seed)
  k_fit, k_test, k_att, k_dae = jax.random.split(key, 4)
  t0 = time.time()

  def rec(k, n):
    ids = jnp.asarray([wid[i % len(wid)] for i in range(n)], jnp.int32)
    return jax.block_until_ready(envs.record(env, jax.random.split(k, n), n_ticks, traces.RECORD_FIELDS, world_ids=ids))

  fit_tr = rec(k_fit, a.fit_missions)
  test_tr = rec(k_test, a.missions)
  t_rec = time.time() - t0
  params = dyn.fit_dynamics(fit_tr)
  cfg = recon.ReconConfig()
  evaluate = make_eval(env, cfg, params)

  # DAE: train on attacked/clean pairs of the fit missions (both sensors, attack windows + some clean ticks).
  xs, ys = [], []
  for i, s in enumerate(SENSORS):
    sch = sample_schedules(jax.random.fold_in(k_dae, i), s, a.fit_missions, a.seconds)
    xe, _, xt, alarm, _ = map(np.asarray, evaluate(fit_tr, sch))
    keep = alarm.astype(bool) | (np.random.default_rng(i).random(alarm.shape) < 0.2)
    xs.append(xe[keep]); ys.append(xt[keep])
  dcfg = dae_lib.DAEConfig(steps=a.dae_steps)
  dparams, dloss = dae_lib.train_dae(dcfg, jnp.asarray(np.concatenate(xs)), jnp.asarray(np.concatenate(ys)), k_dae)
  t_train = time.time() - t0 - t_rec

  rows, curves = {}, {}
  bins = np.arange(0.0, a.seconds - 10.0 + 1e-6, 2.0)
  tot = {m: {"pos": [], "att": []} for m in ("EKF", "DAE", "Reconstruction")}
  for i, s in enumerate(SENSORS):
    sch = sample_schedules(jax.random.fold_in(k_att, i), s, a.missions, a.seconds)
    xe, xr, xt, alarm, since = map(np.asarray, evaluate(test_tr, sch))
    xd = np.asarray(dae_lib.dae_apply(dcfg, dparams, jnp.asarray(xe)))
    m = alarm.astype(bool)
    rows[s], curves[s] = {}, {}
    for name, x in (("EKF", xe), ("DAE", xd), ("Reconstruction", xr)):
      dp, da = errors(x, xt)
      rows[s][name] = {"pos_mse_m2": float(dp[m].mean()), "att_mse_deg2": float(da[m].mean())}
      tot[name]["pos"].append(dp[m]); tot[name]["att"].append(da[m])
      # |x_rec - x_true| vs time since onset: mean Euclidean position error (m), attitude error norm (deg)
      idx = np.digitize(since[m], bins) - 1
      pe, ae = np.sqrt(dp[m].sum(-1)), np.sqrt(da[m].sum(-1))
      curves[s][name] = [(float(bins[j]), float(pe[idx == j].mean()), float(ae[idx == j].mean()))
                         for j in range(len(bins)) if np.any(idx == j)]
  rows["overall"] = {n: {"pos_mse_m2": float(np.concatenate(v["pos"]).mean()),
                         "att_mse_deg2": float(np.concatenate(v["att"]).mean())} for n, v in tot.items()}
  t_all = time.time() - t0

  print(f"# state estimation under overt attacks: {a.missions} test missions x {len(SENSORS)} sensors, "
        f"{a.fit_missions} fit missions, worlds {worlds}, {a.seconds:.0f} s flights, backend {jax.default_backend()}")
  print(f"# model residual RMS: specific force {np.round(np.asarray(params.rms_lin), 3)} m/s^2, "
        f"angular acc {np.round(np.asarray(params.rms_ang), 3)} rad/s^2; DAE train loss {float(dloss):.3f}")
  print(f"# time: record {t_rec:.1f} s, fit+DAE {t_train:.1f} s, total {t_all:.1f} s")
  print("| attack | metric | EKF (sensor fusion) | DAE (denoising) | Reconstruction | paper EKF / DAE / SR |")
  print("|---|---|---|---|---|---|")
  paper = {"pos_mse_m2": "18.91 / 10.33 / 3.25", "att_mse_deg2": "8.67 / 4.62 / 1.28"}
  for s in list(SENSORS) + ["overall"]:
    for met, label in (("pos_mse_m2", "MSE position (m^2)"), ("att_mse_deg2", "MSE attitude (deg^2)")):
      r = rows[s]
      print(f"| {s} | {label} | {r['EKF'][met]:.3g} | {r['DAE'][met]:.3g} | {r['Reconstruction'][met]:.3g} | "
            f"{paper[met] if s == 'overall' else ''} |")
  for s in SENSORS:
    print(f"\n# {s}: mean |x - x_true| vs time since onset (s): position m (EKF / DAE / Rec), attitude deg (same)")
    for j in range(len(curves[s]["EKF"])):
      t = curves[s]["EKF"][j][0]
      p = " / ".join(f"{curves[s][n][j][1]:.2f}" for n in ("EKF", "DAE", "Reconstruction"))
      q = " / ".join(f"{curves[s][n][j][2]:.2f}" for n in ("EKF", "DAE", "Reconstruction"))
      print(f"  t+{t:4.0f}s  pos {p}   att {q}")
  if a.json:
    with open(a.json, "w") as f:
      json.dump({"rows": rows, "curves": curves, "args": vars(a)}, f, indent=1)
  return rows


if __name__ == "__main__":
  main()
