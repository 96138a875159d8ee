"""Mission plans: the `Mission` pytree, a procedural generator and path helpers (jittable, vmappable).

A mission is what a QGroundControl plan gives PX4 / ArduPilot: a home position on the ground, a take-off altitude
(drones), waypoints the autopilot flies THROUGH (no stop at intermediate waypoints; W slots, see Padding), an optional
loiter at one waypoint and an optional landing at the last waypoint. On top of that SpecGuard's S5 ("navigate
through waypoints", F_[t_i, t_j](dist_wp < 5)) needs a time window per waypoint: `window_open` / `deadline`.

Frames: world ENU (x east, y north, z up), ground at z = 0, metres; times in s from mission start.
Rovers: every z is 0 (the env adds the body height), takeoff_alt = 0, land = 0, no loiter.
Padding: waypoint slots k >= n_waypoints repeat the last valid waypoint (and its window/deadline), so polylines
through all slots are geometrically the true path plus degenerate segments. The slot count W is the waypoint array's
own first axis: generated missions have `MissionConfig.max_waypoints` slots, loaded mission files as many as they need
(envs.mission_files); every helper here reads W from the array, so one jitted program serves one slot count.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from specguard_jax.types import VEHICLES

MAX_WAYPOINTS = 12
"""Default waypoint slots per generated mission (`MissionConfig.max_waypoints`; the array is fixed-size, so every
slot costs work in every env step: the default stays small)."""

DEFAULT_EPISODE_CAP_S = 400.0
"""s: the default cap on an episode (envs.base.EnvConfig.max_episode_s), which loaded mission files are checked
against unless given another."""

PATH_KINDS = ("line", "circle", "polygon")
"""Generated path shapes, in the order of `MissionConfig.path_kind_probs`."""


@struct.dataclass
class Mission:
  """One mission plan (add leading axes for a batch).

  home: [3] start position on the ground (z = 0), m.
  waypoints: [W, 3] waypoint positions, m (slots >= n_waypoints repeat the last valid waypoint); W slots (module
    docstring).
  n_waypoints: [] int32, number of valid waypoints (>= 1).
  window_open: [W] earliest time the waypoint counts as reached for S5, s.
  deadline: [W] latest time to reach the waypoint (within acceptance_radius), s; increasing.
  takeoff_alt: [] take-off altitude above home, m (0 for rovers).
  cruise_speed: [] commanded horizontal speed between waypoints, m/s.
  acceptance_radius: [] waypoint acceptance radius, m.
  loiter_wp: [] int32 index of the waypoint to loiter at after reaching it (-1: none).
  loiter_time: [] loiter duration, s (0 if none).  loiter_radius: [] loiter circle radius, m.
  land: [] 0/1 float, 1 if the drone lands (vertically) at the last waypoint.
  nominal_duration: [] nominal mission duration (take-off + legs at cruise speed + loiter + landing), s.
  """

  home: jnp.ndarray
  waypoints: jnp.ndarray
  n_waypoints: jnp.ndarray
  window_open: jnp.ndarray
  deadline: jnp.ndarray
  takeoff_alt: jnp.ndarray
  cruise_speed: jnp.ndarray
  acceptance_radius: jnp.ndarray
  loiter_wp: jnp.ndarray
  loiter_time: jnp.ndarray
  loiter_radius: jnp.ndarray
  land: jnp.ndarray
  nominal_duration: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class MissionConfig:
  """Distribution of generated missions (and timing rules shared with loaded mission files).

  Ranges are (low, high), sampled uniformly. Angles in degrees, lengths in m, speeds in m/s, times in s.
  Paper specs (Table 4): altitude 10-20 m, horizontal speed 5-12 m/s, waypoint radius 5 m, loiter radius 8 m.
  """

  vehicle: str = "drone"                    # "drone" | "rover"
  path_kind_probs: tuple = (0.25, 0.25, 0.5)  # P(line), P(circle), P(polygon), see PATH_KINDS
  n_waypoints: tuple = (4, 10)              # requested count, then trimmed to the duration bounds
  leg_length: tuple = (30.0, 120.0)         # horizontal length of every leg (leg 0 from above home)
  altitude: tuple = (12.0, 18.0)            # take-off and waypoint altitudes (drone); ignored for rovers
  cruise_speed: tuple = (7.0, 9.0)
  acceptance_radius: float = 5.0
  max_turn_deg: float = 100.0               # hard bound on the heading change at any waypoint
  line_turn_deg: float = 15.0               # "line": heading jitter per waypoint in [-x, x]
  circle_turn_deg: tuple = (20.0, 45.0)     # "circle": constant turn per waypoint, constant leg length
  polygon_turn_deg: tuple = (30.0, 100.0)   # "polygon": turn magnitude per waypoint, random side
  p_loiter: float = 0.3
  loiter_time: tuple = (10.0, 30.0)
  loiter_radius: float = 8.0
  p_land: float = 0.8
  climb_speed: float = 2.0                  # nominal take-off climb rate for timing (S10: >= 2 m/s ramp)
  descent_speed: float = 1.0                # nominal landing descent rate for timing
  deadline_factor: float = 1.5              # deadline = factor * nominal arrival + slack
  deadline_slack_s: float = 10.0
  window_open_factor: float = 0.5           # window_open = factor * nominal arrival (0: window open from t = 0)
  min_duration_s: float = 60.0              # soft: waypoints are added (up to max_waypoints) to reach it
  max_duration_s: float = 300.0             # hard (must exceed take-off + landing time): see generate_mission
  max_waypoints: int = MAX_WAYPOINTS        # waypoint slots of a generated mission (the array's fixed size)

  @property
  def is_rover(self) -> bool:
    return self.vehicle == "rover"

  @classmethod
  def drone(cls, **kw) -> "MissionConfig":
    """Quadcopter missions: take-off, 12-18 m cruise altitude, 7-9 m/s, optional loiter and landing, 1-5 min."""
    return cls(**kw)

  @classmethod
  def rover(cls, **kw) -> "MissionConfig":
    """Ground-rover missions: z = 0, 6-8 m/s, no take-off, loiter or landing, 1-5 min; waypoints accepted within
    2 m (ArduRover's WP_RADIUS default; the rover stops where the last one is accepted, so a 5 m radius would leave
    it on the edge of the paper's 5 m recovery-success radius)."""
    base = dict(vehicle="rover", altitude=(0.0, 0.0), cruise_speed=(6.0, 8.0), p_loiter=0.0, p_land=0.0,
                acceptance_radius=2.0)
    base.update(kw)
    return cls(**base)

  def __post_init__(self):
    if self.vehicle not in VEHICLES:
      raise ValueError(f"MissionConfig.vehicle must be one of {', '.join(VEHICLES)}, got {self.vehicle!r}")
    if isinstance(self.max_waypoints, bool) or not isinstance(self.max_waypoints, int) or self.max_waypoints < 1:
      raise ValueError(f"MissionConfig.max_waypoints must be an integer >= 1, got {self.max_waypoints!r}")
    lo, hi = self.n_waypoints
    if not 1 <= lo <= hi <= self.max_waypoints:
      raise ValueError(f"n_waypoints {self.n_waypoints} must satisfy 1 <= lo <= hi <= max_waypoints "
                       f"({self.max_waypoints})")
    if len(self.path_kind_probs) != len(PATH_KINDS) or min(self.path_kind_probs) < 0 or sum(self.path_kind_probs) <= 0:
      raise ValueError(f"path_kind_probs must be {len(PATH_KINDS)} non-negative weights")
    if not 0 < self.leg_length[0] <= self.leg_length[1]:
      raise ValueError(f"bad leg_length {self.leg_length}")
    if not 0 < self.cruise_speed[0] <= self.cruise_speed[1]:
      raise ValueError(f"bad cruise_speed {self.cruise_speed}")
    if self.max_duration_s <= 0:
      raise ValueError("max_duration_s must be > 0")


# ----------------------------------------------------------------------------------------------------------------
# Timing (shared by generated and loaded missions)


def _pad_waypoints(waypoints: jnp.ndarray, n: jnp.ndarray) -> jnp.ndarray:
  """Replace slots >= n of waypoints [M, 3] by the last valid waypoint."""
  k = jnp.arange(waypoints.shape[0])
  return jnp.where((k < n)[:, None], waypoints, waypoints[jnp.maximum(n - 1, 0)])


def leg_lengths(home: jnp.ndarray, waypoints: jnp.ndarray, takeoff_alt: jnp.ndarray) -> jnp.ndarray:
  """3D length of the leg ending at each waypoint slot, [M] m (leg 0 starts above home at takeoff_alt)."""
  start0 = home + jnp.array([0.0, 0.0, 1.0]) * takeoff_alt
  starts = jnp.concatenate([start0[None], waypoints[:-1]], axis=0)
  return jnp.linalg.norm(waypoints - starts, axis=-1)


def mission_timing(home, waypoints, n_waypoints, takeoff_alt, cruise_speed, loiter_wp, loiter_time, land,
                   cfg: MissionConfig):
  """Nominal arrival times and S5 windows.

  arrival_k = takeoff_alt / climb_speed + sum_{j<=k} leg_j / cruise_speed + loiter_time * [loiter_wp < k];
  window_open = window_open_factor * arrival;  deadline = deadline_factor * arrival + deadline_slack_s;
  duration = arrival_{n-1} + loiter_time * [loiter_wp == n-1] + land * z_{n-1} / descent_speed.
  Returns (window_open [M], deadline [M], duration []), slots >= n copy the last valid value.
  """
  m = waypoints.shape[0]
  k = jnp.arange(m)
  n = n_waypoints
  wps = _pad_waypoints(waypoints, n)
  t_takeoff = takeoff_alt / cfg.climb_speed
  loitering = loiter_wp >= 0
  arrival = t_takeoff + jnp.cumsum(leg_lengths(home, wps, takeoff_alt)) / cruise_speed
  arrival = arrival + jnp.where(loitering & (k > loiter_wp), loiter_time, 0.0)
  last = arrival[n - 1]
  arrival = jnp.where(k < n, arrival, last)
  duration = last + jnp.where(loitering & (loiter_wp == n - 1), loiter_time, 0.0)
  duration = duration + land * wps[n - 1, 2] / cfg.descent_speed
  window_open = cfg.window_open_factor * arrival
  deadline = cfg.deadline_factor * arrival + cfg.deadline_slack_s
  return window_open, deadline, duration


# ----------------------------------------------------------------------------------------------------------------
# Generator


class UniformPool:
  """Hands out slices of ONE jax.random.uniform draw (trace-time helper, local to one generator call).

  Each separate jax.random call adds a threefry kernel that XLA compiles slowly on CPU (about 0.4 s each);
  generators draw all their randomness at once instead. `size` must cover every take().
  """

  def __init__(self, rng: jax.Array, size: int):
    self._u = jax.random.uniform(rng, (size,))
    self._i = 0

  def take(self, shape=()) -> jnp.ndarray:
    """U(0, 1) array of the given shape."""
    n = math.prod(shape)
    if self._i + n > self._u.shape[0]:
      raise ValueError("UniformPool exhausted: raise its size")
    out = self._u[self._i:self._i + n].reshape(shape)
    self._i += n
    return out

  def uniform(self, lo, hi, shape=()) -> jnp.ndarray:
    return lo + self.take(shape) * (jnp.asarray(hi) - lo)

  def bernoulli(self, p, shape=()) -> jnp.ndarray:
    return self.take(shape) < p

  def sign(self, shape=()) -> jnp.ndarray:
    return jnp.where(self.take(shape) < 0.5, 1.0, -1.0)

  def randint(self, lo, hi, shape=()) -> jnp.ndarray:
    """Integers uniform in [lo, hi] (inclusive), int32."""
    lo = jnp.asarray(lo)
    return jnp.minimum(lo + jnp.floor(self.take(shape) * (hi - lo + 1)), hi).astype(jnp.int32)

  def categorical(self, weights, shape=()) -> jnp.ndarray:
    """Indices in [0, K) with probability proportional to non-negative weights [K], int32."""
    cdf = jnp.cumsum(weights)
    u = self.take(shape)[..., None] * cdf[-1]
    return jnp.minimum(jnp.sum(u >= cdf, axis=-1), weights.shape[0] - 1).astype(jnp.int32)



def generate_mission(cfg: MissionConfig, rng: jax.Array) -> Mission:
  """Sample one mission from cfg (static) with the PRNG key rng. Jittable (cfg static) and vmappable over rng.

  Paths: heading h_k = h_0 + sum of turns; "line" jitters the heading by <= line_turn_deg, "circle" turns by a
  constant angle with a constant leg length (waypoints on a circle), "polygon" turns by a random-sided angle in
  polygon_turn_deg. Every turn is clipped to max_turn_deg. Waypoint altitudes are independent U(altitude), so the
  climb gradient is <= (alt_hi - alt_lo) / leg_lo (20 % by default). Home is the origin.
  """
  m = cfg.max_waypoints
  r = UniformPool(rng, 8 * m + 16)
  deg = math.pi / 180.0
  max_turn = cfg.max_turn_deg * deg

  kind = r.categorical(jnp.asarray(cfg.path_kind_probs, jnp.float32))
  h0 = r.uniform(-math.pi, math.pi)

  turn_line = r.uniform(-cfg.line_turn_deg * deg, cfg.line_turn_deg * deg, (m,))
  turn_circle = r.sign() * r.uniform(cfg.circle_turn_deg[0] * deg, cfg.circle_turn_deg[1] * deg) * jnp.ones(m)
  turn_poly = r.sign((m,)) * r.uniform(cfg.polygon_turn_deg[0] * deg, cfg.polygon_turn_deg[1] * deg, (m,))
  turns = jnp.stack([turn_line, turn_circle, turn_poly])[kind]
  turns = jnp.clip(turns, -max_turn, max_turn).at[0].set(0.0)
  heading = h0 + jnp.cumsum(turns)

  leg_rand = r.uniform(cfg.leg_length[0], cfg.leg_length[1], (m,))
  leg_const = r.uniform(cfg.leg_length[0], cfg.leg_length[1]) * jnp.ones(m)
  legs = jnp.where(kind == 1, leg_const, leg_rand)
  home = jnp.zeros(3)
  xy = home[:2] + jnp.cumsum(legs[:, None] * jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1), axis=0)

  alt = r.uniform(cfg.altitude[0], cfg.altitude[1], (m,))
  takeoff_alt = r.uniform(cfg.altitude[0], cfg.altitude[1])
  if cfg.is_rover:
    alt, takeoff_alt = jnp.zeros(m), jnp.zeros(())
  waypoints = jnp.concatenate([xy, alt[:, None]], axis=-1)

  cruise = r.uniform(cfg.cruise_speed[0], cfg.cruise_speed[1])
  loiter_on = r.bernoulli(cfg.p_loiter) & (not cfg.is_rover)
  loiter_time = jnp.where(loiter_on, r.uniform(cfg.loiter_time[0], cfg.loiter_time[1]), 0.0)
  land = jnp.where(r.bernoulli(cfg.p_land) & (not cfg.is_rover), 1.0, 0.0)
  loiter_u = r.take()

  # Number of waypoints: requested count, raised (up to max_waypoints) to reach min_duration_s, then lowered
  # (down to 1) to respect max_duration_s. Candidate durations with k = 1..M waypoints (the loiter, placed below,
  # counts wherever it happens). max_duration_s is hard: a loiter that does not fit even with one waypoint is
  # dropped, then a single too-long first leg is shortened (flown level at takeoff_alt).
  k1 = jnp.arange(1, m + 1)
  t_takeoff = takeoff_alt / cfg.climb_speed
  dur_k = t_takeoff + jnp.cumsum(leg_lengths(home, waypoints, takeoff_alt)) / cruise + land * alt / cfg.descent_speed
  loiter_on = loiter_on & (dur_k[0] + loiter_time <= cfg.max_duration_s)
  loiter_time = jnp.where(loiter_on, loiter_time, 0.0)
  dur_k = dur_k + loiter_time
  n_req = r.randint(cfg.n_waypoints[0], cfg.n_waypoints[1])
  long_enough = dur_k >= cfg.min_duration_s
  n_min = jnp.where(jnp.any(long_enough), jnp.argmax(long_enough) + 1, m)
  n_max = jnp.maximum(jnp.sum(dur_k <= cfg.max_duration_s), 1)  # dur_k is increasing in k
  n = jnp.minimum(jnp.maximum(n_req, n_min), n_max).astype(jnp.int32)
  budget = cfg.max_duration_s - t_takeoff - loiter_time - land * takeoff_alt / cfg.descent_speed
  leg0 = jnp.linalg.norm(waypoints[0, :2] - home[:2])
  shrink = jnp.clip(budget * cruise / leg0, 0.0, 1.0)
  wp0_short = jnp.concatenate([home[:2] + shrink * (waypoints[0, :2] - home[:2]), takeoff_alt[None]])
  waypoints = waypoints.at[0].set(jnp.where(dur_k[0] > cfg.max_duration_s, wp0_short, waypoints[0]))

  loiter_wp = jnp.where(loiter_on, jnp.floor(loiter_u * n).astype(jnp.int32), -1)
  loiter_wp = jnp.minimum(loiter_wp, n - 1)
  waypoints = _pad_waypoints(waypoints, n)
  window_open, deadline, duration = mission_timing(home, waypoints, n, takeoff_alt, cruise, loiter_wp, loiter_time,
                                                   land, cfg)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return Mission(
    home=f32(home), waypoints=f32(waypoints), n_waypoints=n, window_open=f32(window_open), deadline=f32(deadline),
    takeoff_alt=f32(takeoff_alt), cruise_speed=f32(cruise), acceptance_radius=f32(cfg.acceptance_radius),
    loiter_wp=loiter_wp.astype(jnp.int32), loiter_time=f32(loiter_time), loiter_radius=f32(cfg.loiter_radius),
    land=f32(land), nominal_duration=f32(duration))


# ----------------------------------------------------------------------------------------------------------------
# Path helpers


def takeoff_point(mission: Mission) -> jnp.ndarray:
  """Top of the vertical take-off segment: home raised to takeoff_alt, [3] (= home for rovers)."""
  return mission.home + jnp.array([0.0, 0.0, 1.0]) * mission.takeoff_alt


def final_waypoint(mission: Mission) -> jnp.ndarray:
  """Last valid waypoint, [3]."""
  return mission.waypoints[jnp.maximum(mission.n_waypoints - 1, 0)]


def landing_point(mission: Mission) -> jnp.ndarray:
  """Touch-down point: below the last waypoint on the ground if land, else the last waypoint itself, [3]."""
  last = final_waypoint(mission)
  return jnp.where(mission.land > 0.5, last * jnp.array([1.0, 1.0, 0.0]), last)


def mission_leg(mission: Mission, target_idx: jnp.ndarray):
  """(start [3], end [3]) of the leg flown while heading for waypoint target_idx ([] int).

  target_idx 0: from the take-off point (above home) to waypoint 0; k in [1, n): waypoint k-1 -> k;
  k >= n (mission done / landing): last waypoint -> landing point (degenerate if no landing); k < 0 is treated as 0.
  """
  n = mission.n_waypoints
  t = jnp.asarray(target_idx, jnp.int32)
  wps = mission.waypoints
  last = final_waypoint(mission)
  prev = wps[jnp.clip(t - 1, 0, n - 1)]
  start = jnp.where(t <= 0, takeoff_point(mission), prev)
  end = wps[jnp.clip(t, 0, n - 1)]
  done = t >= n
  return jnp.where(done, last, start), jnp.where(done, landing_point(mission), end)


def path_polyline(mission: Mission):
  """The whole nominal path as a fixed-size polyline.

  Returns (points [W + 3, 3], valid [W + 3] bool) for W waypoint slots: home, take-off point, waypoints
  0..M-1, landing point. Invalid waypoint slots repeat the last valid waypoint, so every consecutive pair
  (valid or not) is a true sub-segment of the path (or a point on it): distance queries need no mask.
  """
  wps = _pad_waypoints(mission.waypoints, mission.n_waypoints)
  pts = jnp.concatenate([mission.home[None], takeoff_point(mission)[None], wps, landing_point(mission)[None]], 0)
  k = jnp.arange(wps.shape[0])
  valid = jnp.concatenate([jnp.ones(2, bool), k < mission.n_waypoints, jnp.ones(1, bool)])
  return pts, valid


def path_length(mission: Mission) -> jnp.ndarray:
  """Total 3D length of the nominal path (take-off, legs, landing), m."""
  pts, _ = path_polyline(mission)
  return jnp.sum(jnp.linalg.norm(pts[1:] - pts[:-1], axis=-1))
