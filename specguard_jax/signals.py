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
  "loiter_deviation": "horizontal distance from the loiter centre minus nothing (0 outside the loiter phase), m",
  # --- speeds ---
  "speed_xy": "horizontal ground speed, m/s",
  "speed_z": "vertical speed, up positive, m/s",
  "descent_speed": "max(0, -speed_z): sink rate, m/s",
  # --- mission phase indicators (0.0 or 1.0) ---
  "in_takeoff": "1 while climbing to the take-off altitude",
  "in_cruise": "1 while flying/driving between waypoints",
  "in_loiter": "1 while loitering",
  "in_landing": "1 while descending to land",
  "time": "mission time since reset, s",
}

SIGNAL_NAMES = tuple(MONITORED_SIGNALS)
