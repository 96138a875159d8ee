"""Procedural operating environments (the paper's 10 worlds) as analytic shapes, and their geometric signals.

Obstacles and geofences are convex prisms standing on the ground (vertical cylinders and oriented boxes, see
`envs.geometry`), NOT MuJoCo geoms: every distance is an exact jitted query. A `World` has fixed-size arrays + masks
so a batch of worlds is one pytree (vmap over episodes, and over presets: `generate_world` accepts a traced preset id).

Placement (`generate_world`): obstacles are sampled in a corridor along the mission's horizontal legs, so they
matter, then every candidate is checked EXACTLY against the whole nominal path (take-off and landing verticals,
all legs, and the loiter disc) and DROPPED if any surface is closer than `clearance`; candidates are oversampled 2x
and the first valid ones fill the slots. Nothing is pushed, so the distributions of sizes stay as configured.
Fences and the operating boundary likewise keep `clearance`; the ceiling is raised above the path when needed.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import geofence as geofence_lib
from envs import geometry as geo
from envs.missions import Mission, UniformPool, final_waypoint, landing_point, mission_leg, \
  path_polyline, takeoff_point
from specguard_jax.sensors import SURFACES

MAX_CYLINDERS = 24
MAX_BOXES = 24
MAX_FENCES = 6
MAX_KINDS = 4
"""Obstacle kinds per shape type in one preset (cylinder kinds and box kinds separately)."""
DEFAULT_CLEARANCE = 9.0
"""m: obstacle distance spec (5 m) + margin for tracking error / corner cutting."""
SIGNAL_CAP = 100.0
"""m: obstacle_distance, fence_margin, fence_h and fence_v are capped at this value."""
NO_CEILING = 1e3
FENCE_HEIGHT = 120.0
"""m: keep-out prisms (private properties) are this tall, i.e. no over-flight at mission altitudes."""
OVERSAMPLE = 2
_FAR_POS = 1e4  # where unused slots are parked (also masked out)
GEOFENCE_KINDS = ("properties", "boundary", "indoor")


@struct.dataclass
class World:
  """One operating environment (add leading axes for a batch). Units m, m/s; frames ENU, ground z = 0.

  cylinders: [MAX_CYLINDERS, 4] (x, y, radius, height); cylinder_mask: [MAX_CYLINDERS] bool.
  boxes: [MAX_BOXES, 6] (cx, cy, half_x, half_y, yaw, height); box_mask: [MAX_BOXES] bool.
  fences: [MAX_FENCES, 6] keep-out prisms encoded like boxes (height FENCE_HEIGHT); fence_mask: [MAX_FENCES] bool.
  box_axes: [MAX_BOXES, 2], fence_axes: [MAX_FENCES, 2] (cos yaw, sin yaw) of boxes / fences (`make_world` fills them,
    geometry.prism_axes): the env step's queries read them instead of taking 30 cosines and sines per env and step.
  boundary: [4] operating rectangle (xmin, xmax, ymin, ymax); boundary_on: [] bool, outside is forbidden if true.
  ceiling: [] max allowed altitude (NO_CEILING = 1e3 outdoors).
  wind_mean: [3] mean wind velocity (horizontal), m/s; gust_std: [] std of gusts per axis, m/s.
  preset_id: [] int32 index into PRESET_NAMES (-1: custom preset).
  surface: [] int32 index into specguard_jax.sensors.SURFACES, the ground's texture (optical-flow dropouts).
  geofence: the mission's own geofence zones (envs.geofence; a QGC plan's geoFence, a parameter file's home fence);
    empty (zero-size arrays, no cost) for generated missions.
  rally_points: [R, 3] the mission's rally points (a QGC plan's rallyPoints), m, where recovery controllers may
    go to hold (specguard_jax.autopilot.fallback); R = 0 without.
  """

  cylinders: jnp.ndarray
  cylinder_mask: jnp.ndarray
  boxes: jnp.ndarray
  box_mask: jnp.ndarray
  fences: jnp.ndarray
  fence_mask: jnp.ndarray
  box_axes: jnp.ndarray
  fence_axes: jnp.ndarray
  boundary: jnp.ndarray
  boundary_on: jnp.ndarray
  ceiling: jnp.ndarray
  wind_mean: jnp.ndarray
  gust_std: jnp.ndarray
  preset_id: jnp.ndarray
  surface: jnp.ndarray
  geofence: geofence_lib.Geofence = struct.field(default_factory=geofence_lib.empty_geofence)
  rally_points: jnp.ndarray = struct.field(default_factory=lambda: jnp.zeros((0, 3), jnp.float32))


@dataclasses.dataclass(frozen=True)
class ObstacleKind:
  """A kind of obstacle and its analytic stand-in. Ranges (low, high) in m, sampled uniformly.

  shape: "cylinder" (radius, height) or "box" (half_x along the box yaw, half_y across, height).
  density: expected count per hectare of the obstacle corridor (see WorldPreset.corridor).
  """

  name: str
  shape: str
  density: float
  height: tuple
  radius: tuple = (0.0, 0.0)
  half_x: tuple = (0.0, 0.0)
  half_y: tuple = (0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class WorldPreset:
  """Distribution of one operating environment (paper, Appendix "Operating Environments").

  corridor: obstacles are placed with their surface 0..corridor m beside a leg's horizontal line (tall ones at least
    `clearance` beside); corridor area (2 * corridor * horizontal path length) times density = expected count,
    truncated to the slots. yaw_jitter_deg: box yaw = leg heading + U(-j, j) (street-aligned buildings).
  geofence: "properties" (keep-out prisms beside the route, n_fences of them), "boundary" (outside the operating
    boundary is forbidden) or "indoor" (walls = operating boundary, plus a ceiling).
  boundary_margin: the operating rectangle is the path's bounding box grown by U(margin) on each side.
  ceiling: (low, high) or None; raised to the path top + clearance if lower.
  wind_speed: mean horizontal wind magnitude range (direction uniform); gust_std: gust std range, m/s.
  surface: the ground's texture under the routes, one of specguard_jax.sensors.SURFACES (optical-flow dropouts).
  """

  name: str
  label: str
  description: str
  kinds: tuple
  geofence: str
  corridor: float = 30.0
  yaw_jitter_deg: float = 10.0
  n_fences: tuple = (0, 0)
  fence_half_along: tuple = (10.0, 25.0)
  fence_half_across: tuple = (8.0, 15.0)
  fence_gap: tuple = (0.0, 15.0)
  boundary_margin: tuple = (20.0, 40.0)
  ceiling: tuple | None = None
  wind_speed: tuple = (0.0, 3.0)
  gust_std: tuple = (0.0, 0.5)
  surface: str = "grass"

  def __post_init__(self):
    if self.surface not in SURFACES:
      raise ValueError(f"{self.name}: surface must be one of {SURFACES}, got {self.surface!r}")
    if self.geofence not in GEOFENCE_KINDS:
      raise ValueError(f"{self.name}: geofence must be one of {GEOFENCE_KINDS}, got {self.geofence!r}")
    for shape in ("cylinder", "box"):
      if sum(k.shape == shape for k in self.kinds) > MAX_KINDS:
        raise ValueError(f"{self.name}: more than {MAX_KINDS} {shape} kinds")
    if any(k.shape not in ("cylinder", "box") for k in self.kinds):
      raise ValueError(f"{self.name}: obstacle shapes must be 'cylinder' or 'box'")
    if not 0 <= self.n_fences[0] <= self.n_fences[1] <= MAX_FENCES:
      raise ValueError(f"{self.name}: n_fences must be within [0, {MAX_FENCES}]")

  def density(self, shape: str) -> float:
    """Total obstacles per hectare of the given shape."""
    return sum(k.density for k in self.kinds if k.shape == shape)


def _cyl(name, density, radius, height):
  return ObstacleKind(name, "cylinder", density, height, radius=radius)


def _box(name, density, half_x, half_y, height):
  return ObstacleKind(name, "box", density, height, half_x=half_x, half_y=half_y)


_TREE = _cyl("tree", 5.0, (1.5, 4.0), (6.0, 15.0))
_POLE = _cyl("electric pole", 2.0, (0.15, 0.3), (8.0, 12.0))
_PYLON = _cyl("power-line pylon", 0.5, (2.0, 3.0), (20.0, 30.0))
_STREETLIGHT = _cyl("streetlight", 4.0, (0.15, 0.25), (6.0, 10.0))
_SIGNAL = _cyl("traffic signal", 2.0, (0.2, 0.3), (5.0, 7.0))
_BENCH = _box("park bench", 3.0, (0.8, 1.2), (0.3, 0.4), (0.8, 1.0))

PRESETS = {p.name: p for p in (
  WorldPreset(
    "suburban_residential", "A", "houses and streets; trees, power lines, electric poles; private properties fenced",
    (_TREE, _POLE, _PYLON, _box("house", 3.0, (4.0, 8.0), (4.0, 7.0), (6.0, 10.0))),
    geofence="properties", n_fences=(3, 6), wind_speed=(0.0, 3.0), gust_std=(0.0, 0.5),
    surface="grass"),
  WorldPreset(
    "suburban_streets", "B", "busier suburban commercial streets; trees, electric poles, power lines",
    (dataclasses.replace(_TREE, density=4.0), dataclasses.replace(_POLE, density=3.0),
     dataclasses.replace(_PYLON, density=0.6), _box("shop", 3.0, (6.0, 12.0), (5.0, 10.0), (5.0, 12.0))),
    geofence="properties", n_fences=(3, 6), wind_speed=(0.0, 3.0), gust_std=(0.0, 0.5),
    surface="asphalt"),
  WorldPreset(
    "urban_city_areas", "C", "multi-storey buildings, commercial complexes; trees, streetlights, traffic signals",
    (_cyl("tree", 3.0, (1.5, 3.0), (6.0, 12.0)), _STREETLIGHT, _SIGNAL,
     _box("building", 4.0, (8.0, 20.0), (8.0, 15.0), (15.0, 45.0))),
    geofence="properties", n_fences=(4, 6), wind_speed=(0.0, 4.0), gust_std=(0.2, 0.8),
    surface="concrete"),
  WorldPreset(
    "urban_city_streets", "D", "narrow busy streets; trees, streetlights, shop signs, buildings",
    (_cyl("tree", 3.0, (1.5, 3.0), (6.0, 12.0)), dataclasses.replace(_STREETLIGHT, density=5.0),
     _box("shop sign", 3.0, (0.5, 2.0), (0.1, 0.4), (4.0, 8.0)),
     _box("building", 5.0, (6.0, 15.0), (6.0, 12.0), (15.0, 40.0))),
    geofence="properties", n_fences=(4, 6), corridor=25.0, wind_speed=(0.0, 4.0), gust_std=(0.3, 1.0),
    surface="asphalt"),
  WorldPreset(
    "urban_park", "E", "park paths and amenities; trees, benches, playground equipment",
    (_cyl("tree", 10.0, (2.0, 5.0), (8.0, 20.0)), _cyl("lamp post", 2.0, (0.1, 0.2), (4.0, 6.0)), _BENCH,
     _box("playground", 1.0, (2.0, 6.0), (2.0, 5.0), (2.0, 5.0))),
    geofence="boundary", yaw_jitter_deg=180.0, wind_speed=(0.0, 4.0), gust_std=(0.0, 0.6),
    surface="grass"),
  WorldPreset(
    "urban_green_areas", "F", "streets cutting through parks; trees, benches, streetlights, traffic lights",
    (_cyl("tree", 7.0, (2.0, 5.0), (8.0, 20.0)), dataclasses.replace(_STREETLIGHT, density=2.0),
     dataclasses.replace(_SIGNAL, name="traffic light", density=1.0), dataclasses.replace(_BENCH, density=2.0)),
    geofence="boundary", yaw_jitter_deg=90.0, wind_speed=(0.0, 4.0), gust_std=(0.1, 0.7),
    surface="grass"),
  WorldPreset(
    "urban_high_rise", "G", "downtown high-rises; construction cranes (mast), traffic poles, light posts",
    (_cyl("crane mast", 0.5, (2.0, 3.0), (40.0, 80.0)), _cyl("traffic pole", 3.0, (0.2, 0.3), (5.0, 8.0)),
     _cyl("light post", 3.0, (0.15, 0.25), (8.0, 12.0)),
     _box("high-rise", 4.0, (10.0, 25.0), (10.0, 20.0), (60.0, 150.0))),
    geofence="properties", n_fences=(4, 6), wind_speed=(1.0, 6.0), gust_std=(0.5, 1.5),
    surface="concrete"),
  WorldPreset(
    "manufacturing_plant", "H", "indoor plant; pillars, machinery, storage containers, conveyor belts",
    (_cyl("pillar", 3.0, (0.3, 0.6), (40.0, 40.0)), _box("machinery", 6.0, (1.5, 5.0), (1.0, 4.0), (2.0, 6.0)),
     _box("container", 4.0, (3.0, 6.1), (1.2, 1.25), (2.6, 5.2)),
     _box("conveyor belt", 2.0, (8.0, 20.0), (0.5, 1.0), (1.0, 1.5))),
    geofence="indoor", yaw_jitter_deg=5.0, boundary_margin=(18.0, 25.0), ceiling=(25.0, 30.0),
    wind_speed=(0.0, 0.0), gust_std=(0.0, 0.0),
    surface="indoor_floor"),
  WorldPreset(
    "open_mountain", "I", "mountainous terrain; rocks, boulders, fences, sparse trees; windy",
    (_cyl("rock", 3.0, (1.0, 4.0), (1.0, 6.0)), _cyl("tree", 1.0, (1.5, 3.0), (5.0, 12.0)),
     _box("boulder", 2.0, (2.0, 6.0), (2.0, 5.0), (2.0, 10.0)),
     _box("fence", 1.0, (10.0, 30.0), (0.05, 0.15), (1.2, 2.0))),
    geofence="boundary", yaw_jitter_deg=180.0, wind_speed=(3.0, 8.0), gust_std=(1.0, 2.5),
    surface="snow"),
  WorldPreset(
    "open_beach", "J", "coastline; power lines on electric posts, pylons, rocky cliffs; windy",
    (_cyl("electric post", 3.0, (0.15, 0.3), (8.0, 12.0)), _cyl("pylon", 0.5, (2.0, 3.0), (25.0, 40.0)),
     _cyl("rock", 1.0, (1.0, 3.0), (1.0, 4.0)), _box("rocky cliff", 1.0, (10.0, 30.0), (5.0, 15.0), (15.0, 40.0))),
    geofence="boundary", yaw_jitter_deg=30.0, wind_speed=(3.0, 7.0), gust_std=(0.8, 2.0),
    surface="sand"),
)}
PRESET_NAMES = tuple(PRESETS)
"""The 10 world names; index = World.preset_id."""
DEFAULT_WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")
"""The worlds the trainer trains in by default (TrainConfig.env.worlds) and evaluate.py flies without a run."""


# ----------------------------------------------------------------------------------------------------------------
# Preset tables: presets as stacked numpy arrays so a traced preset id can select one inside jit/vmap.


@struct.dataclass
class _PresetTable:
  """Array form of presets, leading axis P (presets); K = MAX_KINDS kinds per shape, ranges as [..., 2]."""

  cyl_density: np.ndarray   # [P, K]
  cyl_radius: np.ndarray    # [P, K, 2]
  cyl_height: np.ndarray    # [P, K, 2]
  box_density: np.ndarray   # [P, K]
  box_hx: np.ndarray        # [P, K, 2]
  box_hy: np.ndarray        # [P, K, 2]
  box_height: np.ndarray    # [P, K, 2]
  corridor: np.ndarray      # [P]
  yaw_jitter: np.ndarray    # [P] rad
  geofence: np.ndarray      # [P] int32 index into GEOFENCE_KINDS
  n_fences: np.ndarray      # [P, 2] int32
  fence_along: np.ndarray   # [P, 2]
  fence_across: np.ndarray  # [P, 2]
  fence_gap: np.ndarray     # [P, 2]
  boundary_margin: np.ndarray  # [P, 2]
  ceiling: np.ndarray       # [P, 2] (NO_CEILING if none)
  wind_speed: np.ndarray    # [P, 2]
  gust_std: np.ndarray      # [P, 2]
  surface: np.ndarray       # [P] int32 index into SURFACES


def _preset_table(presets) -> _PresetTable:
  def kinds(p, shape, fields):
    ks = [k for k in p.kinds if k.shape == shape]
    dens = np.zeros(MAX_KINDS, np.float32)
    ranges = {f: np.zeros((MAX_KINDS, 2), np.float32) for f in fields}
    for i, k in enumerate(ks):
      dens[i] = k.density
      for f in fields:
        ranges[f][i] = getattr(k, f)
    return dens, ranges

  rows = []
  for p in presets:
    cd, cr = kinds(p, "cylinder", ("radius", "height"))
    bd, br = kinds(p, "box", ("half_x", "half_y", "height"))
    rows.append(dict(
      cyl_density=cd, cyl_radius=cr["radius"], cyl_height=cr["height"], box_density=bd, box_hx=br["half_x"],
      box_hy=br["half_y"], box_height=br["height"], corridor=np.float32(p.corridor),
      yaw_jitter=np.float32(math.radians(p.yaw_jitter_deg)), geofence=np.int32(GEOFENCE_KINDS.index(p.geofence)),
      n_fences=np.array(p.n_fences if p.geofence == "properties" else (0, 0), np.int32),
      fence_along=np.array(p.fence_half_along, np.float32), fence_across=np.array(p.fence_half_across, np.float32),
      fence_gap=np.array(p.fence_gap, np.float32), boundary_margin=np.array(p.boundary_margin, np.float32),
      ceiling=np.array(p.ceiling if p.ceiling is not None else (NO_CEILING, NO_CEILING), np.float32),
      wind_speed=np.array(p.wind_speed, np.float32), gust_std=np.array(p.gust_std, np.float32),
      surface=np.int32(SURFACES.index(p.surface))))
  return _PresetTable(**{k: np.stack([r[k] for r in rows]) for k in rows[0]})


_TABLE = _preset_table(PRESETS.values())  # immutable numpy constants


def _resolve(preset):
  """-> (table, row index (int or traced), preset_id) for a name, WorldPreset, int or traced int."""
  if isinstance(preset, str):
    if preset not in PRESETS:
      raise ValueError(f"unknown world preset {preset!r}; choose one of {PRESET_NAMES}")
    i = PRESET_NAMES.index(preset)
    return _TABLE, i, i
  if isinstance(preset, WorldPreset):
    if PRESETS.get(preset.name) == preset:
      i = PRESET_NAMES.index(preset.name)
      return _TABLE, i, i
    return _preset_table([preset]), 0, -1
  return _TABLE, preset, preset  # int or traced int32 id


# ----------------------------------------------------------------------------------------------------------------
# Generation


def _uniform(r: UniformPool, rng_lohi, shape=()):
  """U(lo, hi) with rng_lohi [..., 2] broadcast against shape."""
  return rng_lohi[..., 0] + r.take(shape) * (rng_lohi[..., 1] - rng_lohi[..., 0])


def _path_clear(sdf, pts, mission: Mission, clearance):
  """True iff the convex sdf is >= clearance on the whole mission path (exact; the loiter disc counts as
  loiter_radius extra around the loiter waypoint). Returns [] bool."""
  ok = geo.polyline_clear(sdf, pts, clearance)
  lw = mission.loiter_wp
  loiter_pt = mission.waypoints[jnp.clip(lw, 0, mission.waypoints.shape[0] - 1)]
  return ok & ((lw < 0) | (sdf(loiter_pt) >= clearance + mission.loiter_radius))


def _sample_anchor(r: UniformPool, pts, n):
  """n random points on the horizontal legs of the polyline pts [K, 3] (leg chosen by horizontal length).

  Returns (anchor [n, 3], heading [n] of the leg, rad).
  """
  seg = pts[1:] - pts[:-1]
  hlen = jnp.linalg.norm(seg[:, :2], axis=-1)
  idx = r.categorical(hlen + 1e-6, (n,))
  t = r.take((n,))
  anchor = pts[idx] + t[:, None] * seg[idx]
  heading = jnp.arctan2(seg[idx, 1], seg[idx, 0])
  return anchor, heading


def _compact(cands, valid, n_target, slots, parked):
  """Keep the first n_target valid rows of cands [C, D] in `slots` rows; others parked and masked out."""
  rank = jnp.cumsum(valid) - 1
  keep = valid & (rank < n_target)
  c = cands.shape[0]
  order = jnp.argsort(jnp.where(keep, jnp.arange(c), c + jnp.arange(c)))[:slots]
  mask = keep[order]
  return jnp.where(mask[:, None], cands[order], parked), mask


def _count(r: UniformPool, lam, slots):
  """Integer count with mean lam (stochastic rounding), clipped to [0, slots]."""
  return jnp.clip(jnp.floor(lam + r.take()), 0, slots).astype(jnp.int32)


def generate_world(preset, mission: Mission, rng: jax.Array, clearance: float = DEFAULT_CLEARANCE) -> World:
  """Sample a world of `preset` around `mission`; jittable and vmappable (over mission, rng and a traced preset).

  preset: a name from PRESET_NAMES, a WorldPreset, or an int32 preset id (may be traced: mix presets in one batch).
  clearance: minimum distance (m) from the whole nominal path (incl. take-off/landing verticals and the loiter
    disc) to every obstacle surface, keep-out prism, wall and ceiling. Guaranteed (exact check, violators dropped).
  """
  table, row, preset_id = _resolve(preset)
  p = jax.tree.map(lambda a: jnp.asarray(a)[row], table)
  pts, _ = path_polyline(mission)
  r = UniformPool(rng, 16 * OVERSAMPLE * (MAX_CYLINDERS + MAX_BOXES + MAX_FENCES) + 32)
  clearance = jnp.asarray(clearance, jnp.float32)

  # Operating boundary: path bounding box (+ loiter disc) grown by the margin.
  lw = mission.loiter_wp
  loiter_pt = mission.waypoints[jnp.clip(lw, 0, mission.waypoints.shape[0] - 1)]
  lr = jnp.where(lw >= 0, mission.loiter_radius, 0.0)
  lo = jnp.minimum(jnp.min(pts[:, :2], 0), loiter_pt[:2] - lr)
  hi = jnp.maximum(jnp.max(pts[:, :2], 0), loiter_pt[:2] + lr)
  margin = jnp.maximum(_uniform(r, p.boundary_margin, (4,)), clearance)
  boundary = jnp.stack([lo[0] - margin[0], hi[0] + margin[1], lo[1] - margin[2], hi[1] + margin[3]])
  boundary_on = p.geofence != GEOFENCE_KINDS.index("properties")
  ceiling = _uniform(r, p.ceiling)
  ceiling = jnp.where(ceiling >= NO_CEILING, NO_CEILING, jnp.maximum(ceiling, jnp.max(pts[:, 2]) + clearance))

  seg = pts[1:] - pts[:-1]
  corridor_ha = 2.0 * p.corridor * jnp.sum(jnp.linalg.norm(seg[:, :2], axis=-1)) / 1e4

  def inside_boundary(xy):
    return (xy[:, 0] > boundary[0]) & (xy[:, 0] < boundary[1]) & (xy[:, 1] > boundary[2]) & (xy[:, 1] < boundary[3])

  def place(n, extent, height, gap_max):
    """Centres [n, 2] beside random leg points; tall shapes start `clearance` beside the leg line."""
    anchor, heading = _sample_anchor(r, pts, n)
    low = height + clearance <= anchor[:, 2]  # can stand right below the leg
    gap_lo = jnp.where(low, 0.0, clearance)
    gap = gap_lo + r.take((n,)) * jnp.maximum(gap_max - gap_lo, 0.0) + 1e-3
    side = r.sign((n,))
    normal = jnp.stack([-jnp.sin(heading), jnp.cos(heading)], -1)
    return anchor[:, :2] + (side * (extent + gap))[:, None] * normal, heading

  def clearance_ok(cyl, box):
    """Exact path clearance of candidate cylinders [Nc, 4] and prisms [Nb, 6], in ONE golden-section search."""
    shapes = jnp.concatenate([jnp.pad(cyl, ((0, 0), (0, 2))), box], 0)
    is_cyl = jnp.arange(shapes.shape[0]) < cyl.shape[0]

    def sdf(q, s, c):
      return jnp.where(c, geo.sdf_cylinder(q, s[:4]), geo.sdf_box(q, s))

    ok = jax.vmap(lambda s, c: _path_clear(lambda q: sdf(q, s, c), pts, mission, clearance + 1e-3))(shapes, is_cyl)
    return ok[:cyl.shape[0]], ok[cyl.shape[0]:]

  # Cylinders.
  c = OVERSAMPLE * MAX_CYLINDERS
  kind = r.categorical(p.cyl_density + 1e-12, (c,))
  radius = _uniform(r, p.cyl_radius[kind])
  height = _uniform(r, p.cyl_height[kind])
  xy, _ = place(c, radius, height, clearance + p.corridor)
  cyl = jnp.concatenate([xy, radius[:, None], height[:, None]], -1)
  cyl_in = inside_boundary(xy)

  # Boxes: yaw = leg heading + jitter; lateral extent of the rotated footprint along the leg normal.
  c = OVERSAMPLE * MAX_BOXES
  kind = r.categorical(p.box_density + 1e-12, (c,))
  hx = _uniform(r, p.box_hx[kind])
  hy = _uniform(r, p.box_hy[kind])
  height = _uniform(r, p.box_height[kind])
  jitter = (2.0 * r.take((c,)) - 1.0) * p.yaw_jitter
  extent = jnp.abs(hx * jnp.sin(jitter)) + jnp.abs(hy * jnp.cos(jitter))
  xy, heading = place(c, extent, height, clearance + p.corridor)
  box = jnp.concatenate([xy, hx[:, None], hy[:, None], (heading + jitter)[:, None], height[:, None]], -1)
  box_in = inside_boundary(xy)

  # Keep-out prisms (private properties) aligned with the street (leg), beside it.
  c = OVERSAMPLE * MAX_FENCES
  along = _uniform(r, p.fence_along, (c,))
  across = _uniform(r, p.fence_across, (c,))
  gap = clearance + _uniform(r, p.fence_gap, (c,))
  anchor, heading = _sample_anchor(r, pts, c)
  side = r.sign((c,))
  normal = jnp.stack([-jnp.sin(heading), jnp.cos(heading)], -1)
  xy = anchor[:, :2] + (side * (across + gap))[:, None] * normal
  fen = jnp.concatenate([xy, along[:, None], across[:, None], heading[:, None], jnp.full((c, 1), FENCE_HEIGHT)], -1)

  # Exact clearance check of all candidates; keep the first valid ones up to the sampled counts.
  cyl_ok, rest_ok = clearance_ok(cyl, jnp.concatenate([box, fen], 0))
  box_ok, fen_ok = rest_ok[:box.shape[0]], rest_ok[box.shape[0]:]
  n_cyl = _count(r, jnp.sum(p.cyl_density) * corridor_ha, MAX_CYLINDERS)
  n_box = _count(r, jnp.sum(p.box_density) * corridor_ha, MAX_BOXES)
  n_fen = r.randint(p.n_fences[0], p.n_fences[1])
  parked_box = jnp.array([_FAR_POS, _FAR_POS, 0.0, 0.0, 0.0, 0.0])
  cylinders, cylinder_mask = _compact(cyl, cyl_ok & cyl_in, n_cyl, MAX_CYLINDERS,
                                      jnp.array([_FAR_POS, _FAR_POS, 0.0, 0.0]))
  boxes, box_mask = _compact(box, box_ok & box_in, n_box, MAX_BOXES, parked_box)
  fences, fence_mask = _compact(fen, fen_ok, n_fen, MAX_FENCES, parked_box)

  # Weather.
  speed = _uniform(r, p.wind_speed)
  direction = r.uniform(-math.pi, math.pi)
  wind_mean = jnp.stack([speed * jnp.cos(direction), speed * jnp.sin(direction), jnp.zeros(())])
  gust_std = _uniform(r, p.gust_std)

  return make_world(cylinders=cylinders, cylinder_mask=cylinder_mask, boxes=boxes, box_mask=box_mask, fences=fences,
                    fence_mask=fence_mask, boundary=boundary, boundary_on=boundary_on, ceiling=ceiling,
                    wind_mean=wind_mean, gust_std=gust_std, preset_id=preset_id, surface=p.surface)


def make_world(cylinders, cylinder_mask, boxes, box_mask, fences, fence_mask, boundary, boundary_on, ceiling, wind_mean,
               gust_std, preset_id=-1, surface=0) -> World:
  """A World from its obstacles, fences, limits and weather (shapes and units: World), with the derived fields
  (box_axes, fence_axes) computed from them and every field cast to its dtype."""
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  boxes, fences = f32(boxes), f32(fences)
  return World(
    cylinders=f32(cylinders), cylinder_mask=jnp.asarray(cylinder_mask, bool), boxes=boxes,
    box_mask=jnp.asarray(box_mask, bool), fences=fences, fence_mask=jnp.asarray(fence_mask, bool),
    box_axes=geo.prism_axes(boxes), fence_axes=geo.prism_axes(fences), boundary=f32(boundary),
    boundary_on=jnp.asarray(boundary_on, bool), ceiling=f32(ceiling), wind_mean=f32(wind_mean), gust_std=f32(gust_std),
    preset_id=jnp.asarray(preset_id, jnp.int32), surface=jnp.asarray(surface, jnp.int32))


# ----------------------------------------------------------------------------------------------------------------
# Queries


def obstacle_sdf(world: World, pos: jnp.ndarray) -> jnp.ndarray:
  """Signed 3D distance from pos [3] to the nearest obstacle surface (< 0 inside), uncapped (1e3 if none), m."""
  return jnp.minimum(geo.sdf_cylinders(pos, world.cylinders, world.cylinder_mask),
                     geo.sdf_boxes(pos, world.boxes, world.box_mask))


def obstacle_sdf_and_grad(world: World, pos: jnp.ndarray):
  """(obstacle_sdf(world, pos) [], its gradient w.r.t. pos [3]): the nearest valid obstacle's SDF gradient (a unit
  vector away from it, zero if there is none), from one reverse pass over that obstacle alone instead of over all
  of them (what jax.value_and_grad(obstacle_sdf) does: about twice the forward's work per env). Equal to it
  except where two obstacles are exactly equally near (there it averages their gradients, this takes one), and
  where XLA recomputes the min in the reverse pass with another rounding (no obstacle equals it there: the autodiff
  gradient is 0, seen jitted on the CPU; an argmin cannot miss). `obstacle_queries` with no other points."""
  _, d, g = obstacle_queries(world, jnp.zeros((0, 3), jnp.float32), pos)
  return d, g


def _first_nearest(a, b):
  """Variadic-reduce step of `obstacle_queries`: a, b = (d_points [K]..., d, index); the points' minima elementwise
  and, of (d, index), the one jnp.argmin picks (smaller d, NaN first, the lower index on ties)."""
  k = len(a) - 2
  (da, ia), (db, ib) = a[k:], b[k:]
  a_nan, b_nan = jnp.isnan(da), jnp.isnan(db)
  take_a = (da < db) | (a_nan & ~b_nan) | (((da == db) | (a_nan & b_nan)) & (ia < ib))
  return (tuple(jnp.minimum(x, y) for x, y in zip(a[:k], b[:k]))
          + (jnp.where(take_a, da, db), jnp.where(take_a, ia, ib)))


def obstacle_queries(world: World, points: jnp.ndarray, pos: jnp.ndarray):
  """The env step's obstacle queries with one pass over the world's obstacle slots: (obstacle_sdf at each of points
  [K, 3] -> [K] (K >= 0), the distance and SDF gradient at pos [3] -> ([], [3]), `obstacle_sdf_and_grad`). Each kind's
  slots go through one variadic reduction (every point's distance and the nearest slot's distance and index at pos),
  then the nearest slot's gradient alone, so XLA reads the world's ~1.3 KB per env once, where the three queries
  (collision at the step's ticks, the signals at the last one, the observation at the estimate) read it three times
  (a per-slot gradient inside the reduction is slower: XLA writes it out for every slot)."""
  k = points.shape[0]

  def nearest(sdf, slots, mask):
    n = mask.shape[0]
    d_pts = jax.vmap(lambda s: jax.vmap(sdf, (0, None))(points, s))(slots)        # [n, K]
    d = jax.vmap(sdf, (None, 0))(pos, slots)                                       # [n]
    ops = (*jnp.where(mask[:, None], d_pts, geo.FAR).T, jnp.where(mask, d, geo.FAR), jnp.arange(n, dtype=jnp.int32))
    init = (*([jnp.float32(geo.FAR)] * k), jnp.float32(jnp.inf), jnp.int32(n))
    out = jax.lax.reduce(ops, init, _first_nearest, (0,))
    i = out[k + 1]
    g = jnp.where(mask[i], jax.grad(sdf)(pos, jax.tree.map(lambda x: x[i], slots)), 0.0)
    return jnp.stack(out[:k]) if k else jnp.zeros((0,), jnp.float32), out[k], g

  pc, dc, gc = nearest(geo.sdf_cylinder, world.cylinders, world.cylinder_mask)
  pb, db, gb = nearest(lambda p, s: geo.sdf_box(p, *s), (world.boxes, world.box_axes), world.box_mask)
  return jnp.minimum(pc, pb), jnp.minimum(jnp.minimum(dc, db), geo.FAR), jnp.where(dc <= db, gc, gb)


def with_geofence(world: World, fence: geofence_lib.Geofence, max_alt=None, replace_fences: bool = False,
                  rally_points=None) -> World:
  """`world` with a mission's own geofence (envs.geofence) and rally points [R, 3] (unbatched or batched alike).
  max_alt: a maximum altitude above home (m) that lowers the ceiling (None: unchanged). replace_fences: the generated
  keep-out prisms and operating boundary are dropped (a plan's geoFence is the mission's fence geometry); obstacles,
  the ceiling and the weather stay."""
  out = world.replace(geofence=fence)
  if max_alt is not None:
    out = out.replace(ceiling=jnp.minimum(out.ceiling, jnp.float32(max_alt)))
  if replace_fences:
    out = out.replace(fence_mask=jnp.zeros_like(out.fence_mask), boundary_on=jnp.zeros_like(out.boundary_on))
  if rally_points is not None:
    out = out.replace(rally_points=jnp.asarray(rally_points, jnp.float32))
  return out


def fence_distances(world: World, pos: jnp.ndarray):
  """(margin, h, v) of pos [3] w.r.t. the nearest forbidden region, uncapped; > 0 on the allowed side, m.

  Regions: keep-out prisms (margin = exact 3D SDF, h = footprint SDF, v = z - top), outside the operating boundary
  (margin = h = signed distance to the rectangle edge, v = 1e3), above the ceiling (margin = v = ceiling - z,
  h = 1e3) and the mission's own geofence zones (2D: margin = h = envs.geofence.zone_margins, v = 1e3).
  "Nearest" = smallest margin; its h and v are returned. 1e3 everywhere if there is no fence.
  """
  z = pos[2]
  pm = jax.vmap(geo.sdf_box, (None, 0, 0))(pos, world.fences, world.fence_axes)
  ph = jax.vmap(geo.sdf_box_xy, (None, 0, 0))(pos[:2], world.fences, world.fence_axes)
  pv = z - world.fences[:, 5]
  far = jnp.full((1,), geo.FAR)
  bh = jnp.where(world.boundary_on, geo.rect_inside_margin(pos[:2], world.boundary), geo.FAR)[None]
  cv = (world.ceiling - z)[None]
  margins = [jnp.where(world.fence_mask, pm, geo.FAR), bh, cv]
  hs, vs = [ph, bh, far], [pv, far, cv]
  if world.geofence.active:   # static: a generated mission's world has no zones
    zm = geofence_lib.zone_margins(world.geofence, pos[:2])[None]
    margins, hs, vs = margins + [zm], hs + [zm], vs + [far]
  margins, hs, vs = jnp.concatenate(margins), jnp.concatenate(hs), jnp.concatenate(vs)
  i = jnp.argmin(margins)
  return margins[i], hs[i], vs[i]


def proximity_ranges(world: World, pos: jnp.ndarray, yaw, n_sectors: int, max_range: float) -> jnp.ndarray:
  """[n_sectors] ranges (m, capped at max_range) of a horizontal ring of range sensors at pos [3]: beam k points at
  yaw + 2 pi k / n_sectors (k = 0 straight ahead of the body, counter-clockwise), the distance to the first obstacle,
  keep-out fence or operating-boundary edge it meets (a beam from inside a shape or outside the boundary reads 0).
  From the true geometry; the sensor's noise is the caller's (envs.observation)."""
  ang = jnp.asarray(yaw, jnp.float32) + jnp.arange(n_sectors, dtype=jnp.float32) * (2.0 * jnp.pi / n_sectors)
  dirs = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)                                      # [n, 2]

  def one(d):
    cyl = jax.vmap(geo.ray_cylinder, (None, None, 0))(pos, d, world.cylinders)
    box = jax.vmap(geo.ray_box, (None, None, 0, 0))(pos, d, world.boxes, world.box_axes)
    fen = jax.vmap(geo.ray_box, (None, None, 0, 0))(pos, d, world.fences, world.fence_axes)
    edge = jnp.where(world.boundary_on, geo.ray_rect_exit(pos[:2], d, world.boundary), geo.FAR)
    return jnp.minimum(jnp.minimum(geo.masked_min(cyl, world.cylinder_mask), geo.masked_min(box, world.box_mask)),
                       jnp.minimum(geo.masked_min(fen, world.fence_mask), edge))

  return jnp.minimum(jax.vmap(one)(dirs), max_range)


def world_queries(world: World, mission: Mission, pos: jnp.ndarray, target_idx, obstacle=None) -> dict:
  """Geometric monitored signals (specguard_jax.signals) at pos [3] while heading for waypoint target_idx.

  Returns float32 scalars: obstacle_distance (signed, < 0 inside, capped at SIGNAL_CAP), fence_margin, fence_h,
  fence_v (capped at SIGNAL_CAP), path_deviation (to the current leg; while heading for waypoint 0 the vertical
  take-off segment counts too), dist_wp (to the target waypoint; after the last one: to the landing point),
  dist_final (to the last waypoint). target_idx semantics: see missions.mission_leg. obstacle: obstacle_sdf(world,
  pos) if already at hand (`obstacle_queries`), else computed here.
  """
  t = jnp.asarray(target_idx, jnp.int32)
  obstacle = jnp.minimum(obstacle_sdf(world, pos) if obstacle is None else obstacle, SIGNAL_CAP)
  margin, h, v = fence_distances(world, pos)
  start, end = mission_leg(mission, t)
  dev = geo.dist_point_segment(pos, start, end)
  dev_takeoff = geo.dist_point_segment(pos, mission.home, takeoff_point(mission))
  dev = jnp.where(t <= 0, jnp.minimum(dev, dev_takeoff), dev)
  done = t >= mission.n_waypoints
  target = jnp.where(done, landing_point(mission), mission.waypoints[jnp.clip(t, 0, mission.n_waypoints - 1)])
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return {
    "obstacle_distance": f32(obstacle),
    "fence_margin": f32(jnp.minimum(margin, SIGNAL_CAP)),
    "fence_h": f32(jnp.minimum(h, SIGNAL_CAP)),
    "fence_v": f32(jnp.minimum(v, SIGNAL_CAP)),
    "path_deviation": f32(dev),
    "dist_wp": f32(geo.safe_norm(pos - target)),
    "dist_final": f32(geo.safe_norm(pos - final_waypoint(mission))),
  }


WORLD_SIGNALS = ("obstacle_distance", "fence_margin", "fence_h", "fence_v", "path_deviation", "dist_wp", "dist_final")
"""Keys returned by world_queries (a subset of specguard_jax.signals.SIGNAL_NAMES)."""
