"""Attack-free compliance of the autopilot alone in the conditions that used to violate the specs (issue 5: attack-free
SVR must be 0 %): a long leg into a strong headwind (S7: the velocity loop's output was capped at 5 m/s^2 with the
integrator held at 3, so drag left the drone below MPC_XY_VEL_MIN), a sharp corner (the braking profile reached the corner speed at the corner,
after the waypoint switch, and the drone overshot the turn by ~5 m towards the obstacles) and gusty landings (S9: a
0.4 m/s landing setpoint plus the EKF's vertical velocity error crossed MPC_LAND_SPEED = 0.5 m/s in ~1 % of landings).

One scripted mission, 12 episodes in one jitted rollout with per-episode wind / gusts written into the domain
randomisation: 4 in a steady 9.5 m/s headwind (drag +20 %), 8 in open-mountain gusts (6 m/s wind, gust std 2.2 m/s).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import missions as missions_lib
from envs.base import tree_where
from specguard_jax import attacks

N_HEAD, N_GUST = 4, 8
CORNER_DEG = 100.0     # the generator's max_turn_deg


def _mission(cfg: missions_lib.MissionConfig) -> missions_lib.Mission:
  """Take-off to 15 m, 110 m east, a 100 deg left turn, 60 m, land; cruise 7 m/s (the generator's slowest)."""
  a = math.radians(CORNER_DEG)
  wps = np.array([[110.0, 0.0, 15.0], [110.0 + 60.0 * math.cos(a), 60.0 * math.sin(a), 15.0]], np.float32)
  arr = np.repeat(wps[-1:], missions_lib.MAX_WAYPOINTS, axis=0)
  arr[:2] = wps
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  home, wp, n, tko, cruise = f32(np.zeros(3)), f32(arr), jnp.int32(2), f32(15.0), f32(7.0)
  lw, lt, land = jnp.int32(-1), f32(0.0), f32(1.0)
  window_open, deadline, duration = missions_lib.mission_timing(home, wp, n, tko, cruise, lw, lt, land, cfg)
  return missions_lib.Mission(home=home, waypoints=wp, n_waypoints=n, window_open=window_open, deadline=deadline,
                              takeoff_alt=tko, cruise_speed=cruise, acceptance_radius=f32(cfg.acceptance_radius),
                              loiter_wp=lw, loiter_time=lt, loiter_radius=f32(cfg.loiter_radius), land=land,
                              nominal_duration=duration)


@pytest.fixture(scope="module")
def flights():
  env = envs.make("drone", world="open_mountain")
  mission = _mission(env.mission_cfg)
  b = N_HEAD + N_GUST
  wind = np.zeros((b, 3), np.float32)
  wind[:N_HEAD, 0] = -9.5                                   # blowing west: a headwind on the 110 m east leg
  wind[N_HEAD:, :2] = 6.0 * np.stack([np.cos(np.arange(N_GUST)), np.sin(np.arange(N_GUST))], -1)
  gust = np.where(np.arange(b) < N_HEAD, 0.0, 2.2).astype(np.float32)
  drag = np.where(np.arange(b) < N_HEAD, 1.2, 1.0).astype(np.float32)
  corner = np.asarray(mission.waypoints[0])
  legs = np.stack([[[0.0, 0.0], corner[:2]], [corner[:2], np.asarray(mission.waypoints[1])[:2]]])   # [2, 2, 2]

  def off_path(p):
    """Horizontal distance [B] from positions p [B, 2] to the path (both legs)."""
    a, d = legs[:, 0], legs[:, 1] - legs[:, 0]
    t = jnp.clip(jnp.einsum("bkj,kj->bk", p[:, None] - a, d) / np.sum(d * d, -1), 0.0, 1.0)
    return jnp.min(jnp.linalg.norm(p[:, None] - (a + t[..., None] * d), axis=-1), axis=-1)

  @jax.jit
  def fly(keys):
    ms = jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), mission)
    state = jax.vmap(lambda k, m: env.reset_in_world(k, None, m, attacks.no_attack()))(keys, ms)
    sim = state.info["sim"]
    dr = dict(sim["dr"], wind=jnp.asarray(wind), gust_std=jnp.asarray(gust), drag_scale=jnp.asarray(drag),
              mass_scale=jnp.ones(b), thrust_gain=jnp.ones(b))
    state = state.replace(info=dict(state.info, sim=dict(sim, dr=dr)))
    step = jax.vmap(env.step)
    rec0 = {"land_desc": jnp.zeros(b), "corner_dev": jnp.zeros(b), "speed_after_8s": jnp.full(b, 99.0)}

    def cond(c):
      s, t, _ = c
      return (t < 1500) & ~jnp.all(s.done > 0)

    def body(c):
      s, t, rec = c
      nxt = step(s, jnp.zeros((b, 3)))
      live = s.done == 0
      sig, truth, est = nxt.info["signals"], nxt.info["sim"]["truth"], nxt.info["sim"]["ekf"].pos
      near = jnp.linalg.norm(truth.pos[:, :2] - corner[:2], axis=-1) < 25.0
      cruise = (sig["in_cruise"] > 0) & (nxt.info["time"] > 8.0 + 7.0)   # 8 s after take-off ends (~7 s)
      rec = {"land_desc": jnp.maximum(rec["land_desc"], jnp.where(live & (sig["in_landing"] > 0),
                                                                  sig["descent_speed"], 0.0)),
             "corner_dev": jnp.maximum(rec["corner_dev"], jnp.where(live & near, off_path(est[:, :2]), 0.0)),
             "speed_after_8s": jnp.minimum(rec["speed_after_8s"], jnp.where(live & cruise & (sig["dist_wp"] > 10.0),
                                                                            sig["speed_xy"], 99.0))}
      return tree_where(s.done > 0, s, nxt), t + 1, rec

    s, _, rec = jax.lax.while_loop(cond, body, (state, jnp.zeros((), jnp.int32), rec0))
    ep = s.info["episode"]
    return dict(rec, rob=s.info["spec_robustness"], complete=ep["complete"], crash=ep["crash"],
                collision=ep["collision"], done=s.done)

  out = jax.device_get(fly(jax.random.split(jax.random.PRNGKey(7), b)))
  return {k: np.asarray(v) for k, v in out.items()} | {"names": env.spec_names}


def test_missions_complete(flights):
  assert np.all(flights["done"] > 0) and np.all(flights["complete"] > 0)
  assert not np.any(flights["crash"]) and not np.any(flights["collision"])


def test_no_spec_violated(flights):
  """Every spec holds in every episode (S7 failed in all 4 headwind episodes with the old 5 m/s^2 output cap)."""
  bad = {(i, n) for i in range(len(flights["rob"])) for n, r in zip(flights["names"], flights["rob"][i]) if r < 0}
  assert not bad, bad


def test_headwind_cruise_speed(flights):
  """In a steady 9.5 m/s headwind with 20 % more drag the drone holds well above MPC_XY_VEL_MIN (5 m/s) once it has
  accelerated (it cruises at 7 m/s, 5.9-6.2 at its slowest; the old output cap held it at 4.2-4.4 m/s)."""
  assert np.all(flights["speed_after_8s"][:N_HEAD] > 5.5), flights["speed_after_8s"][:N_HEAD]


def test_landing_keeps_a_margin_under_land_speed(flights):
  """Gusty landings stay under MPC_LAND_SPEED with margin: the worst descent speed of the landing window is < 0.5 in
  every episode and < 0.42 m/s in the median one (now 0.34-0.39; the 0.4 m/s setpoint gave a median of 0.46)."""
  d = flights["land_desc"]
  assert np.all(d > 0.2), d                  # the window was flown
  assert np.all(d < 0.5), d
  assert np.median(d[N_HEAD:]) < 0.42, d


def test_corner_not_overshot(flights):
  """Braking to the corner speed by the waypoint switch keeps the 100 deg turn within 3 m of the path (now <= 2.2 m;
  braking to the corner itself overshot by up to 6 m in the gusty episodes). Measured on the autopilot's estimated
  position, the path it tracks: the true one adds the GPS's slowly correlated error (metres, sensors.SensorConfig),
  which no controller sees."""
  assert np.all(flights["corner_dev"] < 3.0), flights["corner_dev"]
