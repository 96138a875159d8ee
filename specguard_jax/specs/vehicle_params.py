"""What an autopilot parameter file (PX4 `.params`, ArduPilot `.parm`) sets for a vehicle: its spec table's parameters,
its missions' speed and acceptance radius, and the home-centred fence (`VehicleSettings`).

Names (specs.params): the paper's names set the spec table directly; the autopilots' own names are mapped beside them
(a paper name the file sets itself wins over a mapped one):
  WP_RADIUS (ArduPilot Rover, m)       -> WPNAV_RADIUS (rover S5) and the missions' acceptance radius
  CRUISE_SPEED (ArduPilot Rover, m/s)  -> the rover's mission cruise speed, and CRUISE_SPEED_MIN (S7) = half of it:
                                          the paper's floor (5 m/s) is five times the authors' own rover's 1 m/s
  MPC_XY_CRUISE (PX4, m/s)             -> the drone's mission cruise speed
  NAV_ACC_RAD (PX4, m)                 -> NAV_ACC_RAD (drone S5, already a spec name) and the acceptance radius
  AVOID_MARGIN, FENCE_MARGIN           -> already the rover table's names (ArduPilot's own)
Fence: PX4 GF_MAX_HOR_DIST / GF_MAX_VER_DIST (> 0; 0 is PX4's "off") and ArduPilot FENCE_RADIUS / FENCE_ALT_MAX
(used when FENCE_ENABLE is not 0 and FENCE_TYPE has the circle (2) / altitude (1) bit; a file without FENCE_ENABLE
or FENCE_TYPE uses them) give a circle of that radius about home and a maximum altitude above it
(envs.geofence, envs.worlds.with_geofence). Only a file that names them adds a fence: the spec table's defaults
(GF_MAX_HOR_DIST 50 m) add none.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional

from specguard_jax.specs import params as P
from specguard_jax.specs.errors import SpecError


@dataclasses.dataclass(frozen=True)
class VehicleSettings:
  """spec_overrides: ((NAME, value), ...) for the vehicle's spec table; cruise_speed (m/s) and acceptance_radius (m)
  of its missions, None: the MissionConfig's own; fence_radius (m) and fence_alt_max (m above home), 0: none."""

  spec_overrides: tuple = ()
  cruise_speed: Optional[float] = None
  acceptance_radius: Optional[float] = None
  fence_radius: float = 0.0
  fence_alt_max: float = 0.0


def settings_from_params(values: Mapping[str, float], vehicle: str, where: str = "") -> VehicleSettings:
  """VehicleSettings of a parameter file's values ({NAME: SI value}, `P.loads_params`) for `vehicle` ("drone" |
  "rover"). Names of the other vehicle's spec table are left out; a contradiction left by the mapping (a CRUISE_SPEED
  whose half is not below CRUISE_SPEED_MAX) raises SpecError naming the file (`where`)."""
  table = P.DRONE_PARAMS if vehicle == "drone" else P.ROVER_PARAMS
  spec = {n: v for n, v in values.items() if n in table}
  cruise = acceptance = None
  if vehicle == "rover":
    if "WP_RADIUS" in values:
      spec.setdefault("WPNAV_RADIUS", values["WP_RADIUS"])
      acceptance = values["WP_RADIUS"]
    if values.get("CRUISE_SPEED", 0.0) > 0:
      cruise = values["CRUISE_SPEED"]
      spec.setdefault("CRUISE_SPEED_MIN", 0.5 * cruise)
  else:
    if "NAV_ACC_RAD" in values:
      acceptance = values["NAV_ACC_RAD"]
    if values.get("MPC_XY_CRUISE", 0.0) > 0:
      cruise = values["MPC_XY_CRUISE"]
  P.check_consistent({**{n: d.default for n, d in table.items()}, **spec}, where)
  radius, alt = [], []
  if values.get("GF_MAX_HOR_DIST", 0.0) > 0:
    radius.append(values["GF_MAX_HOR_DIST"])
  if values.get("GF_MAX_VER_DIST", 0.0) > 0:
    alt.append(values["GF_MAX_VER_DIST"])
  if values.get("FENCE_ENABLE", 1.0) != 0:
    kinds = int(values.get("FENCE_TYPE", 7))
    if kinds & 2 and values.get("FENCE_RADIUS", 0.0) > 0:
      radius.append(values["FENCE_RADIUS"])
    if kinds & 1 and values.get("FENCE_ALT_MAX", 0.0) > 0:
      alt.append(values["FENCE_ALT_MAX"])
  return VehicleSettings(tuple(sorted(spec.items())), cruise, acceptance, min(radius, default=0.0),
                         min(alt, default=0.0))


def load_vehicle_settings(path: str, vehicle: str) -> VehicleSettings:
  """`settings_from_params` of the parameter file at `path` (SpecError on a bad file, ParamFileWarning listing the
  names the specs do not use)."""
  if vehicle not in ("drone", "rover"):
    raise SpecError(f"vehicle must be 'drone' or 'rover', got {vehicle!r}")
  return settings_from_params(P.load_params_file(path), vehicle, where=path)
