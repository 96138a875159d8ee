"""A user's own QGroundControl plan and autopilot parameters: geofence zones (inclusion / exclusion polygons and
circles) as the mission's fence margins, rally points, survey items expanded into lawn-mower waypoints, the home
fence and the ArduPilot / PX4 names of a parameter file, and the fallback's hold at the nearest rally point."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from envs import geofence as gf
from envs import mission_files as mf
from envs import worlds as worlds_lib
from specguard_jax.autopilot import fallback
from specguard_jax.specs import params as P
from specguard_jax.specs import vehicle_params as V

HOME = (49.2606, -123.2460, 80.0)


def ll(x, y):
  """lat, lon of the ENU point (x, y) m about HOME (the loader's own projection)."""
  lat, lon = mf.enu_to_latlon(x, y, HOME[0], HOME[1])
  return [float(lat), float(lon)]


def wp(x, y, z=15.0):
  return {"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0, None, *ll(x, y), z],
          "autoContinue": True}


def plan_text(items, polygons=(), circles=(), rally=()):
  """A .plan: polygons ((inclusion, [(x, y), ...]), ...), circles ((inclusion, x, y, r), ...), rally ((x, y, alt),)."""
  return json.dumps({
    "fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
    "mission": {"items": items, "plannedHomePosition": list(HOME), "version": 2},
    "geoFence": {"version": 2,
                 "polygons": [{"inclusion": inc, "polygon": [ll(*p) for p in pts], "version": 1}
                              for inc, pts in polygons],
                 "circles": [{"inclusion": inc, "circle": {"center": ll(x, y), "radius": r}, "version": 1}
                             for inc, x, y, r in circles]},
    "rallyPoints": {"version": 2, "points": [ll(x, y) + [a] for x, y, a in rally]}})


def square(cx, cy, h):
  return [(cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h)]


FENCED = dict(polygons=((False, square(100, 0, 10)), (True, square(50, 0, 100))), circles=((True, 300, 0, 60),),
              rally=((50, 40, 12), (200, -40, 14)))


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_fence_margins_at_known_points(vehicle):
  plan = mf.loads_plan(plan_text([wp(20, 0), wp(60, 0)], **FENCED), "plan", vehicle)
  fence = plan.geofence
  assert fence.n_zones == 3 and fence.any_inclusion == (vehicle == "drone")
  margin = lambda x, y: float(gf.zone_margins(fence, jnp.array([x, y], jnp.float32)))
  if vehicle == "drone":
    # inside the inclusion square (edges at x = -50, 150, y = -100, 100), 20 m from the exclusion square (90..110)
    assert margin(70, 0) == pytest.approx(20.0, abs=0.01)
    assert margin(100, 0) == pytest.approx(-10.0, abs=0.01)      # in the exclusion zone: 10 m deep
    assert margin(0, 95) == pytest.approx(5.0, abs=0.01)         # 5 m from the inclusion square's north edge
    # in the inclusion circle (centre 300, 0, r 60) but outside the square: PX4 needs one inclusion zone
    assert margin(310, 0) == pytest.approx(50.0, abs=0.01)
  else:   # ArduPilot needs every inclusion zone: outside the circle or the square is outside the fence
    assert margin(70, 0) == pytest.approx(-170.0, abs=0.01)
    assert margin(310, 0) == pytest.approx(-160.0, abs=0.01)
  np.testing.assert_allclose(plan.rally_points, [[50, 40, 12 if vehicle == "drone" else 0],
                                                 [200, -40, 14 if vehicle == "drone" else 0]], atol=0.01)
  # the world's fence margin (S12's signal) uses them, the generated fences dropped
  world = worlds_lib.make_world(np.zeros((1, 4)), [False], np.zeros((1, 6)), [False], [[0, 0, 50, 50, 0, 120.0]],
                                [True], [0, 1, 0, 1], True, worlds_lib.NO_CEILING, np.zeros(3), 0.0)
  world = worlds_lib.with_geofence(world, fence, replace_fences=True, rally_points=plan.rally_points)
  m, h, v = worlds_lib.fence_distances(world, jnp.array([100.0, 0.0, 15.0]))
  assert float(m) == pytest.approx(margin(100, 0), abs=1e-4) and float(h) == float(m) and float(v) == 1e3
  assert float(m) < 0 and not bool(world.fence_mask[0]) and not bool(world.boundary_on)


def test_home_fence_and_ceiling():
  fence = gf.make_geofence(max_radius=120.0)
  assert float(gf.zone_margins(fence, jnp.array([0.0, 100.0]))) == pytest.approx(20.0, abs=1e-4)
  world = worlds_lib.make_world(np.zeros((1, 4)), [False], np.zeros((1, 6)), [False], np.zeros((1, 6)), [False],
                                [0, 1, 0, 1], False, worlds_lib.NO_CEILING, np.zeros(3), 0.0)
  world = worlds_lib.with_geofence(world, fence, max_alt=30.0)
  m, _, v = worlds_lib.fence_distances(world, jnp.array([0.0, 50.0, 25.0]))
  assert float(m) == pytest.approx(5.0) and float(v) == pytest.approx(5.0)   # the ceiling (30 m) is nearest
  assert not gf.empty_geofence().active


def test_survey_expands_to_lawn_mower_waypoints():
  poly = [ll(0, 0), ll(100, 0), ll(100, 60), ll(0, 60)]
  survey = {"type": "ComplexItem", "complexItemType": "survey", "version": 5, "angle": 0, "polygon": poly,
            "TransectStyleComplexItem": {"CameraCalc": {"DistanceToSurface": 25, "DistanceToSurfaceRelative": True,
                                                        "AdjustedFootprintSide": 20}}}
  m = mf.loads_plan(plan_text([wp(-20, 0), survey]), "plan", "drone").mission
  n = int(m.n_waypoints)
  assert n == 11   # the waypoint before it + 5 north-south transects, entered and left at the polygon's edge
  expected = [[-20, 0]] + [p for x, up in ((10, 1), (30, 0), (50, 1), (70, 0), (90, 1))
                           for p in ([[x, 0], [x, 60]] if up else [[x, 60], [x, 0]])]
  np.testing.assert_allclose(np.asarray(m.waypoints)[:n, :2], expected, atol=0.01)
  np.testing.assert_allclose(np.asarray(m.waypoints)[1:n, 2], 25.0)
  # a polygon narrower than one spacing: one transect through its middle
  np.testing.assert_allclose(mf.survey_waypoints([[0, 0], [10, 0], [10, 30], [0, 30]], 0.0, 20.0),
                             [[5, 0], [5, 30]], atol=1e-9)


@pytest.mark.parametrize("text, message", [
  (plan_text([wp(10, 0), {"type": "ComplexItem", "complexItemType": "CorridorScan"}]),
   "f.plan: item 2: ComplexItem of type 'CorridorScan' is not supported"),
  (plan_text([wp(10, 0)], polygons=((True, [(0, 0), (1, 1)]),)),
   "f.plan: geoFence polygon 1: must be an object with a 'polygon' list of at least 3"),
  (plan_text([wp(10, 0)], circles=((True, 0, 0, 0.0),)), "f.plan: geoFence circle 1: radius 0 m is below"),
  (plan_text([wp(10, 0)], circles=((False, 20000, 0, 5.0),)), "f.plan: geoFence circle 1: .* km from home"),
  (plan_text([wp(10, 0)]).replace('"points": []', '"points": [[49.3, -123.2]]'),
   "f.plan: rally point 1: must be \\[lat, lon, alt\\]"),
])
def test_bad_plan_extras_one_line(text, message):
  with pytest.raises(mf.MissionFileError, match=message) as e:
    mf.loads_plan(text, "plan", "drone", name="f.plan")
  assert "\n" not in str(e.value)


def test_autopilot_parameter_names():
  parm = ("CRUISE_SPEED 1.0\nWP_RADIUS 2.0\nAVOID_MARGIN 2.0\nFENCE_MARGIN 2.0\nFENCE_ENABLE 1\nFENCE_TYPE 6\n"
          "FENCE_RADIUS 300\nFENCE_ALT_MAX 40\nFENCE_TOTAL 0\n")
  vs = V.settings_from_params(P.loads_params(parm, "parm", name="r.parm"), "rover")
  assert dict(vs.spec_overrides) == {"WPNAV_RADIUS": 2.0, "CRUISE_SPEED_MIN": 0.5, "AVOID_MARGIN": 2.0,
                                     "FENCE_MARGIN": 2.0}
  assert vs.cruise_speed == 1.0 and vs.acceptance_radius == 2.0
  assert vs.fence_radius == 300.0 and vs.fence_alt_max == 0.0     # FENCE_TYPE 6: circle and polygons, no altitude
  off = V.settings_from_params(P.loads_params(parm.replace("FENCE_ENABLE 1", "FENCE_ENABLE 0"), "parm"), "rover")
  assert off.fence_radius == 0.0
  px4 = "1\t1\tGF_MAX_HOR_DIST\t120\t9\n1\t1\tGF_MAX_VER_DIST\t30\t9\n1\t1\tMPC_XY_CRUISE\t6\t9\n"
  vd = V.settings_from_params(P.loads_params(px4, "params"), "drone")
  assert (vd.fence_radius, vd.fence_alt_max, vd.cruise_speed) == (120.0, 30.0, 6.0)
  with pytest.raises(P.SpecError, match="r.parm: contradictory parameters: CRUISE_SPEED_MIN = 13"):
    V.settings_from_params(P.loads_params("CRUISE_SPEED 26\n", "parm"), "rover", where="r.parm")


def test_fallback_hold_goes_to_the_nearest_rally_point():
  cfg = fallback.FallbackConfig(margin=5.0, min_speed=5.0)
  vel = jnp.array([8.0, 0.0, 0.0])
  rally = jnp.array([[0.0, 100.0, 0.0], [30.0, -40.0, 0.0]])
  pos = jnp.zeros(3)
  held = fallback.apply(cfg, vel, 6.0, 50.0, jnp.zeros(3), True)     # sigma past the margin: stops
  np.testing.assert_allclose(held[:2], 0.0)
  to_rally = fallback.apply(cfg, vel, 6.0, 50.0, jnp.zeros(3), True, pos, rally)
  np.testing.assert_allclose(to_rally[:2], np.array([0.6, -0.8]) * 6.0, atol=1e-5)   # nearest: 50 m away, 6 m/s
  near = fallback.apply(cfg, vel, 6.0, 50.0, jnp.zeros(3), True, jnp.array([29.0, -40.0, 0.0]), rally)
  np.testing.assert_allclose(near[:2], [0.5, 0.0], atol=1e-5)   # slows to k_push * distance on arrival
  slow = fallback.apply(cfg, vel, 2.0, 50.0, jnp.zeros(3), True, pos, rally)   # not holding: the rally is unused
  np.testing.assert_allclose(slow, fallback.apply(cfg, vel, 2.0, 50.0, jnp.zeros(3), True))


def test_env_takes_the_plan_and_parameter_file(tmp_path):
  import jax

  import envs
  plan = tmp_path / "p.plan"
  plan.write_text(plan_text([wp(20, 0, 0), wp(60, 0, 0)], **FENCED))
  parm = tmp_path / "r.parm"
  parm.write_text("CRUISE_SPEED 3\nWP_RADIUS 1.5\nFENCE_RADIUS 250\n")
  env = envs.make("rover", mission_file=str(plan), params_file=str(parm))
  params = env.spec_table.params
  assert params["CRUISE_SPEED_MIN"] == 1.5 and params["WPNAV_RADIUS"] == 1.5
  assert env.mission_cfg.cruise_speed == (3.0, 3.0) and env.mission_cfg.acceptance_radius == 1.5
  m = env.sample_mission(jax.random.PRNGKey(0))
  assert int(m.n_waypoints) == 2 and float(m.cruise_speed) == 3.0 and float(m.acceptance_radius) == 1.5
  assert env.geofence.n_zones == 3 and env.geofence.max_radius == 250.0 and env.plan.rally_points.shape == (2, 3)
  plain = envs.make("rover")
  assert plain.plan is None and plain.geofence is None
