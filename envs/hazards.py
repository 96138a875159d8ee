"""Hazard points of a mission in its world, on the mission's nominal timeline (jittable, vmappable).

A hazard-timed attack (specguard_jax.evaluation's `hazard` campaign) starts a lead time before a moment where a
corrupted estimate hurts most. The moments, from the nominal path flown at the nominal speeds (the timing of
missions.mission_timing: vertical take-off at climb_speed, legs at cruise_speed, the loiter after its waypoint,
the landing descent at descent_speed):
  obstacle  closest approach of the nominal path to an obstacle surface (obstacle SDF), when one is within reach;
  fence     closest approach to a geofence (keep-out prism, operating boundary or ceiling), when one is within reach;
  turn      arrival at the waypoint with the sharpest horizontal turn (at least `min_turn_deg`);
  loiter    start of the loiter (arrival at the loiter waypoint), when the mission loiters;
  landing   start of the landing descent, when the mission lands.
The vehicle flies behind the nominal timeline by its accelerations and turns (seconds on a minutes-long mission);
the lead time of the campaign absorbs part of that.

Attack scheduling (specguard_jax.attacks) knows no missions or worlds: the evaluation computes the onset here and
hands it to the attack sampler.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from envs import missions as missions_lib
from envs import worlds as worlds_lib

HAZARD_KINDS = ("obstacle", "fence", "turn", "loiter", "landing")
SAMPLES_PER_SEGMENT = 32   # nominal-track samples per path segment (a 120 m leg at 7 m/s: one per ~0.5 s)
REACH_M = 50.0             # an obstacle / fence farther than this from the whole path is no hazard of the mission
MIN_TURN_DEG = 30.0        # a sharpest turn below this is no hazard


def nominal_track(mission: missions_lib.Mission, cfg: missions_lib.MissionConfig,
                  samples: int = SAMPLES_PER_SEGMENT):
  """The nominal path sampled in time: (points [P, 3] m, times [P] s, segment end times [W + 2] s for W waypoint slots).

  Segments (missions.path_polyline): home -> take-off point (climb), take-off point -> waypoint 0, waypoint k-1 ->
  k (cruise; padded slots are degenerate), last waypoint -> landing point (descent); the loiter time is spent at the
  end of the segment into the loiter waypoint. P = (W + 2) * samples. The last segment ends at the
  mission's nominal_duration."""
  pts, _ = missions_lib.path_polyline(mission)
  a, b = pts[:-1], pts[1:]                                             # [S, 3], S = W + 2
  length = jnp.linalg.norm(b - a, axis=-1)
  n_seg = a.shape[0]
  seg = jnp.arange(n_seg)
  speed = jnp.where(seg == 0, cfg.climb_speed, jnp.where(seg == n_seg - 1, cfg.descent_speed, mission.cruise_speed))
  move = jnp.where(seg == n_seg - 1, mission.land * length, length) / speed   # no landing: a zero-length segment
  # segment k + 1 ends at waypoint k
  dwell = jnp.where((mission.loiter_wp >= 0) & (seg == mission.loiter_wp + 1), mission.loiter_time, 0.0)
  end = jnp.cumsum(move + dwell)
  start = end - move - dwell
  u = jnp.linspace(0.0, 1.0, samples)
  points = (a[:, None] + u[None, :, None] * (b - a)[:, None]).reshape(-1, 3)
  times = (start[:, None] + u[None, :] * move[:, None]).reshape(-1)
  return points, times, end


def hazard_times(mission: missions_lib.Mission, world: worlds_lib.World, cfg: missions_lib.MissionConfig,
                 reach: float = REACH_M, min_turn_deg: float = MIN_TURN_DEG):
  """Nominal times of the mission's hazard points: (times [5] s, valid [5] bool), HAZARD_KINDS order."""
  points, times, end = nominal_track(mission, cfg)
  d_obs = jax.vmap(lambda p: worlds_lib.obstacle_sdf(world, p))(points)
  d_fence = jax.vmap(lambda p: worlds_lib.fence_distances(world, p)[0])(points)
  i_obs, i_fence = jnp.argmin(d_obs), jnp.argmin(d_fence)
  # horizontal heading change at waypoint k (0 <= k < n - 1) between the leg into it and the leg out of it
  n = mission.n_waypoints
  wps = mission.waypoints
  prev = jnp.concatenate([missions_lib.takeoff_point(mission)[None], wps[:-1]], 0)
  d_in = (wps - prev)[:, :2]
  d_out = jnp.concatenate([wps[1:] - wps[:-1], jnp.zeros((1, 3))], 0)[:, :2]
  cross = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
  turn = jnp.abs(jnp.arctan2(cross, jnp.sum(d_in * d_out, -1)))
  k = jnp.arange(wps.shape[0])
  turn = jnp.where((k < n - 1) & (jnp.linalg.norm(d_in, axis=-1) > 1e-3), turn, 0.0)
  k_turn = jnp.argmax(turn)
  arrival = end[1:-1] - jnp.where(k == mission.loiter_wp, mission.loiter_time, 0.0)   # segment k + 1 ends at wp k
  t_landing = end[-2]   # the descent starts when the last waypoint (and a loiter there) is done
  out = jnp.stack([times[i_obs], times[i_fence], arrival[k_turn], arrival[jnp.maximum(mission.loiter_wp, 0)],
                   t_landing])
  valid = jnp.stack([d_obs[i_obs] < reach, d_fence[i_fence] < reach, turn[k_turn] >= jnp.deg2rad(min_turn_deg),
                     mission.loiter_wp >= 0, mission.land > 0.5])
  return out.astype(jnp.float32), valid


def hazard_onset(mission: missions_lib.Mission, world: worlds_lib.World, cfg: missions_lib.MissionConfig, rng,
                 lead_s=(2.0, 5.0), kinds=HAZARD_KINDS):
  """Onset (s) of a hazard-timed attack: one hazard point drawn uniformly among the mission's valid ones of `kinds`
  (seeded by rng), minus a lead time U(lead_s) s, at least 0. No valid hazard: the middle of the nominal mission.
  Returns (onset [] s, kind [] int32 index into HAZARD_KINDS, -1 when none, hazard time [] s)."""
  bad = [x for x in kinds if x not in HAZARD_KINDS]
  if bad or not kinds:
    raise ValueError(f"unknown or no hazard kind(s) {bad}; choose from {', '.join(HAZARD_KINDS)}")
  times, valid = hazard_times(mission, world, cfg)
  valid = valid & jnp.asarray([x in kinds for x in HAZARD_KINDS])
  k_pick, k_lead = jax.random.split(rng)
  logits = jnp.where(valid, 0.0, -jnp.inf)
  kind = jnp.where(valid.any(), jax.random.categorical(k_pick, logits), -1)
  t_h = jnp.where(kind >= 0, times[jnp.maximum(kind, 0)], 0.5 * mission.nominal_duration)
  lead = jax.random.uniform(k_lead, (), minval=lead_s[0], maxval=lead_s[1])
  return jnp.maximum(t_h - lead, 0.0), kind.astype(jnp.int32), t_h
