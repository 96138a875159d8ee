"""Reproduce SpecGuard's appendix table "Effectiveness of State Reconstruction": MSE of position and attitude under
overt GPS and gyroscope attacks, for the EKF (sensor fusion), a denoising autoencoder (sensor denoising) and
selective state reconstruction (specguard_jax/estimation).

Protocols:
  replay (default; open loop): attack-free drone missions are flown by the autopilot in several worlds
    (envs.record); attacks are then applied to the recorded sensor streams and replayed through a fresh EKF, the DAE
    (fed that EKF's input vector) and the reconstruction (alarm = the attack window, i.e. an oracle detector without
    delay; the diagnosis names the attacked sensor). All three are scored against the same true trajectory over the
    attack window.
  closed (closed loop): the attacked missions are flown as DeLorean flies them (envs.record of an env with the
    residual detector and the reconstruction: the autopilot flies on the reconstructed state while the alarm is up,
    its diagnosis picks the components to rebuild); the autopilot's EKF (it keeps fusing every sensor), the DAE on
    that EKF's input vector and the reconstruction are scored against the flown true trajectory over the attacked
    ticks until the mission ends (crash, collision or done).
--recon picks the reconstruction mode(s), estimation.recon.ReconConfig.mode: fused (shadow EKF on the uncompromised
sensors) and / or paper (the fitted model open loop from the checkpoint; the env's checkpoint lag, which covers the
detector's delay, in both protocols). Dynamics model and DAE are trained on separate attack-free missions (the DAE
on their open-loop replay with their own random attacks); the closed protocol's env uses the shipped dynamics model.
Attacks: overt, Table 3 magnitudes (GPS 1-50 m, gyro 0.5-9.47 rad/s, random direction), onset 10-14 s.
MSE: mean over attacked ticks and the 3 components; position in m^2, attitude (roll, pitch, yaw; wrapped) in deg^2.

  python experiments/state_estimation.py --missions 8            # CPU, small
  python experiments/state_estimation.py --missions 1024 --fit-missions 256   # GPU
  python experiments/state_estimation.py --protocol closed --recon fused,paper --missions 256 --fit-missions 128
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
from specguard_jax.autopilot import navigator as nav_lib  # noqa: E402
from specguard_jax.estimation import dae as dae_lib  # noqa: E402
from specguard_jax.estimation import dynamics as dyn  # noqa: E402
from specguard_jax.estimation import recon, traces  # noqa: E402
from specguard_jax.types import RECON_MODES  # noqa: E402

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


def fly_closed(mode, keys, world_ids, scheds, n_ticks, mission):
  """Closed loop (module docstring): (x_ekf, x_rec, x_true [B, T, 15], scored [B, T] bool (attack on and the
  mission not ended), time since onset [B, T] s, alarm [B, T] bool, ended [B] bool (crash / collision before the
  recording's end))."""
  env = envs.make("drone", detector="residual", reconstruction=True, recon_mode=mode, mission=mission)
  tr = envs.record(env, keys, n_ticks, ("truth", "readings", "ekf", "x_rec", "alarm", "attack_on", "alive",
                                        "start_time", "phase"), world_ids=world_ids, attacks=scheds)
  vv = lambda f: jax.jit(jax.vmap(jax.vmap(f)))
  x_ekf = np.asarray(vv(recon.input_vector)(tr["ekf"], tr["readings"]))
  x_true = np.asarray(vv(recon.true_input_vector)(tr["truth"]))
  alive = np.cumprod(np.asarray(tr["alive"]), axis=1).astype(bool)
  scored = np.asarray(tr["attack_on"]) & alive
  since = np.asarray(tr["start_time"]) - np.asarray(scheds.onset)[:, None]
  ended = ~alive[:, -1] & (np.asarray(tr["phase"])[:, -1] != nav_lib.DONE)
  return x_ekf, np.asarray(tr["x_rec"]), x_true, scored, since, np.asarray(tr["alarm"]) > 0, ended


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
  ap.add_argument("--protocol", choices=("replay", "closed"), default="replay",
                  help="replay: open-loop replay with an oracle alarm; closed: flown with the residual detector")
  ap.add_argument("--recon", default="fused", help="comma-separated reconstruction modes: fused, paper")
  ap.add_argument("--json", default="", help="write results here")
  a = ap.parse_args(argv)
  worlds = a.worlds.split(",")
  bad = [w for w in worlds if w not in worlds_lib.PRESET_NAMES]
  if bad:
    ap.error(f"unknown world(s) {', '.join(bad)}; choose from {', '.join(worlds_lib.PRESET_NAMES)}")
  wid = [worlds_lib.PRESET_NAMES.index(w) for w in worlds]
  modes = [m for m in a.recon.split(",") if m]
  if not modes or any(m not in RECON_MODES for m in modes):
    ap.error(f"--recon: choose from {', '.join(RECON_MODES)}")
  mission = MissionConfig.drone(min_duration_s=a.seconds + 10.0, max_duration_s=a.seconds + 60)
  env = envs.make("drone", mission=mission)
  n_ticks = int(round(a.seconds / DT))
  key = jax.random.PRNGKey(a.seed)
  k_fit, k_test, k_att, k_dae = jax.random.split(key, 4)
  t0 = time.time()

  def ids_of(n):
    return jnp.asarray([wid[i % len(wid)] for i in range(n)], jnp.int32)

  def rec(k, n):
    ids = ids_of(n)
    return jax.block_until_ready(envs.record(env, jax.random.split(k, n), n_ticks, traces.RECORD_FIELDS, world_ids=ids))

  fit_tr = rec(k_fit, a.fit_missions)
  test_tr = rec(k_test, a.missions) if a.protocol == "replay" else None
  t_rec = time.time() - t0
  params = dyn.fit_dynamics(fit_tr)
  cfg = recon.ReconConfig()
  evaluate = make_eval(env, cfg, params)   # (the EKF rows and the DAE's training data do not depend on the mode)
  evals = {"fused": evaluate}
  if "paper" in modes:   # the checkpoint lag the env gives an oracle without delay
    pcfg = envs.make("drone", detector="oracle", reconstruction=True, recon_mode="paper").recon_cfg
    evals["paper"] = make_eval(env, pcfg, params)

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

  rows, curves, extra = {}, {}, {}
  bins = np.arange(0.0, a.seconds - 10.0 + 1e-6, 2.0)
  names = ["EKF", "DAE"] + [f"Reconstruction ({m})" for m in modes]
  tot = {m: {"pos": [], "att": []} for m in names}
  for i, s in enumerate(SENSORS):
    sch = sample_schedules(jax.random.fold_in(k_att, i), s, a.missions, a.seconds)
    ests = {}
    for mode in modes:
      if a.protocol == "replay":
        xe, xr, xt, alarm, since = map(np.asarray, evals[mode](test_tr, sch))
        m = alarm.astype(bool)
      else:
        xe, xr, xt, m, since, alarm, ended = fly_closed(mode, jax.random.split(k_test, a.missions),
                                                        ids_of(a.missions), sch, n_ticks, mission)
        extra[f"{s}/{mode}"] = {"scored_ticks": int(m.sum()), "alarm_share": float(alarm[m].mean()),
                                "ended_early": int(ended.sum())}
      # closed loop: each mode flies its own trajectory, so EKF / DAE are per mode; replay: the same for every mode
      suffix = f" ({mode})" if a.protocol == "closed" and len(modes) > 1 else ""
      if a.protocol == "closed" or "EKF" not in ests:
        ests["EKF" + suffix] = (xe, xt, m, since)
        ests["DAE" + suffix] = (np.asarray(dae_lib.dae_apply(dcfg, dparams, jnp.asarray(xe))), xt, m, since)
      ests[f"Reconstruction ({mode})"] = (xr, xt, m, since)
    rows[s], curves[s] = {}, {}
    for name, (x, xt, m, since) in ests.items():
      dp, da = errors(x, xt)
      rows[s][name] = {"pos_mse_m2": float(dp[m].mean()), "att_mse_deg2": float(da[m].mean())}
      tot.setdefault(name, {"pos": [], "att": []})
      tot[name]["pos"].append(dp[m]); tot[name]["att"].append(da[m])
      # |x_rec - x_true| vs time since onset: mean Euclidean position error (m), attitude error norm (deg)
      idx = np.digitize(since[m], bins) - 1
      pe, ae = np.sqrt(dp[m].sum(-1)), np.sqrt(da[m].sum(-1))
      curves[s][name] = [(float(bins[j]), float(pe[idx == j].mean()), float(ae[idx == j].mean()))
                         for j in range(len(bins)) if np.any(idx == j)]
  rows["overall"] = {n: {"pos_mse_m2": float(np.concatenate(v["pos"]).mean()),
                         "att_mse_deg2": float(np.concatenate(v["att"]).mean())} for n, v in tot.items() if v["pos"]}
  t_all = time.time() - t0

  print(f"# state estimation under overt attacks: {a.missions} test missions x {len(SENSORS)} sensors, "
        f"{a.fit_missions} fit missions, worlds {worlds}, {a.seconds:.0f} s flights, backend {jax.default_backend()}")
  print(f"# model residual RMS: specific force {np.round(np.asarray(params.rms_lin), 3)} m/s^2, "
        f"angular acc {np.round(np.asarray(params.rms_ang), 3)} rad/s^2; DAE train loss {float(dloss):.3f}")
  print(f"# time: record {t_rec:.1f} s, fit+DAE {t_train:.1f} s, total {t_all:.1f} s")
  cols = list(rows["overall"])
  print(f"# protocol {a.protocol}, reconstruction mode(s) {', '.join(modes)}")
  print("| attack | metric | " + " | ".join(cols) + " | paper EKF / DAE / SR |")
  print("|---|---|" + "---|" * len(cols) + "---|")
  paper = {"pos_mse_m2": "18.91 / 10.33 / 3.25", "att_mse_deg2": "8.67 / 4.62 / 1.28"}
  for s in list(SENSORS) + ["overall"]:
    for met, label in (("pos_mse_m2", "MSE position (m^2)"), ("att_mse_deg2", "MSE attitude (deg^2)")):
      r = rows[s]
      print(f"| {s} | {label} | " + " | ".join(f"{r[c][met]:.3g}" for c in cols)
            + f" | {paper[met] if s == 'overall' else ''} |")
  for k, v in extra.items():
    print(f"# closed loop {k}: {v['scored_ticks']} scored ticks, alarm up on {100 * v['alarm_share']:.0f} % of them, "
          f"{v['ended_early']} / {a.missions} missions crashed or collided before {a.seconds:.0f} s")
  for s in SENSORS:
    print(f"\n# {s}: mean |x - x_true| vs time since onset (s): position m, attitude deg ({' / '.join(cols)})")
    ref = curves[s][cols[0]]
    for j in range(len(ref)):
      t = ref[j][0]
      at = lambda n, i: next((f"{c[i]:.2f}" for c in curves[s][n] if c[0] == t), "-")
      print(f"  t+{t:4.0f}s  pos {' / '.join(at(n, 1) for n in cols)}   att {' / '.join(at(n, 2) for n in cols)}")
  if a.json:
    with open(a.json, "w") as f:
      json.dump({"rows": rows, "curves": curves, "closed_loop": extra, "args": vars(a)}, f, indent=1)
  return rows


if __name__ == "__main__":
  main()
