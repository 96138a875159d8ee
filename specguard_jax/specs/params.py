"""Autopilot parameters behind the mission specifications, with units, defaults (paper Table 4 / ArduPilot table) and
readers for PX4 `.params` and ArduPilot `.parm` files.

Names are the paper's PX4 / ArduPilot names. Names the paper uses that PX4/ArduPilot lack (NAV_MC_POS_TH,
MPC_XY_VEL_MIN, NAV_MC_ALT_RADIUS, CRUISE_SPEED_MIN/MAX) are SpecGuard's own; names starting with `SG_` are ours
(quantities the paper leaves implicit). All values are SI (m, m/s, s); ArduPilot's WPNAV_RADIUS is stored in cm in
.parm files and is converted to m on load.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Dict, Iterable, Mapping, Optional

from specguard_jax.specs.errors import SpecError


@dataclasses.dataclass(frozen=True)
class ParamDef:
  """One named parameter: default value, unit, meaning and allowed range [lo, hi]."""

  name: str
  default: float
  unit: str
  description: str
  lo: float = 0.0
  hi: float = math.inf


def _defs(*rows) -> Dict[str, ParamDef]:
  return {r[0]: ParamDef(*r) for r in rows}


DRONE_PARAMS = _defs(
    ("CP_DIST", 5.0, "m", "collision-prevention distance to obstacles (S1, S6)"),
    ("NAV_MC_POS_TH", 10.0, "m", "max deviation from the mission leg (S2)"),
    ("NAV_MIN_LTR_ALT", 10.0, "m", "min altitude outside take-off/landing (S3)"),
    ("MIS_TAKEOFF_ALT", 20.0, "m", "max altitude (S4; the paper's use of this name)"),
    ("NAV_ACC_RAD", 5.0, "m", "waypoint acceptance radius (S5; paper: CMD_NAV_WAYPOINT 5 m)"),
    ("MPC_XY_VEL_MIN", 5.0, "m/s", "min horizontal cruise speed (S7)"),
    ("MPC_XY_VEL_MAX", 12.0, "m/s", "max horizontal speed (S8)"),
    ("MPC_LAND_SPEED", 0.5, "m/s", "max descent speed while landing (S9)"),
    ("MPC_TKO_SPEED", 2.0, "m/s", "min climb rate during take-off (S10, as Table 4's STL states)"),
    ("NAV_MC_ALT_RADIUS", 8.0, "m", "max horizontal distance from the loiter centre (S11)"),
    ("GF_MAX_HOR_DIST", 50.0, "m", "geofence horizontal extent (fence geometry, consumed by the env)"),
    ("GF_MAX_VER_DIST", 10.0, "m", "geofence vertical extent (fence geometry, consumed by the env)"),
    ("SG_GF_MARGIN", 1.0, "m", "min margin to the geofence (S12)"),
    ("SG_TURN_DIST", 10.0, "m", "S7 min-speed exemption radius around the target waypoint (turns, braking)"),
    ("SG_ACCEL_TIME", 3.0, "s", "S7/S10 grace: the speed bound must be met within this time of any phase instant"),
)

ROVER_PARAMS = _defs(
    ("AVOID_MARGIN", 5.0, "m", "obstacle avoidance margin (S1, S6)"),
    ("SG_POS_TH", 10.0, "m", "max deviation from the mission leg (S2; paper lists GPS_POS_X/Y/Z, which are antenna "
                              "offsets in ArduPilot)"),
    ("WPNAV_RADIUS", 5.0, "m", "waypoint radius (S5; .parm files store cm)"),
    ("CRUISE_SPEED_MIN", 5.0, "m/s", "min cruise speed (S7)"),
    ("CRUISE_SPEED_MAX", 12.0, "m/s", "max speed (S8)"),
    ("FENCE_MARGIN", 1.0, "m", "min margin to the fence (S12)"),
    ("SG_TURN_DIST", 10.0, "m", "S7 min-speed exemption radius around the target waypoint (turns, braking)"),
    ("SG_ACCEL_TIME", 3.0, "s", "S7 grace: the min speed must be met within this time of any cruise instant"),
)

# Multipliers from a .parm / .params file's unit to the SI unit used here.
ARDUPILOT_FILE_SCALE = {"WPNAV_RADIUS": 0.01}
PX4_FILE_SCALE: Dict[str, float] = {}


def check_value(name: str, value, pdef: Optional[ParamDef] = None) -> float:
  """Return `value` as a float, or raise SpecError naming the parameter if it is not a finite number in range."""
  try:
    v = float(value)
  except (TypeError, ValueError):
    raise SpecError(f"parameter {name}: value {value!r} is not a number") from None
  if not math.isfinite(v):
    raise SpecError(f"parameter {name}: value {v} is not finite")
  if pdef is not None and not (pdef.lo <= v <= pdef.hi):
    raise SpecError(f"parameter {name}: value {v} {pdef.unit} is outside [{pdef.lo}, {pdef.hi}] "
                    f"({pdef.description}; note PX4 uses -1/0 for 'disabled', which a spec cannot use)")
  return v


def resolve(defs: Mapping[str, ParamDef], overrides: Optional[Mapping[str, float]] = None) -> Dict[str, float]:
  """Defaults of `defs` updated by `overrides`; unknown names or bad values raise SpecError."""
  out = {n: d.default for n, d in defs.items()}
  for name, value in (overrides or {}).items():
    if name not in defs:
      raise SpecError(f"unknown parameter {name!r} (known: {', '.join(sorted(defs))})")
    out[name] = check_value(name, value, defs[name])
  return out


def load_params_file(path: str, known: Optional[Iterable[str]] = None) -> Dict[str, float]:
  """Read a PX4 `.params` (tab-separated `1 1 NAME VALUE TYPE`) or ArduPilot `.parm` (`NAME,VALUE` / `NAME VALUE`) file.

  Returns {NAME: value in SI units} for the names in `known` (default: every drone and rover spec parameter); other
  autopilot parameters in the file are ignored. Malformed lines raise SpecError naming file and line.
  """
  known = set(DRONE_PARAMS) | set(ROVER_PARAMS) if known is None else set(known)
  ext = os.path.splitext(path)[1].lower()
  out: Dict[str, float] = {}
  try:
    with open(path, encoding="utf-8") as fh:
      lines = fh.read().splitlines()
  except OSError as e:
    raise SpecError(f"cannot read parameter file {path}: {e.strerror}") from None
  for lineno, raw in enumerate(lines, 1):
    line = raw.split("#", 1)[0].strip()
    if not line:
      continue
    fields = line.replace(",", " ").split()
    if len(fields) >= 5 and ext != ".parm":  # PX4: vehicle-id component-id name value type
      name, value, scale = fields[2], fields[3], PX4_FILE_SCALE
    elif len(fields) == 2:  # ArduPilot
      name, value, scale = fields[0], fields[1], ARDUPILOT_FILE_SCALE
    else:
      raise SpecError(f"{path}:{lineno}: cannot parse {raw.strip()!r} (expected PX4 'SYS COMP NAME VALUE TYPE' or "
                      "ArduPilot 'NAME,VALUE')")
    if name in known:
      out[name] = check_value(f"{name} ({path}:{lineno})", value) * scale.get(name, 1.0)
  return out
