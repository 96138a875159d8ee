"""Load QGroundControl mission files (`QGC WPL 110` .waypoints and `.plan` JSON) into a `Mission`.

Coordinates: lat/lon (degrees, WGS-84) become local ENU metres about the home position with an equirectangular
projection on a sphere of radius 6378137 m: x = R * dlon * cos(lat_home), y = R * dlat (radians). Over the few km of
a mission this differs from a proper local tangent plane by < 1 cm per km (error ~ d^2 / R). Altitudes become height
above home (z = 0 at home; frame 0/5 "global" altitudes are AMSL and get the home altitude subtracted, frame 3/6
are already relative). Rovers ignore altitudes (z = 0).

Supported commands (MAV_CMD): 16 NAV_WAYPOINT, 22 NAV_TAKEOFF (drone; only its altitude is used: the take-off is
vertical above home), 17 NAV_LOITER_UNLIM and 19 NAV_LOITER_TIME (drone, at most one; p1 = time s, p3 = radius m;
an unlimited loiter lasts MissionConfig.loiter_time[1] and must end the mission), 21 NAV_LAND (drone; lands at its
lat/lon, a waypoint is added there at the previous altitude unless it is within the acceptance radius of the last
waypoint; lat = lon = 0 means land in place), 20 NAV_RETURN_TO_LAUNCH (adds a waypoint above home, then lands for
drones) and 178 DO_CHANGE_SPEED (p2 m/s; one speed per mission). Without a take-off item a drone takes off to its first
waypoint's altitude. The cruise speed otherwise is the middle of MissionConfig.cruise_speed: the .plan file's
cruiseSpeed / hoverSpeed are QGC defaults more often than intent and are ignored. Deadlines follow
`missions.mission_timing` exactly like generated missions.

Mission length: any number of waypoints up to `max_waypoints` (MAX_FILE_WAYPOINTS = 1000 unless given; more is a
one-line error, never a silent truncation). The waypoint array has max(MissionConfig.max_waypoints, n) slots: a short
file has the generated missions' shape, a long one exactly its own length.

Home: a home at lat = lon = 0 (QGC writes it when no vehicle position is known) is replaced by the first item with a
position (a one-line MissionFileWarning says so). If that item is itself at 0, 0, the file's coordinates are a local
frame around 0, 0 (a simulator's) and lat = lon = 0 is a real position in it; otherwise, as in QGC, it means "none".

.plan extras (`load_plan`):
  * ComplexItem "survey": expanded into lawn-mower waypoints over its polygon (`survey_waypoints`): transects along
    `angle` (degrees clockwise from north) spaced CameraCalc.AdjustedFootprintSide apart (else `spacing` /
    `grid.spacing`), centred on the polygon, flown alternately, two waypoints per transect where it enters and
    leaves the polygon, at CameraCalc.DistanceToSurface (relative to home unless
    DistanceToSurfaceRelative is false); QGC's turnaround distance and camera triggers are left out. Other complex
    items (corridor scan, structure scan) are a one-line error naming the item and its type.
  * geoFence polygons and circles (inclusion and exclusion): the mission's fence geometry (envs.geofence.Geofence),
    which replaces the generated world's fences when the env flies the plan.
  * rallyPoints: [R, 3] positions (altitude relative to home; 0 for rovers) for the recovery controllers.

Checks (every value must also be finite; JSON's NaN / Infinity and booleans are refused where numbers belong):
  * latitudes in [-90, 90], longitudes in [-180, 180], the home altitude in [MIN_HOME_AMSL_M, MAX_HOME_AMSL_M];
  * every position within MAX_HOME_DISTANCE_M (10 km) of home: the equirectangular projection's error grows as
    d^2 / R (about 10 m at 10 km east-west at mid latitudes), and no episode flies that far anyway;
  * drone waypoints above the ground (height above home > 0) and at most MAX_ALTITUDE_M above home, take-off likewise;
  * DO_CHANGE_SPEED in (0, MAX_SPEED_M_S], loiter times in (0, MAX_LOITER_S], loiter radii at most MAX_LOITER_RADIUS_M;
  * a mission whose nominal duration exceeds the episode cap (`max_episode_s`, EnvConfig's default unless given)
    cannot finish inside an episode: a MissionFileWarning, or a MissionFileError with strict=True.

Errors: `MissionFileError` (a ValueError) with one line "<file>: line <n>: <problem>" / "<file>: item <k>: ...".
Files are read as UTF-8 (a byte-order mark is dropped); the format is JSON (.plan) when the extension is .plan or the
text starts with '{' or '[', else QGC WPL.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings

import jax.numpy as jnp
import numpy as np

from envs import geofence as geofence_lib
from envs.missions import DEFAULT_EPISODE_CAP_S, Mission, MissionConfig, mission_timing
from specguard_jax.types import VEHICLES

EARTH_RADIUS = 6378137.0
WPL_HEADER = "QGC WPL 110"
WPL_COLUMNS = ("seq", "current", "frame", "command", "param1", "param2", "param3", "param4", "lat", "lon", "alt",
               "autocontinue")

CMD_WAYPOINT, CMD_LOITER_UNLIM, CMD_LOITER_TIME, CMD_RTL, CMD_LAND, CMD_TAKEOFF = 16, 17, 19, 20, 21, 22
CMD_CHANGE_SPEED = 178
COMMAND_NAMES = {16: "NAV_WAYPOINT", 17: "NAV_LOITER_UNLIM", 19: "NAV_LOITER_TIME", 20: "NAV_RETURN_TO_LAUNCH",
                 21: "NAV_LAND", 22: "NAV_TAKEOFF", 178: "DO_CHANGE_SPEED"}
_NAV_COMMANDS = (16, 17, 19, 20, 21, 22)
_GLOBAL_FRAMES = (0, 5)    # MAV_FRAME_GLOBAL(_INT): altitude AMSL
_RELATIVE_FRAMES = (3, 6)  # MAV_FRAME_GLOBAL_RELATIVE_ALT(_INT): altitude above home
_MISSION_FRAME = 2         # MAV_FRAME_MISSION: DO_ commands without coordinates
_PLAN_PARAMS = ("", "", "", "", "latitude", "longitude", "altitude")  # what a .plan item's params[j] holds

MAX_HOME_DISTANCE_M = 10_000.0  # farthest position from home (m), see the module docstring
MAX_ALTITUDE_M = 1_000.0        # highest waypoint / take-off above home (m)
MIN_HOME_AMSL_M, MAX_HOME_AMSL_M = -500.0, 9_000.0  # home altitude above mean sea level (m)
MAX_SPEED_M_S = 30.0            # fastest DO_CHANGE_SPEED (m/s), above both vehicles' speed specs
MAX_LOITER_S = 3_600.0          # longest NAV_LOITER_TIME (s)
MAX_LOITER_RADIUS_M = 1_000.0   # widest loiter radius (m)
MAX_FILE_WAYPOINTS = 1_000      # default limit on a file's waypoints (load_mission(max_waypoints=...) raises it)
MAX_SURVEY_TRANSECTS = 500      # transects one survey item may expand into (a tiny spacing is a typo)
MIN_FENCE_RADIUS_M = 0.1        # smallest geofence circle radius (m)


class MissionFileError(ValueError):
  """A mission file that cannot be loaded; the message names the file, the line/item and the problem."""


class MissionFileWarning(UserWarning):
  """A mission file that loads but is unlikely to do what was meant (it cannot finish within the episode cap)."""


class _JSONConstant:
  """A JSON NaN / Infinity / -Infinity token (not standard JSON), kept so that the field it sits in can be named."""

  def __init__(self, token: str):
    self.token = token

  def __repr__(self) -> str:
    return self.token


@dataclasses.dataclass(frozen=True)
class MissionItem:
  """One parsed mission item. where: "line 5" / "item 3" (for messages); alt as written (frame decides)."""

  where: str
  command: int
  frame: int
  params: tuple  # (p1, p2, p3, p4)
  lat: float
  lon: float
  alt: float


@dataclasses.dataclass(frozen=True)
class SurveyItem:
  """A QGC survey complex item, expanded by `items_to_mission` (it needs the home position). polygon: ((lat, lon),
  ...) degrees; angle_deg: transect direction, clockwise from north; spacing_m: between transects; alt: altitude
  (above home if relative, else AMSL)."""

  where: str
  polygon: tuple
  angle_deg: float
  spacing_m: float
  alt: float
  relative: bool
  command: int = CMD_WAYPOINT


@dataclasses.dataclass(frozen=True)
class PlanExtras:
  """A .plan's geoFence and rallyPoints as read (degrees, metres): polygons ((where, inclusion, ((lat, lon), ...)),
  ...), circles ((where, inclusion, lat, lon, radius), ...), rally ((where, lat, lon, alt), ...)."""

  polygons: tuple = ()
  circles: tuple = ()
  rally: tuple = ()


@dataclasses.dataclass(frozen=True)
class Plan:
  """A loaded mission file: the Mission, its geofence (envs.geofence.Geofence, empty for WPL files or a .plan
  without geoFence) and rally points [R, 3] (m, numpy)."""

  mission: Mission
  geofence: geofence_lib.Geofence
  rally_points: np.ndarray

  @property
  def has_fence(self) -> bool:
    return self.geofence.n_zones > 0


def latlon_to_enu(lat, lon, home_lat, home_lon):
  """Equirectangular (x east, y north) metres of lat/lon (deg) about home (deg). Works on floats or arrays."""
  lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)  # float32 degrees would cost ~0.5 m
  x = EARTH_RADIUS * np.radians(lon - home_lon) * math.cos(math.radians(home_lat))
  y = EARTH_RADIUS * np.radians(lat - home_lat)
  return x, y


def enu_to_latlon(x, y, home_lat, home_lon):
  """Inverse of latlon_to_enu: (lat, lon) degrees."""
  x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
  lat = home_lat + np.degrees(y / EARTH_RADIUS)
  lon = home_lon + np.degrees(x / (EARTH_RADIUS * math.cos(math.radians(home_lat))))
  return lat, lon


# ----------------------------------------------------------------------------------------------------------------
# Parsers


def _fail(name, where, problem):
  raise MissionFileError(f"{name}: {where}: {problem}" if where else f"{name}: {problem}")


def parse_wpl(text: str, name: str = "<string>"):
  """Parse `QGC WPL 110` text. Returns (home (lat, lon, alt_amsl), [MissionItem]); line 0 (seq 0) is home."""
  lines = text.splitlines()
  if not lines or lines[0].strip() != WPL_HEADER:
    _fail(name, "line 1", f"missing header {WPL_HEADER!r} (got {lines[0].strip()[:40]!r})" if lines
          else f"empty file (expected header {WPL_HEADER!r})")
  rows = []
  for lineno, line in enumerate(lines[1:], start=2):
    if not line.strip():
      continue
    cols = line.rstrip("\r\n").split("\t")
    if len(cols) != len(WPL_COLUMNS):
      cols = line.split()  # some tools write spaces
    if len(cols) != len(WPL_COLUMNS):
      _fail(name, f"line {lineno}", f"expected {len(WPL_COLUMNS)} tab-separated columns, got {len(cols)}")
    vals = []
    for col, raw in zip(WPL_COLUMNS, cols):
      try:
        v = float(raw)
      except ValueError:
        _fail(name, f"line {lineno}", f"column {col!r} is not a number: {raw.strip()[:20]!r}")
      if not math.isfinite(v):
        _fail(name, f"line {lineno}", f"column {col!r} is not finite: {raw.strip()!r}")
      if col in ("seq", "current", "frame", "command", "autocontinue") and not v.is_integer():
        _fail(name, f"line {lineno}", f"column {col!r} must be an integer, got {raw.strip()[:20]!r}")
      vals.append(v)
    seq = int(vals[0])
    if seq != len(rows):
      _fail(name, f"line {lineno}", f"sequence number {seq}, expected {len(rows)}")
    rows.append((lineno, vals))
  if not rows:
    _fail(name, "", "no items (not even the home line)")
  _, h = rows[0]
  items = [MissionItem(f"line {ln}", int(v[3]), int(v[2]), tuple(v[4:8]), v[8], v[9], v[10]) for ln, v in rows[1:]]
  return (h[8], h[9], h[10]), items


def parse_plan(text: str, name: str = "<string>", extras: bool = False):
  """Parse QGC `.plan` JSON. Returns (home (lat, lon, alt_amsl), [MissionItem | SurveyItem]), items numbered from 1,
  and with extras=True also the PlanExtras (geoFence, rallyPoints)."""
  try:
    doc = json.loads(text, parse_constant=_JSONConstant)
  except json.JSONDecodeError as e:
    _fail(name, f"line {e.lineno}", f"not valid JSON ({e.msg})")
  except RecursionError:
    _fail(name, "", "JSON nested too deeply to read (a .plan nests a few levels)")
  except ValueError as e:  # e.g. an integer of more than 4300 digits
    _fail(name, "", f"unreadable JSON ({str(e)[:80]})")
  if not isinstance(doc, dict):
    _fail(name, "", f"not a .plan object: the top level is a JSON {_json_type(doc)} (a QGroundControl .plan is an "
          "object with \"fileType\": \"Plan\")")
  if doc.get("fileType") != "Plan":
    _fail(name, "", "not a QGroundControl plan (fileType != 'Plan')")
  mission = doc.get("mission")
  if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
    _fail(name, "", "missing 'mission.items' list")
  home = mission.get("plannedHomePosition")
  if not isinstance(home, list) or len(home) != 3:
    _fail(name, "", "missing or malformed 'mission.plannedHomePosition' [lat, lon, alt]")
  home = [_number(v, name, "", f"plannedHomePosition[{j}]", what)
          for j, (v, what) in enumerate(zip(home, ("latitude", "longitude", "altitude")))]
  items = []
  for k, it in enumerate(mission["items"], start=1):
    where = f"item {k}"
    if not isinstance(it, dict):
      _fail(name, where, "not a JSON object")
    typ = it.get("type")
    if typ == "ComplexItem":
      items.append(_complex_item(it, name, where))
      continue
    if typ != "SimpleItem":
      _fail(name, where, f"unknown item type {typ!r}")
    cmd, frame, params = it.get("command"), it.get("frame", 3), it.get("params")
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (cmd, frame)):
      _fail(name, where, f"'command' and 'frame' must be integers, got {str(cmd)[:20]} and {str(frame)[:20]}")
    if not isinstance(params, list) or len(params) != 7:
      _fail(name, where, "'params' must be a list of 7 values")
    vals = []
    for j, v in enumerate(params):
      if v is None:  # QGC writes NaN as null
        vals.append(math.nan if j >= 4 else 0.0)
      else:
        vals.append(_number(v, name, where, f"param {j + 1}", _PLAN_PARAMS[j]))
    items.append(MissionItem(where, cmd, frame, tuple(vals[:4]), vals[4], vals[5], vals[6]))
  home = tuple(float(v) for v in home)
  return (home, items, _plan_extras(doc, name)) if extras else (home, items)


def _complex_item(it: dict, name: str, where: str) -> SurveyItem:
  """A ComplexItem: a survey as a SurveyItem; any other kind a one-line error naming it."""
  kind = it.get("complexItemType")
  if kind != "survey":
    _fail(name, where, f"ComplexItem of type {str(kind)[:40]!r} is not supported (only 'survey' items are expanded "
          "into waypoints): replace it by simple waypoints in QGroundControl")
  poly = it.get("polygon")
  if not isinstance(poly, list) or len(poly) < 3:
    _fail(name, where, "survey 'polygon' must be a list of at least 3 [lat, lon] points")
  pts = []
  for j, v in enumerate(poly, start=1):
    if not isinstance(v, list) or len(v) < 2:
      _fail(name, where, f"survey polygon point {j} must be [lat, lon]")
    pts.append(tuple(_number(x, name, where, f"survey polygon point {j}", m) for x, m in zip(v[:2], ("lat", "lon"))))
  tsc = it.get("TransectStyleComplexItem") if isinstance(it.get("TransectStyleComplexItem"), dict) else {}
  cam = tsc.get("CameraCalc") if isinstance(tsc.get("CameraCalc"), dict) else {}
  grid = it.get("grid") if isinstance(it.get("grid"), dict) else {}
  spacing = next((v for v in (cam.get("AdjustedFootprintSide"), it.get("spacing"), grid.get("spacing"))
                  if v is not None), None)
  alt = next((v for v in (cam.get("DistanceToSurface"), grid.get("altitude")) if v is not None), None)
  if spacing is None or alt is None:
    _fail(name, where, "survey lacks its transect spacing (CameraCalc.AdjustedFootprintSide) or altitude "
          "(CameraCalc.DistanceToSurface)")
  spacing = _number(spacing, name, where, "survey transect spacing", "m")
  if not spacing > 0:
    _fail(name, where, f"survey transect spacing must be > 0 m, got {spacing:g}")
  angle = _number(it.get("angle", grid.get("angle", 0.0)), name, where, "survey angle", "degrees")
  relative = cam.get("DistanceToSurfaceRelative", grid.get("relativeAltitude", True))
  return SurveyItem(where, tuple(pts), angle, spacing, _number(alt, name, where, "survey altitude", "m"),
                    bool(relative))


def _latlon_pair(v, name, where, field):
  if not isinstance(v, list) or len(v) < 2:
    _fail(name, where, f"{field} must be [lat, lon]")
  return tuple(_number(x, name, where, field, m) for x, m in zip(v[:2], ("latitude", "longitude")))


def _plan_extras(doc: dict, name: str) -> PlanExtras:
  """The geoFence polygons / circles and rallyPoints of a .plan document, checked for shape and finite numbers."""
  polys, circles, rally = [], [], []
  fence = doc.get("geoFence", {})
  if fence is None:
    fence = {}
  if not isinstance(fence, dict):
    _fail(name, "geoFence", "must be a JSON object")
  for key in ("polygons", "circles"):
    if not isinstance(fence.get(key, []), list):
      _fail(name, "geoFence", f"'{key}' must be a list")
  for k, p in enumerate(fence.get("polygons", []), start=1):
    where = f"geoFence polygon {k}"
    if not isinstance(p, dict) or not isinstance(p.get("polygon"), list) or len(p["polygon"]) < 3:
      _fail(name, where, "must be an object with a 'polygon' list of at least 3 [lat, lon] points")
    pts = tuple(_latlon_pair(v, name, where, f"point {j}") for j, v in enumerate(p["polygon"], start=1))
    polys.append((where, bool(p.get("inclusion", True)), pts))
  for k, c in enumerate(fence.get("circles", []), start=1):
    where = f"geoFence circle {k}"
    circ = c.get("circle") if isinstance(c, dict) else None
    if not isinstance(circ, dict):
      _fail(name, where, "must be an object with a 'circle': {'center': [lat, lon], 'radius': m}")
    lat, lon = _latlon_pair(circ.get("center"), name, where, "center")
    r = _number(circ.get("radius"), name, where, "radius", "m")
    if not r >= MIN_FENCE_RADIUS_M:
      _fail(name, where, f"radius {r:g} m is below {MIN_FENCE_RADIUS_M:g} m")
    circles.append((where, bool(c.get("inclusion", True)), lat, lon, r))
  rp = doc.get("rallyPoints", {}) or {}
  if not isinstance(rp, dict) or not isinstance(rp.get("points", []), list):
    _fail(name, "rallyPoints", "must be an object with a 'points' list of [lat, lon, alt]")
  for k, v in enumerate(rp.get("points", []), start=1):
    where = f"rally point {k}"
    if not isinstance(v, list) or len(v) != 3:
      _fail(name, where, "must be [lat, lon, alt]")
    rally.append((where,) + tuple(_number(x, name, where, f, f) for x, f in zip(v, ("latitude", "longitude",
                                                                                   "altitude"))))
  return PlanExtras(tuple(polys), tuple(circles), tuple(rally))


def survey_waypoints(polygon_xy, angle_deg: float, spacing: float):
  """Lawn-mower waypoints [2K, 2] (m) covering the polygon polygon_xy [V, 2] (ENU): K = ceil(width / spacing)
  transects along the direction angle_deg clockwise from north, `spacing` m apart and centred on the polygon's
  extent across them (so each covers half a spacing either side; one line through the middle when the polygon is
  narrower than a spacing), each entered and left where it crosses the polygon's outline first and last, flown
  alternately (boustrophedon)."""
  poly = np.asarray(polygon_xy, np.float64)
  a = math.radians(angle_deg)
  d = np.array([math.sin(a), math.cos(a)])      # along the transects (east, north)
  n = np.array([math.cos(a), -math.sin(a)])     # across them
  across = poly @ n
  lo, hi = float(across.min()), float(across.max())
  k = max(1, math.ceil((hi - lo) / spacing - 1e-6))
  if k > MAX_SURVEY_TRANSECTS:
    raise ValueError(f"{k} transects (more than {MAX_SURVEY_TRANSECTS}): spacing {spacing:g} m is too small for a "
                     f"{hi - lo:.0f} m wide polygon")
  offsets = [0.5 * (lo + hi) + spacing * (j - 0.5 * (k - 1)) for j in range(k)]
  a_pts, b_pts = poly, np.roll(poly, -1, axis=0)
  out = []
  for j, o in enumerate(offsets):
    s_a, s_b = a_pts @ n - o, b_pts @ n - o
    ts = []
    for pa, pb, sa, sb in zip(a_pts, b_pts, s_a, s_b):
      if (sa <= 0 < sb) or (sb <= 0 < sa):
        p = pa + (pb - pa) * (sa / (sa - sb))
        ts.append(float(p @ d))
    if len(ts) < 2:
      continue
    t0, t1 = (min(ts), max(ts)) if j % 2 == 0 else (max(ts), min(ts))
    out += [o * n + t0 * d, o * n + t1 * d]
  return np.asarray(out, np.float64).reshape(-1, 2)


def _json_type(v) -> str:
  return {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(type(v), "number")


def _number(v, name: str, where: str, field: str, meaning: str) -> float:
  """A JSON value that must be a finite number, as a float; MissionFileError naming `field` (`meaning`) otherwise."""
  note = f" ({meaning})" if meaning else ""
  if isinstance(v, _JSONConstant):
    _fail(name, where, f"{field}{note} is {v.token}: JSON NaN / Infinity are not allowed (QGC writes null for an "
          "unset value)")
  if isinstance(v, bool) or not isinstance(v, (int, float)):
    _fail(name, where, f"{field} is not a number{note}: {_json_type(v)} {str(v)[:20]}")
  try:
    x = float(v)
  except OverflowError:
    x = math.inf
  if not math.isfinite(x):
    _fail(name, where, f"{field}{note} is not finite: {str(v)[:24]}")
  return x


# ----------------------------------------------------------------------------------------------------------------
# Items -> Mission


def _positioned(it) -> bool:
  return (isinstance(it, SurveyItem) or (it.command in _NAV_COMMANDS and math.isfinite(it.lat)
                                         and math.isfinite(it.lon)))


def resolve_home(home, items, name: str = "<string>"):
  """(home (lat, lon, alt), zero_is_position): a home at lat = lon = 0 replaced by the first positioned item's lat/lon
  (a one-line MissionFileWarning), see the module docstring; zero_is_position: lat = lon = 0 is a real position."""
  if not (home[0] == 0.0 and home[1] == 0.0):
    return tuple(home), False
  first = next((it for it in items if _positioned(it)), None)
  if first is None:
    _fail(name, "", "home position has lat = lon = 0 and no item has a position to take it from")
  lat, lon = first.polygon[0] if isinstance(first, SurveyItem) else (first.lat, first.lon)
  zero = lat == 0.0 and lon == 0.0
  warnings.warn(f"{name}: home at lat = lon = 0 (no home known): home taken from {first.where} at lat {lat:.7f}, "
                f"lon {lon:.7f}" + (" (a local frame around 0, 0: zero coordinates are positions)" if zero else ""),
                MissionFileWarning, stacklevel=3)
  return (float(lat), float(lon), float(home[2])), zero


def items_to_mission(home, items, vehicle: str, cfg: MissionConfig, name: str = "<string>",
                     max_episode_s: float | None = None, strict: bool = False, max_waypoints: int | None = None,
                     zero_is_position: bool | None = None) -> Mission:
  """Interpret parsed items (see module docstring) as a Mission for `vehicle` ("drone" | "rover").

  max_episode_s: the episode cap the mission must fit in (s; EnvConfig's default if None); a longer nominal duration
  warns (MissionFileWarning) or, with strict=True, raises MissionFileError. max_waypoints: the most waypoints
  accepted (MAX_FILE_WAYPOINTS if None). zero_is_position: `resolve_home`'s flag when home is already resolved
  (None: resolved here)."""
  rover = vehicle == "rover"
  limit = MAX_FILE_WAYPOINTS if max_waypoints is None else int(max_waypoints)
  if zero_is_position is None:
    home, zero_is_position = resolve_home(home, items, name)
  home_lat, home_lon, home_alt = home
  if not (-90 <= home_lat <= 90 and -180 <= home_lon <= 180):
    _fail(name, "", f"home position lat {home_lat}, lon {home_lon} is outside [-90, 90] x [-180, 180] degrees")
  if not MIN_HOME_AMSL_M <= home_alt <= MAX_HOME_AMSL_M:
    _fail(name, "", f"home altitude {home_alt} m AMSL is outside [{MIN_HOME_AMSL_M:g}, {MAX_HOME_AMSL_M:g}] m")
  wps = []          # [x, y, z] relative to home
  takeoff_alt = None
  loiter_wp, loiter_time, loiter_radius = -1, 0.0, cfg.loiter_radius
  land = 0.0
  speeds = set()
  ended_by = None   # command that must end the mission

  def altitude(it):
    if not math.isfinite(it.alt):
      _fail(name, it.where, f"{COMMAND_NAMES[it.command]} without altitude")
    if it.frame in _GLOBAL_FRAMES:
      return it.alt - home_alt
    if it.frame in _RELATIVE_FRAMES:
      return it.alt
    _fail(name, it.where, f"unsupported frame {it.frame} (use 0/5 global or 3/6 relative altitude)")

  def height(it):
    """Height above home of a drone item, checked to be above the ground and below MAX_ALTITUDE_M."""
    z = float(altitude(it))
    frame = f" (frame {it.frame}: {it.alt:g} m AMSL, home at {home_alt:g} m)" if it.frame in _GLOBAL_FRAMES else ""
    if not z > 0:
      _fail(name, it.where, f"{COMMAND_NAMES[it.command]} altitude {z:.2f} m above home{frame} is not above the "
            "ground (must be > 0)")
    if z > MAX_ALTITUDE_M:
      _fail(name, it.where, f"{COMMAND_NAMES[it.command]} altitude {z:.2f} m above home{frame} is above "
            f"{MAX_ALTITUDE_M:g} m")
    return z

  def position(it, with_altitude=True):
    cname = COMMAND_NAMES[it.command]
    if not (math.isfinite(it.lat) and math.isfinite(it.lon)):
      _fail(name, it.where, f"{cname} without coordinates")
    if not (-90 <= it.lat <= 90 and -180 <= it.lon <= 180):
      _fail(name, it.where, f"{cname} lat {it.lat}, lon {it.lon} is outside [-90, 90] x [-180, 180] degrees")
    x, y = (float(v) for v in latlon_to_enu(it.lat, it.lon, home_lat, home_lon))
    if math.hypot(x, y) > MAX_HOME_DISTANCE_M:
      _fail(name, it.where, f"{cname} at lat {it.lat}, lon {it.lon} is {math.hypot(x, y) / 1000:.1f} km from home "
            f"(at most {MAX_HOME_DISTANCE_M / 1000:g} km)")
    if rover:
      altitude(it)
      return [x, y, 0.0]
    return [x, y, height(it) if with_altitude else 0.0]

  def has_latlon(it):
    return (math.isfinite(it.lat) and math.isfinite(it.lon)
            and (zero_is_position or not (it.lat == 0.0 and it.lon == 0.0)))

  def survey(it):
    """The survey's lawn-mower waypoints, [x, y, z] each."""
    for j, (lat, lon) in enumerate(it.polygon, start=1):
      if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        _fail(name, it.where, f"survey polygon point {j} lat {lat}, lon {lon} is outside [-90, 90] x [-180, 180]")
    xy = np.stack(latlon_to_enu([p[0] for p in it.polygon], [p[1] for p in it.polygon], home_lat, home_lon), -1)
    if np.max(np.hypot(xy[:, 0], xy[:, 1])) > MAX_HOME_DISTANCE_M:
      _fail(name, it.where, f"survey polygon reaches farther than {MAX_HOME_DISTANCE_M / 1000:g} km from home")
    try:
      pts = survey_waypoints(xy, it.angle_deg, it.spacing_m)
    except ValueError as e:
      _fail(name, it.where, f"survey: {e}")
    if not len(pts):
      _fail(name, it.where, "survey polygon has no area to cover (degenerate polygon)")
    z = 0.0
    if not rover:
      z = it.alt if it.relative else it.alt - home_alt
      if not 0 < z <= MAX_ALTITUDE_M:
        _fail(name, it.where, f"survey altitude {z:.2f} m above home is not in (0, {MAX_ALTITUDE_M:g}] m")
    return [[float(x), float(y), float(z)] for x, y in pts]

  def current_alt():
    return wps[-1][2] if wps else (takeoff_alt or 0.0)

  for it in items:
    if isinstance(it, SurveyItem):
      if ended_by is not None:
        _fail(name, it.where, f"survey after {ended_by}, which ends the mission")
      wps.extend(survey(it))
      if len(wps) > limit:
        _fail(name, it.where, f"too many waypoints (more than {limit}; the limit is load_mission's max_waypoints, "
              "--max-waypoints on the command line)")
      continue
    cmd = it.command
    if cmd not in COMMAND_NAMES:
      _fail(name, it.where, f"unsupported command {cmd} (supported: {sorted(COMMAND_NAMES)})")
    cname = COMMAND_NAMES[cmd]
    if ended_by is not None and cmd in _NAV_COMMANDS:
      _fail(name, it.where, f"{cname} after {ended_by}, which ends the mission")
    if rover and cmd in (CMD_TAKEOFF, CMD_LAND, CMD_LOITER_TIME, CMD_LOITER_UNLIM):
      _fail(name, it.where, f"{cname} is not supported for rovers")
    if cmd == CMD_CHANGE_SPEED:
      if not 0 < it.params[1] <= MAX_SPEED_M_S:
        _fail(name, it.where, f"DO_CHANGE_SPEED speed must be > 0 and <= {MAX_SPEED_M_S:g} m/s, got {it.params[1]}")
      speeds.add(round(it.params[1], 6))
      if len(speeds) > 1:
        _fail(name, it.where, "only one DO_CHANGE_SPEED speed per mission is supported")
      continue
    if cmd == CMD_TAKEOFF:
      if wps or takeoff_alt is not None:
        _fail(name, it.where, "NAV_TAKEOFF must come before any waypoint (and only once)")
      takeoff_alt = height(it)
      continue
    if cmd == CMD_WAYPOINT:
      if not has_latlon(it):
        _fail(name, it.where, "NAV_WAYPOINT without coordinates (lat = lon = 0)")
      wps.append(position(it))
    elif cmd in (CMD_LOITER_TIME, CMD_LOITER_UNLIM):
      if loiter_wp >= 0:
        _fail(name, it.where, "only one loiter item per mission is supported")
      if has_latlon(it):
        wps.append(position(it))
      elif not wps:
        _fail(name, it.where, f"{cname} in place before any waypoint")
      loiter_wp = len(wps) - 1
      if cmd == CMD_LOITER_TIME:
        if not 0 < it.params[0] <= MAX_LOITER_S:
          _fail(name, it.where, f"NAV_LOITER_TIME time (param1) must be > 0 s and <= {MAX_LOITER_S:g} s, "
                f"got {it.params[0]}")
        loiter_time = it.params[0]
      else:
        loiter_time = float(cfg.loiter_time[1])
        ended_by = cname
      if abs(it.params[2]) > MAX_LOITER_RADIUS_M:
        _fail(name, it.where, f"{cname} radius (param3) {it.params[2]} m is wider than {MAX_LOITER_RADIUS_M:g} m")
      if it.params[2] != 0:
        loiter_radius = abs(it.params[2])
    elif cmd == CMD_LAND:
      if has_latlon(it):
        p = position(it, with_altitude=False)
        p[2] = current_alt()
        if not wps or math.dist(p[:2], wps[-1][:2]) > cfg.acceptance_radius:
          wps.append(p)
      elif not wps:
        _fail(name, it.where, "NAV_LAND in place before any waypoint")
      land, ended_by = 1.0, cname
    elif cmd == CMD_RTL:
      wps.append([0.0, 0.0, 0.0 if rover else current_alt()])
      land, ended_by = (0.0 if rover else 1.0), cname
    if len(wps) > limit:
      _fail(name, it.where, f"too many waypoints (more than {limit}; the limit is load_mission's max_waypoints, "
            "--max-waypoints on the command line)")

  if not wps:
    _fail(name, "", "empty mission (no navigation waypoints)")
  if rover:
    takeoff_alt = 0.0
  elif takeoff_alt is None:
    takeoff_alt = wps[0][2]
  n = len(wps)
  arr = np.zeros((max(cfg.max_waypoints, n), 3), np.float32)
  arr[:n] = wps
  arr[n:] = wps[-1]
  cruise = next(iter(speeds)) if speeds else 0.5 * (cfg.cruise_speed[0] + cfg.cruise_speed[1])
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  home_v, wp_v, n_v = f32(np.zeros(3)), f32(arr), jnp.int32(n)
  lw, lt, ld, to = jnp.int32(loiter_wp), f32(loiter_time), f32(land), f32(takeoff_alt)
  window_open, deadline, duration = mission_timing(home_v, wp_v, n_v, to, f32(cruise), lw, lt, ld, cfg)
  cap = DEFAULT_EPISODE_CAP_S if max_episode_s is None else float(max_episode_s)
  if not float(duration) <= cap:
    problem = (f"the mission's nominal duration {float(duration):.0f} s exceeds the episode cap of {cap:g} s "
               "(EnvConfig.max_episode_s): it cannot finish within an episode")
    if strict:
      _fail(name, "", problem)
    warnings.warn(f"{name}: {problem}", MissionFileWarning, stacklevel=3)
  return Mission(home=home_v, waypoints=wp_v, n_waypoints=n_v, window_open=f32(window_open),
                 deadline=f32(deadline), takeoff_alt=to, cruise_speed=f32(cruise),
                 acceptance_radius=f32(cfg.acceptance_radius), loiter_wp=lw, loiter_time=lt,
                 loiter_radius=f32(loiter_radius), land=ld, nominal_duration=f32(duration))


def _config(vehicle, cfg):
  if vehicle not in VEHICLES:
    raise ValueError(f"vehicle must be one of {', '.join(VEHICLES)}, got {vehicle!r}")
  cfg = cfg if cfg is not None else (MissionConfig.rover() if vehicle == "rover" else MissionConfig.drone())
  if cfg.vehicle != vehicle:
    raise ValueError(f"cfg is for a {cfg.vehicle}, but vehicle={vehicle!r}")
  return cfg


def extras_to_geofence(extras: PlanExtras, home, vehicle: str, name: str = "<string>"):
  """(Geofence, rally points [R, 3] m) of a .plan's PlanExtras about `home` (lat, lon, alt AMSL; resolved). Every
  point must lie within MAX_HOME_DISTANCE_M of home; rally altitudes are above home (0 for rovers). Inclusion zones
  combine as the vehicle's autopilot does (envs.geofence: PX4 for the drone, ArduPilot for the rover)."""
  home_lat, home_lon = home[0], home[1]

  def xy(where, lat, lon):
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
      _fail(name, where, f"lat {lat}, lon {lon} is outside [-90, 90] x [-180, 180] degrees")
    x, y = (float(v) for v in latlon_to_enu(lat, lon, home_lat, home_lon))
    if math.hypot(x, y) > MAX_HOME_DISTANCE_M:
      _fail(name, where, f"lat {lat}, lon {lon} is {math.hypot(x, y) / 1000:.1f} km from home (at most "
            f"{MAX_HOME_DISTANCE_M / 1000:g} km)")
    return [x, y]

  polys = [[xy(where, lat, lon) for lat, lon in pts] for where, _, pts in extras.polygons]
  circles = [xy(where, lat, lon) + [r] for where, _, lat, lon, r in extras.circles]
  fence = geofence_lib.make_geofence(polys, [inc for _, inc, _ in extras.polygons], circles,
                                     [inc for _, inc, *_ in extras.circles], any_inclusion=vehicle == "drone")
  rally = np.asarray([xy(where, lat, lon) + [0.0 if vehicle == "rover" else float(alt)]
                      for where, lat, lon, alt in extras.rally], np.float32).reshape(-1, 3)
  return fence, rally


def loads_plan(text: str, fmt: str, vehicle: str, cfg: MissionConfig | None = None, name: str = "<string>",
               max_episode_s: float | None = None, strict: bool = False, max_waypoints: int | None = None) -> Plan:
  """Load a Plan (mission, geofence, rally points) from file contents; fmt: "wpl" (QGC WPL 110: no geofence or rally
  points) or "plan" (.plan JSON). max_episode_s, strict, max_waypoints: see `items_to_mission`."""
  cfg = _config(vehicle, cfg)
  if fmt == "wpl":
    home, items = parse_wpl(text, name)
    extras = PlanExtras()
  elif fmt == "plan":
    home, items, extras = parse_plan(text, name, extras=True)
  else:
    raise ValueError(f"fmt must be 'wpl' or 'plan', got {fmt!r}")
  home, zero = resolve_home(home, items, name)
  mission = items_to_mission(home, items, vehicle, cfg, name, max_episode_s, strict, max_waypoints, zero)
  fence, rally = extras_to_geofence(extras, home, vehicle, name)
  return Plan(mission, fence, rally)


def loads_mission(text: str, fmt: str, vehicle: str, cfg: MissionConfig | None = None,
                  name: str = "<string>", max_episode_s: float | None = None, strict: bool = False,
                  max_waypoints: int | None = None) -> Mission:
  """The Mission of `loads_plan` (its geofence and rally points dropped)."""
  return loads_plan(text, fmt, vehicle, cfg, name, max_episode_s, strict, max_waypoints).mission


def load_plan(path, vehicle: str, cfg: MissionConfig | None = None, max_episode_s: float | None = None,
              strict: bool = False, max_waypoints: int | None = None) -> Plan:
  """Load a `.plan` (JSON) or QGC WPL 110 (`.waypoints` / `.txt` / `.mission`) file as a Plan: the Mission (home at
  the origin), the .plan's geofence and rally points.

  vehicle: "drone" | "rover"; cfg: timing/acceptance defaults (MissionConfig.drone()/rover() if None).
  max_episode_s: the episode cap the mission must fit in (s; EnvConfig's default if None); strict: a mission that
  cannot finish within it raises instead of warning; max_waypoints: the most waypoints accepted (MAX_FILE_WAYPOINTS).
  The format is JSON for a .plan file or text starting with '{' or '[' (a JSON plan), else WPL. Raises
  MissionFileError on bad files (see the module docstring for the checks).
  """
  path = os.fspath(path)
  name = os.path.basename(path)
  try:
    with open(path, encoding="utf-8-sig") as f:
      text = f.read()
  except (OSError, UnicodeDecodeError) as e:
    raise MissionFileError(f"{name}: cannot read: {e}") from None
  is_json = os.path.splitext(path)[1].lower() == ".plan" or text.lstrip()[:1] in ("{", "[")
  return loads_plan(text, "plan" if is_json else "wpl", vehicle, cfg, name, max_episode_s, strict, max_waypoints)


def load_mission(path, vehicle: str, cfg: MissionConfig | None = None, max_episode_s: float | None = None,
                 strict: bool = False, max_waypoints: int | None = None) -> Mission:
  """The Mission of `load_plan` (see there)."""
  return load_plan(path, vehicle, cfg, max_episode_s, strict, max_waypoints).mission


# ----------------------------------------------------------------------------------------------------------------
# Writer (tests, examples, exporting generated missions to QGroundControl)


def to_wpl(mission: Mission, home_lat: float, home_lon: float, home_alt: float = 0.0) -> str:
  """QGC WPL 110 text for a single (unbatched) Mission: home, take-off (if any), speed, waypoints (loiter as
  NAV_LOITER_TIME), NAV_LAND at the last waypoint if land. Altitudes relative (frame 3); lat/lon with 9 decimals."""
  m = {k: np.asarray(v) for k, v in vars(mission).items()}
  rows = [(0, 1, 0, CMD_WAYPOINT, 0, 0, 0, 0, home_lat, home_lon, home_alt)]

  def add(cmd, frame, params, lat=0.0, lon=0.0, alt=0.0):
    rows.append((len(rows), 0, frame, cmd, *params, lat, lon, alt))

  if m["takeoff_alt"] > 0:
    add(CMD_TAKEOFF, 3, (0, 0, 0, 0), 0.0, 0.0, float(m["takeoff_alt"]))
  add(CMD_CHANGE_SPEED, _MISSION_FRAME, (1, float(m["cruise_speed"]), -1, 0))
  n = int(m["n_waypoints"])
  for k in range(n):
    x, y, z = (float(v) for v in m["waypoints"][k])
    lat, lon = enu_to_latlon(x - m["home"][0], y - m["home"][1], home_lat, home_lon)
    if k == int(m["loiter_wp"]):
      add(CMD_LOITER_TIME, 3, (float(m["loiter_time"]), 0, float(m["loiter_radius"]), 0), float(lat), float(lon), z)
    else:
      add(CMD_WAYPOINT, 3, (0, 0, 0, 0), float(lat), float(lon), z)
  if m["land"] > 0.5:
    add(CMD_LAND, 3, (0, 0, 0, 0), float(lat), float(lon), 0.0)
  out = [WPL_HEADER]
  for r in rows:
    out.append("\t".join([str(int(v)) for v in r[:4]] + [f"{float(v):.6f}" for v in r[4:8]]
                         + [f"{float(r[8]):.9f}", f"{float(r[9]):.9f}", f"{float(r[10]):.6f}", "1"]))
  return "\n".join(out) + "\n"
