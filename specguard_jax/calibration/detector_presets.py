"""Calibrate the residual detector's shipped presets (assets/detector_<vehicle>.json) on attack-free missions.

`python tools/calibrate_detector.py --vehicle drone --missions 1024` (and rover) flies `missions` attack-free missions
(MissionConfig of the vehicle, nominal length `--mission-s`, flown whole: `--seconds` covers the longest), worlds
CAL_WORLDS round robin, domain randomisation on, through the env's own ticks (envs.record), and runs
`detection.calibrate` for `--target-fpr` false alarms per mission (seeded; the file records the seed, missions,
worlds, mission lengths, target and in-sample statistics).

The shipped recipe: 1024 missions of 60-120 s nominal flown whole (135 s recorded), all 10 worlds, target 0.01 false
alarms per mission, calibrate's defaults (scale = 0.999 quantile of |r|, h = 3 x the per-mission CUSUM maximum at the
1 - 0.01 / n_channels quantile, here the sample maximum). The IMU-model thresholds come out high (heavy-tailed
residuals in manoeuvres), so a 3 m/s^2 accel-z bias is caught through the GPS channels first and blamed on the GPS; a
smaller --h-margin trades that against margin.
GPS cross-checks: dr_h, vel_h, hgt_h = --xcheck-margin (1.2) x the sample maximum of each mission's largest
|GPS - dead reckoning| (1 s EMA), velocity chi and |GPS height - baro| (3 s EMA) over the same missions; the rover has
no height check (hgt_h 0: off). Multi-sensor diagnosis: mask_h [6] = max(mask_h_min, mask_margin x the sensor's
largest attack-free score at the same quantile) (detection.calibrate, `mask_thresholds`). Each file's 'meta' records
how it was made.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import worlds as worlds_lib
from envs.missions import MissionConfig
from specguard_jax import attacks
from specguard_jax.detection import detector as det
from specguard_jax.detection import preset_file
from specguard_jax.detection import traces
from specguard_jax.types import VEHICLES

# The trainer's worlds (specguard_jax.ppo.config) first, then the other presets: the preset holds in all of them.
CAL_WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain", "suburban_streets",
              "urban_city_areas", "urban_green_areas", "urban_high_rise", "manufacturing_plant", "open_beach")


def record_free(env, base: det.DetectorConfig, keys, world_ids, n_ticks: int, batch: int = 64):
  """Fly len(keys) attack-free missions of `env` in worlds `world_ids` [N] for n_ticks ticks, in chunks of `batch`
  (the last padded: one compile). Returns numpy (|r| [N, T, C] float32, fresh [N, T, C] bool & valid, end [N] s:
  how long each mission stayed valid, xmax [N, 3]: each mission's maximum of the raw GPS cross-checks,
  traces.xcheck_trace)."""
  n = int(keys.shape[0])
  free = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.asarray(x).dtype), (batch,) + jnp.shape(x)),
                      attacks.no_attack())
  world_ids = np.asarray(world_ids, np.int32)
  r_all = np.zeros((n, n_ticks, det.N_CHANNELS), np.float32)
  f_all = np.zeros((n, n_ticks, det.N_CHANNELS), bool)
  end = np.zeros((n,), np.float32)
  xmax = np.zeros((n, 3), np.float32)
  for i in range(0, n, batch):
    idx = np.minimum(np.arange(i, i + batch), n - 1)
    tr = traces.tick_trace(envs.record(env, keys[idx], n_ticks, traces.RECORD_FIELDS, attacks=free,
                                       world_ids=world_ids[idx]))
    r, fresh = traces.residual_trace(base, tr, env.config.tick_dt)
    x = jnp.max(traces.xcheck_trace(base, tr, env.config.tick_dt), axis=1)
    m = min(batch, n - i)
    r, fresh, valid, x = jax.device_get((r[:m], fresh[:m], tr.valid[:m], x[:m]))
    r_all[i:i + m], f_all[i:i + m], xmax[i:i + m] = r, fresh, x
    end[i:i + m] = valid.sum(-1) * env.config.tick_dt
  return r_all, f_all, end, xmax


def calibrate_vehicle(vehicle: str, missions: int = 1024, seconds: float = 135.0, mission_s=(60.0, 120.0),
                      target_fpr: float = 0.01, seed: int = 0, worlds=CAL_WORLDS, batch: int = 64,
                      h_margin: float | None = None, verbose: bool = True, xcheck_margin: float = 1.2):
  """Record `missions` attack-free missions (worlds round robin) and calibrate. Returns (DetectorConfig, meta).
  h_margin: calibrate's threshold margin over the per-mission maxima (None: the DetectorConfig default).
  The GPS cross-check thresholds dr_h, vel_h are xcheck_margin x the same quantile of the per-mission maxima of
  the raw checks (traces.xcheck_trace) as the CUSUM's (with 1024 missions: the sample maximum)."""
  bad = [w for w in worlds if w not in worlds_lib.PRESETS]
  if bad or not worlds:
    raise ValueError(f"unknown or no world(s) {bad}; choose from {', '.join(worlds_lib.PRESETS)}")
  t0 = time.time()
  mcfg = (MissionConfig.drone if vehicle == "drone" else MissionConfig.rover)(
      min_duration_s=float(mission_s[0]), max_duration_s=float(mission_s[1]))
  base = (det.DetectorConfig.drone if vehicle == "drone" else det.DetectorConfig.rover)(calibrated=False)
  if h_margin is not None:
    base = dataclasses.replace(base, h_margin=float(h_margin))
  # detector_config given: the env does not read the (possibly missing or stale) preset being regenerated.
  env = envs.make(vehicle, mission=mcfg, worlds=tuple(worlds), detector_config=base)
  ids = [worlds_lib.PRESET_NAMES.index(worlds[i % len(worlds)]) for i in range(missions)]
  n_ticks = int(round(seconds / env.config.tick_dt))
  r, fresh, end, xmax = record_free(env, base, jax.random.split(jax.random.PRNGKey(seed), missions), ids, n_ticks,
                                    batch)
  t_rec = time.time() - t0
  cfg = det.calibrate(base, r, fresh, target_fpr)
  q_x = float(np.clip(1.0 - target_fpr / max(1.0, float(np.asarray(base.used).sum())), 0.0, 1.0))
  x_raw = np.quantile(xmax, q_x, axis=0, method="higher")
  cfg = dataclasses.replace(cfg, dr_h=float(xcheck_margin * x_raw[0]), vel_h=float(xcheck_margin * x_raw[1]),
                            hgt_h=float(xcheck_margin * x_raw[2]))
  # In-sample statistics: per-mission max of the uncapped CUSUM S (k = 1), relative to the calibrated h.
  used = np.asarray(cfg.used) > 0
  q = float(np.clip(1.0 - target_fpr / max(1.0, float(np.asarray(base.used).sum())), 0.0, 1.0))
  _, h_raw, max_s, n_fresh = jax.device_get(det.calibration_stats(jnp.asarray(r), jnp.asarray(fresh),
                                                                   base.k_quantile, q))
  score = np.asarray(max_s) / np.asarray(cfg.h)
  mission_score = np.max(np.where(used, score, 0.0), axis=-1)
  per_world = {w: float(np.max(mission_score[np.asarray(ids) == worlds_lib.PRESET_NAMES.index(w)], initial=0.0))
               for w in worlds}
  meta = {"vehicle": vehicle, "missions": missions, "seconds": seconds, "mission_s": list(mission_s),
          "seed": seed, "worlds": list(worlds), "target_fpr_per_mission": target_fpr,
          "k_quantile": base.k_quantile, "h_margin": base.h_margin, "h_min": base.h_min,
          "h_quantile": q, "h_quantile_is_sample_max": bool(missions < 1.0 / max(1e-12, 1.0 - q)),
          "mission_end_s": [float(np.min(end)), float(np.median(end)), float(np.max(end))],
          "whole_missions": float(np.mean(end < seconds - 1e-3)),
          "n_fresh": [int(x) for x in n_fresh], "h_raw": [float(x) for x in h_raw],
          "xcheck_margin": xcheck_margin, "xcheck_raw": [float(x) for x in x_raw],
          "mask_margin": base.mask_margin, "mask_h_min": base.mask_h_min,
          "xcheck_max_per_mission_q50_q90_q99_max": [[float(v) for v in np.quantile(xmax[:, j], [0.5, 0.9, 0.99, 1.0])]
                                                     for j in range(3)],
          "in_sample_false_alarms": float(np.mean((mission_score > 1.0)
                                                  | np.any(xmax > [cfg.dr_h, cfg.vel_h, cfg.hgt_h], -1))),
          "in_sample_max_score": float(np.max(mission_score)),
          "in_sample_max_score_per_world": per_world,
          "calibration_s": round(time.time() - t0, 1)}
  if verbose:
    print(f"{vehicle}: {missions} attack-free missions ({mission_s[0]:.0f}-{mission_s[1]:.0f} s nominal, ended "
          f"{meta['mission_end_s'][0]:.0f}-{meta['mission_end_s'][2]:.0f} s, {100 * meta['whole_missions']:.0f}% "
          f"flown whole in {seconds:.0f} s) recorded in {t_rec:.1f} s; calibrated in {meta['calibration_s']:.1f} s")
  return cfg, meta


def main(argv=None):
  ap = argparse.ArgumentParser(description="calibrate and save the vehicle's residual-detector preset")
  ap.add_argument("--vehicle", choices=VEHICLES, default="drone")
  ap.add_argument("--missions", type=int, default=1024, help="attack-free calibration missions")
  ap.add_argument("--seconds", type=float, default=135.0, help="recorded length (s): covers the longest mission")
  ap.add_argument("--mission-s", type=float, nargs=2, default=(60.0, 120.0), metavar=("MIN", "MAX"),
                  help="nominal mission length range (s), MissionConfig min/max_duration_s")
  ap.add_argument("--target-fpr", type=float, default=0.01, help="false alarms per mission")
  ap.add_argument("--worlds", default=",".join(CAL_WORLDS), help="comma-separated world presets (round robin)")
  ap.add_argument("--h-margin", type=float, default=None,
                  help=f"threshold margin over the per-mission CUSUM maxima (default {det.DetectorConfig.h_margin})")
  ap.add_argument("--xcheck-margin", type=float, default=1.2,
                  help="GPS cross-check thresholds over the per-mission maxima of the raw checks")
  ap.add_argument("--seed", type=int, default=0)
  ap.add_argument("--batch", type=int, default=64)
  ap.add_argument("--out", default="", help="default: assets/detector_<vehicle>.json")
  a = ap.parse_args(argv)
  worlds = tuple(w for w in a.worlds.split(",") if w)
  try:
    if not a.xcheck_margin > 0:
      raise ValueError("--xcheck-margin must be > 0")
    cfg, meta = calibrate_vehicle(a.vehicle, a.missions, a.seconds, tuple(a.mission_s), a.target_fpr, a.seed,
                                  worlds, a.batch, a.h_margin, xcheck_margin=a.xcheck_margin)
  except ValueError as e:
    ap.error(str(e))
  out = a.out or preset_file.default_path(a.vehicle)
  preset_file.save_preset(cfg, out, meta)
  print(f"wrote {out}: in-sample false alarms {meta['in_sample_false_alarms']:.3f}, max score "
        f"{meta['in_sample_max_score']:.2f}")
  for c, u, s, h in zip(det.CHANNELS, cfg.used, cfg.scale, cfg.h):
    if u:
      print(f"  {c:10s} scale {s:9.4g}  h {h:8.2f}")
  print(f"  GPS cross-checks: dr_h {cfg.dr_h:.2f} m, vel_h {cfg.vel_h:.2f}, hgt_h {cfg.hgt_h:.2f} m")
  print("  diagnosis mask_h: " + ", ".join(f"{n} {x:.2f}" for n, x in zip(det.SENSOR_NAMES, cfg.mask_h)))


if __name__ == "__main__":
  main()
