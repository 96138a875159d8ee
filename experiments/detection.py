"""Detection benchmark: calibrate the residual CUSUM detector on attack-free missions, then measure it per sensor and
attack profile on missions flown through the real env ticks (sensors -> attack -> EKF -> navigator -> autopilot ->
MJX).

  JAX_PLATFORMS=cpu python experiments/detection.py --missions 4          # CPU, small
  python experiments/detection.py --missions 256 --seconds 90             # GPU

Table columns: n missions; TPR = alarm raised while the attack is on (and none before it); FPR = missions with an
alarm before the onset (the attack-free row: anywhere); delay = s from onset to the first alarm (median, p90);
diag = diagnosis on the first alarm (after the diagnosis window) names the attacked sensor, among detected missions;
mask = the diagnosed mask (detector `mask`, every sensor found compromised) equals the attack's mask exactly, read at
the last alarm tick up to diag_window_s + mask_listen_s after the first alarm (--single-diag: the one-sensor mask);
hit = share of the attacked sensors the mask names; extra = share of missions whose mask names a sensor that was not
attacked (all three among detected missions). The tables below count, per row, the sensor blamed
(`diagnosis`) and each sensor the mask names on those missions (SENSOR_NAMES columns: per-sensor accuracy).
Rows: attack-free, each single sensor, and the sensor pairs PAIRS (both attacked from the same onset, same profile;
--no-pairs / --no-singles leave them out). Attack magnitudes are drawn from the paper's Table 3 ranges
(specguard_jax.attacks.BIAS_RANGES), random direction.

  JAX_PLATFORMS=cpu python experiments/detection.py --stealthy 10         # designed stealthy ramps (calibration.stealthy)

--stealthy S: per sensor, the fastest ramp `stealthy.design_stealthy` finds to stay hidden S s from the calibrated
detector (design missions), then its hidden time and that of a 4x faster ramp on held-out missions (those whose
attack-free twin raised a false alarm left out; hidden times censored at the window S x (1 + margin) + 1 s).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.missions import MissionConfig
from specguard_jax import attacks
from specguard_jax.calibration import stealthy
from specguard_jax.detection import detector as det
from specguard_jax.detection import traces
from specguard_jax.types import SENSOR_NAMES

SENSORS = {"drone": ("gps", "gyro", "accel", "mag", "baro", "flow"),
           "rover": ("gps", "gyro", "accel", "mag", "baro")}
# Two-sensor attacks (issue 52's multi-sensor settings), written "a+b".
PAIRS = {"drone": ("gps+flow", "gps+mag", "gps+baro", "gps+gyro"),
         "rover": ("gps+mag", "gps+baro", "gps+gyro")}


def make_attacks(sensor: str, profile: str, n: int, key, onset: float, duration: float, scale: float = 1.0):
  """n attacks with Table-3 magnitudes, fixed onset/duration (s), ramp 10-30 s when stealthy; `sensor` is one
  sensor or several joined by '+' (all attacked together, same profile)."""
  names = tuple(sensor.split("+"))
  cfg = attacks.AttackConfig(sensors=names, profiles=(profile,), ramp_s=(10.0, 30.0), scale=scale,
                             n_sensors=len(names))
  s = jax.vmap(lambda k: attacks.sample_attack(cfg, k, 100.0))(jax.random.split(key, n))
  return s.replace(onset=jnp.full((n,), onset, jnp.float32), duration=jnp.full((n,), duration, jnp.float32))


def stack_attacks(parts):
  return jax.tree.map(lambda *x: jnp.concatenate(x), *parts)


def free_attacks(n: int):
  return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), attacks.no_attack())


def run(vehicle: str = "drone", missions: int = 4, seconds: float = 60.0, onset: float = 25.0,
        duration: float = 20.0, target_fpr: float = 0.05, n_cal: int | None = None, seed: int = 0,
        batch: int = 64, verbose: bool = True, singles: bool = True, pairs: bool = True, multi: bool = True):
  """Returns (rows: list of dicts, calibrated DetectorConfig)."""
  mc = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      max_duration_s=seconds + 30.0, min_duration_s=seconds)
  env = envs.make(vehicle, mission=mc)
  dt = env.config.tick_dt
  n_ticks = int(round(seconds / dt))
  n_cal = n_cal or max(8, 2 * missions)
  key = jax.random.PRNGKey(seed)

  def record(keys, atk):
    out = []
    for i in range(0, keys.shape[0], batch):
      sl = lambda x: x[i:i + batch]
      out.append(jax.device_get(traces.tick_trace(envs.record(env, keys[i:i + batch], n_ticks, traces.RECORD_FIELDS,
                                                                attacks=jax.tree.map(sl, atk)))))
    return jax.tree.map(lambda *x: np.concatenate(x), *out)

  t0 = time.time()
  k_cal, k_free, k_att, k_bias = jax.random.split(key, 4)
  cal = record(jax.random.split(k_cal, n_cal), free_attacks(n_cal))
  base = det.DetectorConfig.drone() if vehicle == "drone" else det.DetectorConfig.rover()
  r, f = traces.residual_trace(base, cal, dt)
  cfg = dataclasses.replace(det.calibrate(base, r, f, target_fpr), multi_diag=multi)
  if verbose:
    print(f"calibrated on {n_cal} attack-free {vehicle} missions of {seconds:.0f} s ({time.time() - t0:.1f} s)")

  cells = ([("none", "-")] + [(s, p) for s in SENSORS[vehicle] * singles for p in attacks.PROFILES]
           + [(s, p) for s in PAIRS[vehicle] * pairs for p in attacks.PROFILES])
  parts = []
  for i, (s, p) in enumerate(cells):
    if s == "none":
      parts.append(free_attacks(missions))
    else:
      # (keyed by the setting, not its row: adding rows leaves the other rows' attacks as they were)
      parts.append(make_attacks(s, p, missions, jax.random.fold_in(k_bias, _cell_id(vehicle, s, p)), onset,
                                duration))
  atk = stack_attacks(parts)
  n = missions * len(cells)
  tr = record(jax.random.split(k_att, n), atk)
  out = traces.run_detector(cfg, tr, dt)
  win = int(round(cfg.diag_window_s / dt))
  mwin = int(round((cfg.diag_window_s + cfg.mask_listen_s) / dt))
  m = jax.device_get(traces.detection_metrics(out["alarm"], out["diagnosis"], tr, atk, win, out["mask"], mwin))
  true_mask = np.asarray(atk.mask) > 0.5
  any_alarm = np.asarray(jnp.any(out["alarm"] & tr.valid, axis=-1))
  rows = []
  for i, (s, p) in enumerate(cells):
    sl = slice(i * missions, (i + 1) * missions)
    det_ = m["detected"][sl]
    delay = m["delay"][sl][det_]
    row = {"sensor": s, "profile": p, "n": missions,
           "fpr": float(np.mean(any_alarm[sl] if s == "none" else m["false_alarm"][sl])),
           "tpr": float("nan") if s == "none" else float(np.mean(det_)),
           "delay_med": float(np.median(delay)) if delay.size else float("nan"),
           "delay_p90": float(np.percentile(delay, 90)) if delay.size else float("nan"),
           "diag": float(np.mean(m["correct"][sl][det_])) if det_.any() else float("nan"),
           "blamed": blamed_counts(out["alarm"][sl], out["diagnosis"][sl], tr.valid[sl], det_, win)}
    named, truth = m["mask_at"][sl][det_], true_mask[sl][det_]
    row.update(mask=float(np.mean(m["mask_exact"][sl][det_])) if det_.any() else float("nan"),
               hit=float(np.sum(named & truth) / max(1, np.sum(truth))) if det_.any() else float("nan"),
               extra=float(np.mean(np.any(named & ~truth, axis=-1))) if det_.any() else float("nan"),
               named=named.sum(0).astype(int))
    rows.append(row)
  if verbose:
    print(f"{n} test missions in {time.time() - t0:.1f} s total; onset {onset:.0f} s, duration {duration:.0f} s, "
          f"target FPR {target_fpr:.2f}/mission")
    print(format_table(rows))
    print(format_confusion(rows))
    print(format_confusion(rows, "named"))
  return rows, cfg


def _cell_id(vehicle: str, sensor: str, profile: str) -> int:
  """A fixed integer per (sensor setting, profile): the attack draws' key."""
  names = SENSORS[vehicle] + PAIRS[vehicle]
  return 1 + 2 * names.index(sensor) + attacks.PROFILES.index(profile)


def blamed_counts(alarm, diagnosis, valid, detected, win: int):
  """[N_SENSORS] how often each sensor is blamed win ticks after the first alarm, over the `detected` missions."""
  alarm, diagnosis, valid, detected = (np.asarray(x) for x in (alarm, diagnosis, valid, detected))
  first = np.argmax(alarm & valid, axis=-1)
  at = np.minimum(first + win, alarm.shape[-1] - 1)
  d = np.take_along_axis(diagnosis, at[:, None], axis=-1)[:, 0]
  return np.bincount(d[detected & (d >= 0)], minlength=len(SENSOR_NAMES)).astype(int)


STEALTHY_BIAS = {"drone": {"gps": [30.0, 0.0, 0.0], "baro": [-8.0], "mag": [float(np.pi / 2)], "flow": [1.0, 0.0],
                            "gyro": [0.0, 0.0, 0.5], "accel": [0.0, 0.0, -2.0]},
                  "rover": {"gps": [30.0, 0.0, 0.0], "baro": [-8.0], "mag": [float(np.pi / 2)],
                            "gyro": [0.0, 0.0, 0.5], "accel": [2.0, 0.0, 0.0]}}


def stealthy_table(vehicle: str = "drone", hidden_s: float = 10.0, onset: float = 12.0, n_design: int = 8,
                   n_held: int = 24, n_rates: int = 7, margin: float = 0.2, target_fpr: float = 0.05, seed: int = 0,
                   verbose: bool = True):
  """Design a stealthy ramp per sensor (STEALTHY_BIAS) against the detector calibrated on (n_rates + 1) x n_design
  attack-free missions; measure it and a 4x faster ramp on n_held held-out missions. Returns (rows, cfg)."""
  mc = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(max_duration_s=80.0, min_duration_s=50.0)
  env = envs.make(vehicle, mission=mc)
  batch = (n_rates + 1) * n_design
  n_ticks = stealthy.window_ticks(env, onset, hidden_s * (1 + margin) + 1.0)
  t0 = time.time()
  k_cal, k_held = jax.random.split(jax.random.PRNGKey(seed + 1))
  base = det.DetectorConfig.drone() if vehicle == "drone" else det.DetectorConfig.rover()
  r, f, _, _ = stealthy.record_residuals(env, base, jax.random.split(k_cal, batch), free_attacks(batch), n_ticks, batch)
  cfg = det.calibrate(base, r, f, target_fpr)
  keys = jax.random.split(k_held, n_held)
  hid, fa = stealthy.hidden_times(cfg, *stealthy.record_residuals(env, cfg, keys, free_attacks(n_held), n_ticks, batch),
                                 0.0)
  ok = ~fa
  rows = []
  for s, b in STEALTHY_BIAS[vehicle].items():
    d = stealthy.design_stealthy(env, cfg, s, b, hidden_s, onset, n_rates=n_rates, n_missions=n_design, margin=margin,
                                seed=seed, batch=batch)
    row = {"sensor": s, "bias": b, "rate": d.rate, "ramp_s": d.ramp_time, "feasible": d.feasible}
    if d.feasible:
      i = int(np.searchsorted(d.rates, d.rate))
      fast = d.schedule.replace(ramp_time=d.schedule.ramp_time / 4.0)
      sched = jax.tree.map(lambda a, c: jnp.stack([a] * n_held + [c] * n_held), d.schedule, fast)
      h, _ = stealthy.hidden_times(cfg, *stealthy.record_residuals(env, cfg, jnp.concatenate([keys, keys]), sched,
                                                                  n_ticks, batch), onset)
      hd, hf = h[:n_held][ok], h[n_held:][ok]
      row.update(design_min=float(d.hidden[i, ~d.dropped].min()), held_min=float(hd.min()),
                 held_ok=float(np.mean(hd >= hidden_s)), fast_med=float(np.median(hf)), fast_max=float(hf.max()))
    rows.append(row)
  if verbose:
    print(f"{vehicle}: detector calibrated on {batch} attack-free missions (FPR target {target_fpr}); onset "
          f"{onset:.0f} s, hidden_s {hidden_s:.0f} s, margin {margin}, {n_design} design / {int(ok.sum())} held-out "
          f"missions ({int(fa.sum())} with a false alarm left out); {time.time() - t0:.1f} s")
    print(f"{'sensor':7s} {'bias':>18s} {'rate/s':>9s} {'ramp_s':>7s} {'design_min':>10s} {'held_min':>8s} "
          f"{'held_ok':>7s} {'4x_med':>6s} {'4x_max':>6s}")
    for w in rows:
      if not w["feasible"]:
        print(f"{w['sensor']:7s} {str(w['bias']):>18s}  infeasible: no rate in {stealthy.RATE_RANGES[w['sensor']]}")
        continue
      print(f"{w['sensor']:7s} {str([round(x, 2) for x in w['bias']]):>18s} {w['rate']:9.4g} {w['ramp_s']:7.1f} "
            f"{w['design_min']:10.2f} {w['held_min']:8.2f} {w['held_ok']:7.2f} {w['fast_med']:6.2f} "
            f"{w['fast_max']:6.2f}")
  return rows, cfg


def format_table(rows) -> str:
  f = lambda x, d=2: "   -" if x != x else f"{x:.{d}f}"
  lines = [f"{'sensor':9s} {'profile':9s} {'n':>4s} {'TPR':>5s} {'FPR':>5s} {'delay_med':>9s} {'delay_p90':>9s} "
           f"{'diag':>5s} {'mask':>5s} {'hit':>5s} {'extra':>5s}"]
  for r in rows:
    lines.append(f"{r['sensor']:9s} {r['profile']:9s} {r['n']:4d} {f(r['tpr']):>5s} {f(r['fpr']):>5s} "
                 f"{f(r['delay_med'], 2):>9s} {f(r['delay_p90'], 2):>9s} {f(r['diag']):>5s} "
                 f"{f(r.get('mask', float('nan'))):>5s} {f(r.get('hit', float('nan'))):>5s} "
                 f"{f(r.get('extra', float('nan'))):>5s}")
  return "\n".join(lines)


def format_confusion(rows, key: str = "blamed") -> str:
  """Per attacked sensor/profile (rows), counts over the detected missions of each sensor (columns) blamed
  (key 'blamed': the diagnosis) or named by the mask (key 'named')."""
  lines = [f"{key + ':':19s} " + " ".join(f"{n:>5s}" for n in SENSOR_NAMES)]
  for r in rows:
    if r["sensor"] != "none":
      lines.append(f"{r['sensor'] + ' ' + r['profile']:19s} " + " ".join(f"{c:5d}" for c in r[key]))
  return "\n".join(lines)


def main():
  ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  ap.add_argument("--vehicle", default="drone", choices=("drone", "rover"))
  ap.add_argument("--missions", type=int, default=4, help="missions per (sensor, profile) cell")
  ap.add_argument("--seconds", type=float, default=60.0, help="recorded mission length (s)")
  ap.add_argument("--onset", type=float, default=25.0)
  ap.add_argument("--duration", type=float, default=20.0)
  ap.add_argument("--fpr", type=float, default=0.05, help="target false-positive rate per mission")
  ap.add_argument("--cal", type=int, default=None, help="attack-free calibration missions (default max(8, 2N))")
  ap.add_argument("--batch", type=int, default=64)
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--no-pairs", action="store_true", help="leave out the two-sensor rows (PAIRS)")
  ap.add_argument("--no-singles", action="store_true", help="leave out the single-sensor rows")
  ap.add_argument("--single-diag", action="store_true", help="the mask names the diagnosis only (multi_diag off)")
  ap.add_argument("--stealthy", type=float, default=None, metavar="S",
                  help="design stealthy ramps hidden S s per sensor instead (onset: --onset, default 12 s here)")
  a = ap.parse_args()
  if a.stealthy is not None:
    stealthy_table(a.vehicle, a.stealthy, onset=12.0 if a.onset == ap.get_default("onset") else a.onset,
                   target_fpr=a.fpr, seed=a.seed)
    return
  run(a.vehicle, a.missions, a.seconds, a.onset, a.duration, a.fpr, a.cal, a.seed, a.batch,
      singles=not a.no_singles, pairs=not a.no_pairs, multi=not a.single_diag)


if __name__ == "__main__":
  main()
