"""Closed-loop check of the GPS cross-check alarm and the GPS-free reconstruction start (zero policy = DeLorean:
the autopilot flies on the reconstruction; RC + residual detector + reconstruction).

  python bench/gps_xcheck.py [--vehicle drone] --missions 16 --free 128 --seed 7 [--sensors gps,flow] [--no-xcheck]
      [--json OUT]

Per setting (--sensors, stealthy and overt; missions paired across settings: same plan, world and noise, the attack
drawn from the same key), one batched, jitted `lax.scan` of env steps over all missions; prints per setting:
detected, detection delay (s after onset, median / max), diagnosis correct (the sensor blamed 1.2 s after the first
alarm at or after onset), complete, crash (+collision), stall, new spec violation after onset, final horizontal
distance to the last waypoint (m, median / p90), the horizontal reconstruction error at the alarm (|x_rec - truth| m,
median / max over the 5 s after the alarm), the diagnosis sequence of the first alarm after onset (first blamed
sensor; missions where another sensor was blamed at some tick; missions where the reconstruction replaced a gyro /
accelerometer that was not the target; --verbose prints the run-length sequence, --evidence the diagnosis evidence
peak / cpeak / xpeak 0.1 s and 1.2 s after the alarm) and the attack-free false alarms (missions with any alarm).
--no-xcheck: the residual CUSUM alone raises the alarm (DetectorConfig(xcheck=False)); the reconstruction still
starts from the dead-reckoned position when the GPS is blamed. --baseline: neither (for code before the cross-check;
run from that checkout).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import rollout
from specguard_jax import attacks
from specguard_jax import detection

WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")
SENSORS = ("gps", "flow")


def _seq(d, names):
  """Run-length string of a diagnosis sequence (env steps of 0.1 s), e.g. 'accel x3 > gyro x40'."""
  out, prev, n = [], None, 0
  for x in list(d) + [None]:
    if x == prev:
      n += 1
      continue
    if prev is not None:
      out.append(f"{names[int(prev)] if prev >= 0 else '-'} x{n}")
    prev, n = x, 1
  return " > ".join(out)


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  ap.add_argument("--missions", type=int, default=16, help="missions per attack setting")
  ap.add_argument("--free", type=int, default=128, help="attack-free missions (false alarms)")
  ap.add_argument("--seconds", type=float, default=130.0)
  ap.add_argument("--seed", type=int, default=7)
  ap.add_argument("--no-xcheck", action="store_true")
  ap.add_argument("--baseline", action="store_true", help="code before the cross-check (no xcheck field)")
  ap.add_argument("--json", default="")
  ap.add_argument("--verbose", action="store_true", help="one line per attacked mission")
  ap.add_argument("--evidence", action="store_true", help="with --verbose: the diagnosis evidence at the alarm")
  ap.add_argument("--sensors", default=",".join(SENSORS), help="attacked sensors, stealthy and overt each")
  a = ap.parse_args(argv)
  if a.missions < 1 or a.free < 0 or a.seconds <= 0:
    ap.error("--missions >= 1, --free >= 0, --seconds > 0")
  sensors = tuple(x for x in a.sensors.split(",") if x)
  bad = [x for x in sensors if x not in attacks.SENSOR_NAMES]
  if bad or not sensors:
    ap.error(f"unknown or no sensor(s) {bad}; choose from {', '.join(attacks.SENSOR_NAMES)}")
  SETTINGS = tuple((x, p) for x in sensors for p in ("stealthy", "overt"))
  kw = dict(worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5, reconstruction=True,
            override_residual=True, override_frame="body")
  if a.no_xcheck and not a.baseline:
    kw["detector_config"] = getattr(detection.DetectorConfig, a.vehicle)(xcheck=False)
  env = envs.make(a.vehicle, **kw)
  n, T = a.missions, int(round(a.seconds / env.dt))
  keys = jax.random.split(jax.random.PRNGKey(a.seed), max(n, a.free))
  rows = [(s, p, j) for s, p in SETTINGS for j in range(n)] + [(None, None, j) for j in range(a.free)]

  def one(key, si):
    return rollout.draw_paired_episode(env, key, SETTINGS + (None,), si)

  @jax.jit
  def run(keys, sid):
    s = jax.vmap(one)(keys, sid)
    B = keys.shape[0]

    def body(s, _):
      nx = jax.vmap(env.step)(s, jnp.zeros((B, 3)))
      nx = jax.tree.map(lambda x, y: jnp.where(jnp.reshape(s.done > 0, s.done.shape + (1,) * (x.ndim - 1)), y, x),
                        nx, s)
      sim = nx.info["sim"]
      rec = dict(alarm=nx.info["alarm"] > 0, diag=nx.info["diagnosis"], t=nx.info["time"], done=nx.done > 0,
                 viol=nx.info["spec_robustness"] < 0,
                 rec_err=jnp.linalg.norm(sim["x_rec"][:, :2] - sim["truth"].pos[:, :2], axis=-1),
                 blamed=sim["recon"].blamed > 0.5, peak=sim["det"].peak, cpeak=sim["det"].cpeak,
                 xpeak=sim["det"].xpeak, xraised=sim["det"].xraised)
      return nx, rec

    s, recs = jax.lax.scan(body, s, None, length=T)
    m = s.info["mission"]
    last = jnp.take_along_axis(m.waypoints, (m.n_waypoints - 1)[:, None, None], axis=1)[:, 0]
    fin = jnp.linalg.norm(s.info["sim"]["truth"].pos[:, :2] - last[:, :2], axis=-1)
    return recs, s.info["episode"], s.info["attack"], fin

  sid = np.array([len(SETTINGS) if s is None else SETTINGS.index((s, p)) for s, p, _ in rows], np.int32)
  kk = keys[np.array([j for _, _, j in rows])]
  t0 = time.time()
  recs, ep, atk, fin = jax.device_get(run(kk, jnp.asarray(sid)))
  wall = time.time() - t0
  names = list(attacks.SENSOR_NAMES)
  out = {"wall_s": wall, "settings": {}}
  print(f"{len(rows)} missions x {T} steps in {wall:.1f} s (compile included); xcheck "
        f"{'off' if a.no_xcheck or a.baseline else 'on'}")
  print("| setting | detected | delay s (med / max) | diagnosis correct | complete | crash (+coll) | stall | "
        "new violation after onset | final dist m (med / p90) | recon err 5 s after alarm m (med / max) | "
        "recon err whole alarm m (med / max) | first blame | other sensor blamed in the 1st alarm | "
        "other IMU sensor replaced |")
  print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
  for si, (s, p) in enumerate(list(SETTINGS) + [(None, None)]):
    idx = np.flatnonzero(sid == si)
    t = recs["t"][:, idx]
    onset = atk.onset[idx]
    alarm = recs["alarm"][:, idx]
    det, delay, diag_ok, viol_new, err, err_all = [], [], [], [], [], []
    first_blame, wrong_any, wrong_imu = [], [], []
    for c, i in enumerate(idx):
      after = alarm[:, c] & (t[:, c] >= onset[c])
      if s is None:
        det.append(bool(alarm[:, c].any()))
        continue
      hit = after.any()
      det.append(bool(hit))
      v = recs["viol"][:, i]
      first = np.where(v.any(0), t[np.argmax(v, 0), c], np.inf)
      viol_new.append(bool(np.any(v.any(0) & (first >= onset[c]))))
      if hit:
        k = int(np.argmax(after))
        delay.append(float(t[k, c] - onset[c]))
        diag_ok.append(int(recs["diag"][min(k + 12, len(t) - 1), i]) == names.index(s))
        err.append(float(np.max(recs["rec_err"][k:k + 50, i])))
        span = alarm[:, c] & (t[:, c] >= t[k, c]) & ~recs["done"][:, i]
        err_all.append(float(np.max(recs["rec_err"][span, i])) if span.any() else 0.0)
        # the diagnosis sequence over this alarm (env steps of 0.1 s): first blame, any other sensor blamed, and a
        # gyro / accelerometer that is not the target replaced by the reconstruction (`blamed` mask)
        end = k + int(np.argmax(~alarm[k:, c])) if (~alarm[k:, c]).any() else len(t)
        dseq = recs["diag"][k:end, i]
        first_blame.append(names[int(dseq[0])])
        wrong_any.append(bool(np.any((dseq >= 0) & (dseq != names.index(s)))))
        bl = recs["blamed"][k:end, i]
        wrong_imu.append(bool(any(bl[:, names.index(x)].any() for x in ("gyro", "accel") if x != s)))
      if a.verbose:
        b = atk.bias[i][names.index(s)]
        late = [(env.spec_names[j], round(float(first[j]), 1)) for j in range(len(first))
                if np.isfinite(first[j]) and first[j] >= onset[c]]
        print(f"  {s} {p} #{c:2d}: onset {onset[c]:5.1f} |b| {np.linalg.norm(b):5.1f} ramp {atk.ramp_time[i]:4.1f} "
              f"dur {atk.duration[i]:4.1f} delay {delay[-1] if hit else float('nan'):5.1f} "
              f"diag {names[int(recs['diag'][min(k + 12, len(t) - 1), i])] if hit else '-'} "
              f"first {first_blame[-1] if hit else '-'} seq {_seq(recs['diag'][k:end, i], names) if hit else '-'} "
              f"complete {int(ep['complete'][i])} crash {int(ep['crash'][i])} "
              f"final {fin[i]:6.1f} m rec_err {err[-1] if hit else float('nan'):5.1f} "
              f"(whole alarm {err_all[-1] if hit else float('nan'):5.1f}) "
              f"new violations {late}")
        if hit and a.evidence:
          print(f"      at alarm +0.1 s: peak {np.round(recs['peak'][k + 1, i], 2).tolist()} cpeak "
                f"{np.round(recs['cpeak'][k + 1, i], 2).tolist()} xpeak {np.round(recs['xpeak'][k + 1, i], 2).tolist()} "
                f"xraised {bool(recs['xraised'][k + 1, i])}; at +1.2 s: peak "
                f"{np.round(recs['peak'][min(k + 12, len(t) - 1), i], 2).tolist()} cpeak "
                f"{np.round(recs['cpeak'][min(k + 12, len(t) - 1), i], 2).tolist()} xpeak "
                f"{np.round(recs['xpeak'][min(k + 12, len(t) - 1), i], 2).tolist()}")
    row = {"missions": int(len(idx)), "detected": int(np.sum(det))}
    if s is not None:
      row.update(delay_med=float(np.median(delay)) if delay else None, delay_max=float(np.max(delay)) if delay else None,
                 diag_ok=int(np.sum(diag_ok)), complete=int(ep["complete"][idx].sum()),
                 crash=int(ep["crash"][idx].sum()), collision=int(ep["collision"][idx].sum()),
                 stall=int(ep["stall"][idx].sum()), new_violation=int(np.sum(viol_new)),
                 final_dist_med=float(np.median(fin[idx])), final_dist_p90=float(np.percentile(fin[idx], 90)),
                 rec_err_med=float(np.median(err)) if err else None, rec_err_max=float(np.max(err)) if err else None,
                 rec_err_alarm_med=float(np.median(err_all)) if err_all else None,
                 rec_err_alarm_max=float(np.max(err_all)) if err_all else None,
                 first_blame={x: first_blame.count(x) for x in sorted(set(first_blame))},
                 wrong_blame_any=int(np.sum(wrong_any)), wrong_imu_replaced=int(np.sum(wrong_imu)))
      f = lambda x: "-" if x is None else f"{x:.1f}"
      print(f"| {s} {p} | {row['detected']}/{len(idx)} | {f(row['delay_med'])} / {f(row['delay_max'])} | "
            f"{row['diag_ok']}/{row['detected']} | {row['complete']} | {row['crash']} (+{row['collision']}) | "
            f"{row['stall']} | {row['new_violation']} | {row['final_dist_med']:.1f} / {row['final_dist_p90']:.1f} | "
            f"{f(row['rec_err_med'])} / {f(row['rec_err_max'])} | {f(row['rec_err_alarm_med'])} / "
            f"{f(row['rec_err_alarm_max'])} | {row['first_blame']} | {row['wrong_blame_any']} | "
            f"{row['wrong_imu_replaced']} |")
    else:
      row.update(complete=int(ep["complete"][idx].sum()))
      print(f"| attack-free | false alarms {row['detected']}/{len(idx)} | | | {row['complete']} | | | | | | |")
    out["settings"][f"{s}/{p}" if s else "attack_free"] = row
  if a.json:
    with open(a.json, "w") as fh:
      json.dump(out, fh, indent=1)


if __name__ == "__main__":
  main()
