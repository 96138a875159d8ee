"""Names and meanings of the monitored signals the env exposes for the mission specifications (STL).

Every env step fills `State.info["signals"]`, a dict from these names to float32 arrays of shape [] per vehicle
(computed from the TRUE state, never from attacked sensors). The STL specs (`specguard_jax.specs`) and rewards
(`specguard_jax.rewards`) are written over these names only.
"""

MONITORED_SIGNALS = {
  # --- distances (metres) ---
  "obstacle_distance": "3D distance from the vehicle centre to the nearest obstacle surface, m (capped at 100)",
  "path_deviation": "3D distance from the vehicle to the current mission leg (segment previous->current waypoint), m",
  "altitude": "height of the vehicle centre above the ground plane, m",
  "dist_wp": "3D distance to the current target waypoint, m",
  "dist_final": "3D distance to the final waypoint of the mission, m",
  "wp_slack": "seconds left before the current target waypoint's deadline (negative: late), s",
  "fence_margin": "signed 3D distance to the nearest forbidden region (keep-out prisms, outside the operating "
                  "boundary, above the ceiling); > 0 on the allowed side, m",
  "fence_h": "signed horizontal margin to the nearest fence (> 0 allowed side), m",
  "fence_v": "signed vertical margin to the nearest fence (> 0 allowed side: above a keep-out prism's top or below "
             "the ceiling), m",
  "loiter_deviation": "horizontal distance from the loiter centre (0 outside the loiter phase), m",
  # --- speeds ---
  "speed_xy": "horizontal ground speed, m/s",
  "speed_z": "vertical speed, up positive, m/s",
  "descent_speed": "max(0, -speed_z): sink rate, m/s",
  # --- mission phase indicators (0.0 or 1.0; at most one is 1 at a time; all 0 before take-off and after landing) ---
  # Windows follow PX4's ramps so the speed specs have a meaningful window [t_i, t_j]:
  "in_takeoff": "1 in the take-off climb window: take-off phase, 1 m above ground up to 2 m below the take-off "
                "altitude (S10 applies here)",
  "in_cruise": "1 while flying/driving between waypoints, excluding turn zones within 2 acceptance radii of an "
               "intermediate waypoint (where the vehicle slows for the corner) (S7 applies here)",
  "in_turn": "1 in the turn zone around an intermediate waypoint (cruise phase, near the corner)",
  "in_loiter": "1 while loitering around a waypoint (S11 applies here)",
  "in_descent": "1 while descending from the last waypoint towards the landing zone, above 5 m (MPC_LAND_ALT2)",
  "in_landing": "1 in the final landing window: descending below 5 m until touchdown (S9 applies here)",
  "time": "mission time since reset, s",
}

SIGNAL_NAMES = tuple(MONITORED_SIGNALS)
