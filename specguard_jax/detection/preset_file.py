"""The shipped detector presets as JSON: save, load and check them.

`DetectorConfig.drone()` / `.rover()` (what the env uses when EnvConfig.detector_config is None) return the
vehicle model with the calibrated `scale`, `h`, `used` and `k` and the GPS cross-check alarm thresholds `dr_h`,
`vel_h`, `hgt_h` (detector.position_check) and the multi-sensor diagnosis thresholds `mask_h` (detector.diagnose_mask)
read from assets/detector_<vehicle>.json;
`DetectorConfig.drone(calibrated=False)` gives the uncalibrated defaults (the starting point of `calibrate`).
Calibration flies attack-free missions (specguard_jax.calibration.detector_presets, which documents the shipped
files' recipe and what they were checked against), so the thresholds ship as constants and are regenerated with

  python tools/calibrate_detector.py --vehicle drone --missions 1024
  python tools/calibrate_detector.py --vehicle rover --missions 1024

Custom presets: `DetectorConfig.drone(**load_preset(path, "drone"))`.
"""

from __future__ import annotations

import functools
import json
import math
import os

from specguard_jax import assets
from specguard_jax.detection.channels import CHANNELS, N_CHANNELS
from specguard_jax.types import SENSOR_NAMES

FIELDS = ("scale", "h", "used", "k")
XCHECK_FIELDS = ("dr_h", "vel_h", "hgt_h")   # cross-check alarm thresholds (optional in a file: defaults otherwise)
MASK_FIELDS = ("mask_h",)   # per-sensor thresholds of the multi-sensor diagnosis [6] (optional: defaults otherwise)


def default_path(vehicle: str) -> str:
  return assets.asset_path(f"detector_{vehicle}.json")


def save_preset(cfg, path: str, meta: dict | None = None) -> None:
  """Write a DetectorConfig's calibrated fields (FIELDS, XCHECK_FIELDS, MASK_FIELDS) and `meta` as JSON."""
  out = {"vehicle": cfg.vehicle, "channels": list(CHANNELS), "scale": list(cfg.scale), "h": list(cfg.h),
         "used": list(cfg.used), "k": float(cfg.k), **{k: float(getattr(cfg, k)) for k in XCHECK_FIELDS},
         **{k: [float(x) for x in getattr(cfg, k)] for k in MASK_FIELDS}, "meta": meta or {}}
  with open(path, "w") as f:
    json.dump(out, f, indent=1)


@functools.lru_cache(maxsize=16)
def _load(path: str, mtime_ns: int, vehicle: str | None) -> tuple:
  try:
    with open(path) as f:
      d = json.load(f)
    if not isinstance(d, dict):
      raise TypeError(f"top level is {type(d).__name__}, expected an object")
    out = {k: tuple(float(x) for x in d[k]) for k in ("scale", "h", "used")}
    out["k"] = float(d["k"])
    out.update({k: float(d[k]) for k in XCHECK_FIELDS if k in d})
    out.update({k: tuple(float(x) for x in d[k]) for k in MASK_FIELDS if k in d})
    channels, file_vehicle = list(d["channels"]), d["vehicle"]
  except (OSError, KeyError, TypeError, ValueError) as e:
    raise ValueError(f"cannot load detector preset {path}: {type(e).__name__}: {e}") from None
  if vehicle is not None and file_vehicle != vehicle:
    raise ValueError(f"detector preset {path} is for vehicle {file_vehicle!r}, expected {vehicle!r}")
  if channels != list(CHANNELS):
    raise ValueError(f"detector preset {path} has channels {channels}, expected {list(CHANNELS)}")
  bad = [k for k in ("scale", "h", "used") if len(out[k]) != N_CHANNELS]
  bad += [k for k in ("scale", "h") if k not in bad and not all(math.isfinite(x) and x > 0 for x in out[k])]
  bad += ["used"] if "used" not in bad and not set(out["used"]) <= {0.0, 1.0} else []
  bad += [k for k in ("k",) + XCHECK_FIELDS
          if k in out and not (math.isfinite(out[k]) and (out[k] > 0 or (k == "hgt_h" and out[k] == 0)))]
  bad += [k for k in MASK_FIELDS
          if k in out and not (len(out[k]) == len(SENSOR_NAMES) and all(math.isfinite(x) and x > 0 for x in out[k]))]
  if bad:
    raise ValueError(f"detector preset {path}: bad {', '.join(bad)} (need {N_CHANNELS} finite positive scale/h, "
                     f"used in {{0, 1}}, k > 0, dr_h / vel_h > 0, hgt_h >= 0, {len(SENSOR_NAMES)} positive mask_h)")
  return tuple(out.items())


def load_preset(path: str, vehicle: str | None = None) -> dict:
  """The calibrated DetectorConfig fields {scale, h, used, k} (and the cross-check thresholds dr_h, vel_h, hgt_h and
  the multi-sensor diagnosis thresholds mask_h where the file has them) from a JSON file written by save_preset
  (checked against `vehicle` if given and against CHANNELS); one-line ValueError if missing or malformed."""
  try:
    mtime = os.stat(path).st_mtime_ns
  except OSError as e:
    raise ValueError(f"cannot load detector preset {path}: {type(e).__name__}: {e}") from None
  return dict(_load(os.path.abspath(path), mtime, vehicle))
