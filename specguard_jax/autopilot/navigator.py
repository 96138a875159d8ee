"""Mission navigator (PX4 `navigator` / ArduPilot `mode_auto`): phase machine and guidance velocity setpoints.

Runs on the autopilot's *estimated* position. Phases: TAKEOFF -> CRUISE (waypoint legs, optional LOITER at one
waypoint) -> DESCENT (drone, landing at the last waypoint) -> DONE. Guidance is line following: along-track speed
limited by the cruise speed and by a braking profile towards the corner speed of the next waypoint (PX4's trajectory
generator slows for corners; sqrt(a_lat * r_acc / tan(turn/2))), plus cross-track correction with MPC_XY_P / MPC_Z_P.
Intermediate waypoints are flown through (switch at the acceptance radius, or when passed within 2 radii); the braking
profile reaches the corner speed where the switch happens (one acceptance radius before the corner), not at the
corner itself, or the vehicle carries ~2 m/s too much into the turn and overshoots it by several metres.
"""

import dataclasses

import jax.numpy as jnp
from flax import struct

from specguard_jax.math3d import dot, norm, scale_head, with_component

TAKEOFF, CRUISE, LOITER, DESCENT, DONE = 0, 1, 2, 3, 4
PHASE_NAMES = ("takeoff", "cruise", "loiter", "descent", "done")


@dataclasses.dataclass(frozen=True)
class NavParams:
  """Guidance parameters (PX4 names where they exist)."""
  planar: bool = False         # rover: distances and guidance in the horizontal plane only
  xy_p: float = 0.95           # MPC_XY_P  (1/s) cross-track and hold gain
  z_p: float = 1.0             # MPC_Z_P   (1/s)
  acc_brake: float = 2.0       # deceleration used to plan stops and corner slow-downs (m/s^2, < MPC_ACC_HOR)
  acc_turn: float = 3.0        # lateral acceleration allowed in a corner (m/s^2)
  xy_vel_max: float = 12.0     # MPC_XY_VEL_MAX
  z_vel_max_up: float = 3.0    # MPC_Z_VEL_MAX_UP
  z_vel_max_dn: float = 1.5    # MPC_Z_VEL_MAX_DN (descent speed above MPC_LAND_ALT2)
  tko_speed: float = 2.5       # MPC_TKO_SPEED (climb rate in take-off)
  land_speed: float = 0.3      # final landing descent below land_alt2 (PX4 MPC_LAND_SPEED; PX4's MPC_LAND_CRWL is
  #                              0.3): 0.2 m/s under the S9 bound (0.5), for the EKF's vertical velocity error (up to
  #                              ~0.15 m/s in gusts) plus gust-driven tracking error; 0.4 left ~1 % of landings above 0.5
  land_alt2: float = 5.0       # MPC_LAND_ALT2 (m)
  hold_speed_max: float = 3.0  # speed cap when holding a point (loiter, landing xy)
  turn_zone: float = 2.0       # turn zone = this many acceptance radii around an intermediate waypoint
  final_radius: float = 0.5    # drone mission that does not land: its last waypoint counts as reached within this
  #                              many acceptance radii (PX4 then holds that waypoint; the episode ends at once, and
  #                              5 m short of it left 2.5 % of attack-free missions just outside the 5 m RSR radius)


@struct.dataclass
class NavState:
  """phase, target (current waypoint index) int32; leg_start [3]; loiter_timer, time (s); reach_time [MAX_WP] (s,
  -1 = not reached)."""
  phase: jnp.ndarray
  target: jnp.ndarray
  leg_start: jnp.ndarray
  loiter_timer: jnp.ndarray
  time: jnp.ndarray
  reach_time: jnp.ndarray


def nav_init(mission) -> NavState:
  has_takeoff = mission.takeoff_alt > 0
  start = mission.home + jnp.array([0.0, 0.0, 1.0]) * mission.takeoff_alt
  return NavState(phase=jnp.where(has_takeoff, TAKEOFF, CRUISE).astype(jnp.int32),
                  target=jnp.zeros((), jnp.int32), leg_start=start, loiter_timer=jnp.zeros(()),
                  time=jnp.zeros(()), reach_time=-jnp.ones_like(mission.deadline))


def _norm(v, planar):
  return norm(v[..., :2]) if planar else norm(v)


def corner_speed(p: NavParams, mission, idx):
  """Speed (m/s) at which to pass waypoint idx: 0 at the last waypoint and the loiter waypoint."""
  n = mission.n_waypoints
  wp = mission.waypoints
  prev = jnp.where(idx > 0, wp[jnp.maximum(idx - 1, 0)], mission.home + jnp.array([0, 0, 1.0]) * mission.takeoff_alt)
  nxt = wp[jnp.minimum(idx + 1, wp.shape[0] - 1)]
  a = (wp[idx] - prev)[:2]
  b = (nxt - wp[idx])[:2]
  cosang = dot(a, b) / (norm(a) * norm(b) + 1e-6)
  half = 0.5 * jnp.arccos(jnp.clip(cosang, -1.0, 1.0))
  v = jnp.sqrt(p.acc_turn * mission.acceptance_radius / jnp.maximum(jnp.tan(half), 1e-3))
  v = jnp.minimum(v, mission.cruise_speed)
  stop = (idx >= n - 1) | (idx == mission.loiter_wp)
  return jnp.where(stop, 0.0, v)


def _clip_vel(p: NavParams, v):
  h = norm(v[:2]) + 1e-9
  v = scale_head(v, 2, jnp.minimum(1.0, p.xy_vel_max / h))
  return with_component(v, 2, jnp.clip(v[2], -p.z_vel_max_dn, p.z_vel_max_up))


def _hold(p: NavParams, target, pos):
  v = jnp.array([p.xy_p, p.xy_p, p.z_p]) * (target - pos)
  h = norm(v[:2]) + 1e-9
  return scale_head(v, 2, jnp.minimum(1.0, p.hold_speed_max / h))


def nav_step(p: NavParams, nav: NavState, mission, pos, landed, dt):
  """Advance the phase machine on the estimated position and return the guidance.

  pos: [3] estimated position (m).  landed: [] bool, the land detector (drone on its legs).
  Returns (NavState, vel_sp [3] world m/s, yaw_sp [] rad or NaN-free hold flag, leg_dir [3]).
  """
  wp = mission.waypoints
  n = mission.n_waypoints
  last = n - 1
  tgt = nav.target
  target = wp[tgt]
  planar = p.planar
  pos_g = with_component(pos, 2, 0.0) if planar else pos
  target_g = with_component(target, 2, 0.0) if planar else target
  start_g = with_component(nav.leg_start, 2, 0.0) if planar else nav.leg_start

  # ---- cruise guidance along the leg start -> target ----
  leg = target_g - start_g
  leg_len = norm(leg) + 1e-6
  u = leg / leg_len
  along = dot(pos_g - start_g, u)
  s = jnp.clip(along, 0.0, leg_len)
  closest = start_g + s * u
  remaining = jnp.maximum(leg_len - along, 0.0)
  v_corner = corner_speed(p, mission, tgt)
  # Brake to the corner speed by the switch point (acceptance radius before an intermediate waypoint; a stop at 0).
  to_switch = jnp.maximum(remaining - jnp.where(v_corner > 0, mission.acceptance_radius, 0.0), 0.0)
  v_along = jnp.minimum(mission.cruise_speed, jnp.sqrt(v_corner ** 2 + 2.0 * p.acc_brake * to_switch))
  v_along = jnp.minimum(v_along, v_corner + p.xy_p * remaining)
  gains = jnp.array([p.xy_p, p.xy_p, p.z_p])
  vel_cruise = _clip_vel(p, v_along * u + gains * (closest - pos_g))
  dist = _norm(target - pos, planar)
  r_acc = mission.acceptance_radius
  if not planar:   # a rover stops where its last waypoint is accepted (ArduRover), a multicopter holds it
    r_acc = jnp.where((tgt >= n - 1) & (mission.land <= 0), p.final_radius * r_acc, r_acc)
  passed = (along > leg_len) & (dist < 2.0 * r_acc)
  reached = (dist < r_acc) | passed

  # ---- phase machine ----
  takeoff_pt = mission.home + jnp.array([0.0, 0.0, 1.0]) * mission.takeoff_alt
  climb_left = takeoff_pt[2] - pos[2]
  vel_takeoff = with_component(_hold(p, takeoff_pt, pos), 2, jnp.clip(p.z_p * climb_left + 0.5, 0.0, p.tko_speed))
  takeoff_done = climb_left < 0.5

  land_pt = with_component(wp[last], 2, 0.0)
  h = pos[2]
  # Slow to the landing speed 2 m above MPC_LAND_ALT2 so the final window (S9) starts at the landing speed.
  vz_desc = jnp.clip(p.land_speed + 0.6 * (h - p.land_alt2 - 2.0), p.land_speed, p.z_vel_max_dn)
  vel_descent = with_component(_hold(p, land_pt, pos), 2, -vz_desc)
  vel_loiter = _hold(p, target, pos)
  vel_done = jnp.where(mission.land > 0, jnp.zeros(3), _hold(p, wp[last], pos))
  if planar:
    vel_done = jnp.zeros(3)

  phase = nav.phase
  is_loiter_wp = tgt == mission.loiter_wp
  at_last = tgt >= last
  # Transitions.
  arrive = (phase == CRUISE) & reached
  go_loiter = arrive & is_loiter_wp & (mission.loiter_time > 0)
  finish = arrive & at_last & ~go_loiter
  advance = arrive & ~at_last & ~go_loiter
  loiter_over = (phase == LOITER) & (nav.loiter_timer + dt >= mission.loiter_time)
  loiter_advance = loiter_over & ~at_last
  loiter_finish = loiter_over & at_last
  end_mission = finish | loiter_finish
  to_descent = end_mission & (mission.land > 0)
  to_done = (end_mission & (mission.land <= 0)) | ((phase == DESCENT) & landed)

  new_phase = phase
  new_phase = jnp.where((phase == TAKEOFF) & takeoff_done, CRUISE, new_phase)
  new_phase = jnp.where(go_loiter, LOITER, new_phase)
  new_phase = jnp.where(loiter_advance, CRUISE, new_phase)
  new_phase = jnp.where(to_descent, DESCENT, new_phase)
  new_phase = jnp.where(to_done, DONE, new_phase)
  step_target = advance | loiter_advance
  new_target = jnp.where(step_target, tgt + 1, tgt)
  new_start = jnp.where(step_target, wp[tgt], nav.leg_start)
  new_start = jnp.where((phase == TAKEOFF) & takeoff_done, takeoff_pt, new_start)
  reach_time = jnp.where((jnp.arange(wp.shape[0]) == tgt) & arrive & (nav.reach_time < 0), nav.time,
                         nav.reach_time)
  loiter_timer = jnp.where(phase == LOITER, nav.loiter_timer + dt, 0.0)

  vel_sp = jnp.select([phase == TAKEOFF, phase == CRUISE, phase == LOITER, phase == DESCENT],
                      [vel_takeoff, vel_cruise, vel_loiter, vel_descent], vel_done)
  if planar:
    vel_sp = with_component(vel_sp, 2, 0.0)
  new_nav = NavState(phase=new_phase.astype(jnp.int32), target=new_target.astype(jnp.int32), leg_start=new_start,
                     loiter_timer=loiter_timer, time=nav.time + dt, reach_time=reach_time)
  return new_nav, vel_sp, u
