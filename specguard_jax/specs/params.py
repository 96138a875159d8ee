"""Autopilot parameters behind the mission specifications, with units, defaults (paper Table 4 / ArduPilot table) and
readers for PX4 `.params` and ArduPilot `.parm` files.

Names are the paper's PX4 / ArduPilot names. Names the paper uses that PX4/ArduPilot lack (NAV_MC_POS_TH,
MPC_XY_VEL_MIN, NAV_MC_ALT_RADIUS, CRUISE_SPEED_MIN/MAX) are SpecGuard's own; names starting with `SG_` are ours
(quantities the paper leaves implicit). All values are SI (m, m/s, s); ArduPilot's WPNAV_RADIUS is stored in cm in
.parm files and is converted to m on load.

Every route that sets a known parameter (overrides, `with_params`, spec files, parameter files) checks it against its
ParamDef range, so PX4's / ArduPilot's "disabled" values (-1) are refused the same way everywhere, and `CONSTRAINTS`
(a minimum below its maximum) are checked on every table (`specs.table.validate`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import warnings
from typing import Dict, Iterable, Mapping, Optional, Union

from specguard_jax.specs.errors import ParamFileWarning, SpecError


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
    ("GF_MAX_HOR_DIST", 50.0, "m", "geofence radius about home: a parameter file that sets it (> 0) adds that fence "
                                    "(specs.vehicle_params); the table's value alone adds none"),
    ("GF_MAX_VER_DIST", 10.0, "m", "geofence height above home: a parameter file that sets it (> 0) adds that "
                                    "ceiling (specs.vehicle_params); the table's value alone adds none"),
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

AUTOPILOT_PARAMS = _defs(
    # The autopilots' own names a parameter file may carry beside the paper's (specs.vehicle_params maps them).
    ("WP_RADIUS", 2.0, "m", "ArduPilot Rover waypoint radius: the rover's WPNAV_RADIUS (S5) and mission acceptance "
                            "radius", 0.01, 1000.0),
    ("CRUISE_SPEED", 2.0, "m/s", "ArduPilot Rover cruise speed: the rover's mission speed; CRUISE_SPEED_MIN (S7) "
                                 "becomes half of it", 0.0, 100.0),
    ("MPC_XY_CRUISE", 5.0, "m/s", "PX4 multicopter cruise speed: the drone's mission speed", 0.0, 100.0),
    ("FENCE_ENABLE", 0.0, "", "ArduPilot fence switch: 0 leaves FENCE_RADIUS / FENCE_ALT_MAX unused", 0.0, 1.0),
    ("FENCE_TYPE", 7.0, "", "ArduPilot fence types bitmask: 1 maximum altitude, 2 circle about home, 4 polygons",
     0.0, 15.0),
    ("FENCE_RADIUS", 300.0, "m", "ArduPilot fence: circle radius about home", 0.0, 10_000.0),
    ("FENCE_ALT_MAX", 100.0, "m", "ArduPilot fence: maximum altitude above home", 0.0, 10_000.0),
)

CONSTRAINTS = (
    # (lower, upper): a table (or a file) that sets both must have lower < upper, else no trace satisfies both specs.
    ("MPC_XY_VEL_MIN", "MPC_XY_VEL_MAX"),
    ("NAV_MIN_LTR_ALT", "MIS_TAKEOFF_ALT"),
    ("CRUISE_SPEED_MIN", "CRUISE_SPEED_MAX"),
)


def param_def(name: str) -> Optional[ParamDef]:
  """The ParamDef of a drone or rover spec parameter (the names both tables share have the same range) or of an
  autopilot name a parameter file may carry (AUTOPILOT_PARAMS), else None."""
  return DRONE_PARAMS.get(name) or ROVER_PARAMS.get(name) or AUTOPILOT_PARAMS.get(name)


def check_consistent(values: Mapping[str, float], where: str = "", lines: Optional[Mapping[str, int]] = None) -> None:
  """Raise SpecError naming both parameters and values if `values` break one of `CONSTRAINTS`.
  where: prefix for the message (a file name); lines: {name: line number} to cite."""
  for lo, hi in CONSTRAINTS:
    if lo in values and hi in values and not values[lo] < values[hi]:
      at = lambda n: f" (line {lines[n]})" if lines and n in lines else ""  # noqa: E731
      unit = param_def(lo).unit
      raise SpecError(f"{where + ': ' if where else ''}contradictory parameters: {lo} = {values[lo]:g} {unit}{at(lo)} "
                      f"must be below {hi} = {values[hi]:g} {unit}{at(hi)} ({param_def(lo).description} / "
                      f"{param_def(hi).description})")


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
  check_consistent(out)
  return out


def decode_text(data: bytes) -> str:
  """Text of a parameter or spec file: UTF-8 (a leading byte-order mark dropped), else Latin-1, which decodes any
  byte (comments written by old Windows tools); the readers then refuse non-ASCII outside comments."""
  if data.startswith(b"\xef\xbb\xbf"):
    data = data[3:]
  try:
    return data.decode("utf-8")
  except UnicodeDecodeError:
    return data.decode("latin-1")


def read_text(path: str, what: str) -> str:
  """`decode_text` of the file at `path`; SpecError naming `what` and the file if it cannot be read."""
  try:
    with open(path, "rb") as fh:
      return decode_text(fh.read())
  except OSError as e:
    raise SpecError(f"cannot read {what} {path}: {e.strerror or e}") from None


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_MAX_LISTED = 20  # unknown names listed by name in the warning


def load_params_file(path: str, known: Optional[Iterable[str]] = None) -> Dict[str, float]:
  """Read a PX4 `.params` (tab-separated `SYS COMP NAME VALUE TYPE`) or ArduPilot `.parm` (`NAME,VALUE` / `NAME VALUE`)
  file: `loads_params` of its bytes (see there)."""
  fmt = "parm" if os.path.splitext(path)[1].lower() == ".parm" else "params"
  return loads_params(read_text(path, "parameter file"), fmt, known, name=path)


def loads_params(text: Union[str, bytes], fmt: str = "params", known: Optional[Iterable[str]] = None,
                 name: str = "<string>") -> Dict[str, float]:
  """Parse parameter-file contents; returns {NAME: value in SI units} for the names in `known` (default: every drone
  and rover spec parameter and the autopilot names of AUTOPILOT_PARAMS).

  fmt "params" (PX4; ArduPilot lines are accepted too) or "parm" (ArduPilot only). Bytes are decoded by `decode_text`
  (UTF-8 with or without a BOM, else Latin-1). '#' starts a comment. Every other non-blank line must be a parameter
  line with an identifier name and a finite number (PX4: integer SYS, COMP and TYPE columns), ASCII only: the first
  line that is not raises SpecError "<file>:<line>: ...", as does a name set twice, a known parameter outside its
  range (PX4's -1 "disabled" included) or a contradictory pair (`CONSTRAINTS`). Names outside `known` (the autopilot's
  other parameters) are ignored, listed in one ParamFileWarning.
  """
  if fmt not in ("params", "parm"):
    raise SpecError(f"parameter file format must be 'params' or 'parm', got {fmt!r}")
  known = set(DRONE_PARAMS) | set(ROVER_PARAMS) | set(AUTOPILOT_PARAMS) if known is None else set(known)
  text = decode_text(text) if isinstance(text, bytes) else text.removeprefix("\ufeff")
  out: Dict[str, float] = {}
  seen: Dict[tuple, tuple] = {}   # key -> (line, raw value) of its first setting
  lines: Dict[str, int] = {}
  unknown = []
  for lineno, raw in enumerate(text.split("\n"), 1):
    line = raw.split("#", 1)[0].strip()
    if not line:
      continue
    where = f"{name}:{lineno}"
    if not (line.isascii() and line.replace("\t", " ").isprintable()):
      raise SpecError(f"{where}: non-ASCII or control character in {_show(line)} (only comments may hold them)")
    fields = line.replace(",", " ").split()
    if len(fields) == 5 and fmt == "params":  # PX4: vehicle-id component-id name value type
      pname, value, scale = fields[2], fields[3], PX4_FILE_SCALE
      if not all(re.fullmatch(r"\d+", f) for f in (fields[0], fields[1], fields[4])):
        raise SpecError(f"{where}: {_show(line)}: PX4 lines are 'SYS COMP NAME VALUE TYPE' with integer SYS, COMP "
                        "and TYPE")
      key = (fields[0], fields[1], pname)
    elif len(fields) == 2:  # ArduPilot
      pname, value, scale = fields[0], fields[1], ARDUPILOT_FILE_SCALE
      key = ("", "", pname)
    else:
      raise SpecError(f"{where}: cannot parse {_show(line)} (expected PX4 'SYS COMP NAME VALUE TYPE' or ArduPilot "
                      "'NAME,VALUE')")
    if not _NAME.fullmatch(pname):
      raise SpecError(f"{where}: {pname[:40]!r} is not a parameter name (letters, digits, '_')")
    v = check_value(f"{pname} ({where})", value)
    if key in seen:
      first, first_value = seen[key]
      raise SpecError(f"{where}: {pname} is set twice: {first_value} on line {first} and {value} on line {lineno}")
    seen[key] = (lineno, value)
    if pname in known:
      out[pname] = check_value(f"{pname} ({where})", v * scale.get(pname, 1.0), param_def(pname))
      lines[pname] = lineno
    else:
      unknown.append(pname)
  check_consistent(out, name, lines)
  if unknown:
    listed = ", ".join(unknown[:_MAX_LISTED]) + (f" and {len(unknown) - _MAX_LISTED} more" if len(unknown) > _MAX_LISTED
                                                 else "")
    warnings.warn(f"{name}: ignored {len(unknown)} parameter(s) the specs do not use: {listed}", ParamFileWarning,
                  stacklevel=2)
  return out


def _show(line: str) -> str:
  """A file line for a message: repr, cut to 60 characters."""
  return repr(line if len(line) <= 60 else line[:57] + "...")
