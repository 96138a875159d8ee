"""Attack campaigns (specguard_jax.evaluation.campaign_settings) and `evaluate.py --suite hard`: hazard-timed onsets
on a constructed mission with known geometry, attacks that last until the episode ends, the multi-sensor pairs, the
designed ramp rates, and the hard suite end to end at a tiny size (its report opens with the campaign table)."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evaluate as evaluate_cli
from envs import hazards
from envs import missions as missions_lib
from envs import worlds as worlds_lib
from specguard_jax import attacks
from specguard_jax import evaluation as E
from specguard_jax import metrics as M
from specguard_jax.cli import evaluate as cli

CFG = missions_lib.MissionConfig.drone()
ALT, SPEED = 10.0, 10.0          # m, m/s: take-off 5 s at 2 m/s, then level legs at 10 m/s


def _mission(waypoints, loiter_wp=-1, loiter_time=0.0, land=0.0):
  """A mission through `waypoints` [(x, y), ...] at ALT, SPEED, timed like generated ones (missions.mission_timing)."""
  m = missions_lib.MAX_WAYPOINTS
  n = len(waypoints)
  wps = np.zeros((m, 3), np.float32)
  wps[:n, :2] = waypoints
  wps[:, 2] = ALT
  wps[n:] = wps[n - 1]
  home = jnp.zeros(3)
  args = (home, jnp.asarray(wps), jnp.int32(n), jnp.float32(ALT), jnp.float32(SPEED), jnp.int32(loiter_wp),
          jnp.float32(loiter_time), jnp.float32(land))
  window_open, deadline, duration = missions_lib.mission_timing(*args, CFG)
  return missions_lib.Mission(home=home, waypoints=jnp.asarray(wps), n_waypoints=jnp.int32(n),
                              window_open=window_open, deadline=deadline, takeoff_alt=jnp.float32(ALT),
                              cruise_speed=jnp.float32(SPEED), acceptance_radius=jnp.float32(5.0),
                              loiter_wp=jnp.int32(loiter_wp), loiter_time=jnp.float32(loiter_time),
                              loiter_radius=jnp.float32(8.0), land=jnp.float32(land), nominal_duration=duration)


def _world(cylinders=(), fences=()):
  """Cylinders (x, y, radius, height) and keep-out fences (cx, cy, half_x, half_y, yaw, height); no boundary."""
  cyl = np.full((worlds_lib.MAX_CYLINDERS, 4), 1e4, np.float32)
  cyl[:len(cylinders)] = np.reshape(cylinders, (-1, 4))
  fen = np.full((worlds_lib.MAX_FENCES, 6), 1e4, np.float32)
  fen[:len(fences)] = np.reshape(fences, (-1, 6))
  return worlds_lib.make_world(
      cyl, np.arange(worlds_lib.MAX_CYLINDERS) < len(cylinders), np.full((worlds_lib.MAX_BOXES, 6), 1e4),
      np.zeros(worlds_lib.MAX_BOXES, bool), fen, np.arange(worlds_lib.MAX_FENCES) < len(fences),
      np.zeros(4), False, worlds_lib.NO_CEILING, np.zeros(3), 0.0)


def test_hazard_onset_straight_past_an_obstacle():
  """East 200 m at 10 m/s after a 5 s climb, a pole 8 m beside the path at x = 80 m: closest approach at 13 s."""
  mission = _mission([(200.0, 0.0)])
  world = _world(cylinders=[(80.0, 9.0, 1.0, 20.0)])
  times, valid = jax.jit(hazards.hazard_times, static_argnums=2)(mission, world, CFG)
  assert valid.tolist() == [True, False, False, False, False]    # no fence, no turn, no loiter, no landing
  assert abs(float(times[0]) - 13.0) < 1.0
  onset, kind, t_h = hazards.hazard_onset(mission, world, CFG, jax.random.PRNGKey(0), lead_s=(3.0, 3.0))
  assert int(kind) == 0 and abs(float(onset) - 10.0) < 1.0 and float(t_h) - float(onset) == pytest.approx(3.0)
  # the onset reaches the attack unchanged
  acfg = attacks.AttackConfig(sensors=("gps",), profiles=("overt",), onset="given")
  s = attacks.sample_attack(acfg, jax.random.PRNGKey(1), mission.nominal_duration, onset)
  assert float(s.onset) == pytest.approx(float(onset))
  with pytest.raises(ValueError, match="needs the onset"):
    attacks.sample_attack(acfg, jax.random.PRNGKey(1), mission.nominal_duration)


def test_hazard_times_turn_fence_loiter_landing():
  """An L-shaped mission: 100 m east, then 100 m north (90 deg turn at 15 s), a 20 s loiter at the corner, landing
  after the second leg (35 s + 10 s descent); a keep-out fence beside the second leg's middle (at 40 s)."""
  mission = _mission([(100.0, 0.0), (100.0, 100.0)], loiter_wp=0, loiter_time=20.0, land=1.0)
  world = _world(fences=[(115.0, 50.0, 5.0, 5.0, 0.0, 120.0)])
  times, valid = hazards.hazard_times(mission, world, CFG)
  assert float(mission.nominal_duration) == pytest.approx(5.0 + 20.0 + 20.0 + 10.0)
  assert valid.tolist() == [False, True, True, True, True]
  np.testing.assert_allclose(np.asarray(times)[1:], [40.0, 15.0, 15.0, 45.0], atol=1.0)
  # the pick is seeded and only among valid hazards
  kinds = {int(hazards.hazard_onset(mission, world, CFG, jax.random.PRNGKey(i))[1]) for i in range(40)}
  assert kinds == {1, 2, 3, 4}


def test_long_lasts_until_the_episode_ends():
  s = E.campaign_setting("long", "gps")
  assert s.name == "long/gps/overt" and s.attack.until_end
  sched = attacks.sample_attack(s.attack, jax.random.PRNGKey(0), jnp.float32(100.0))
  assert 15.0 <= float(sched.onset) <= 50.0
  assert bool(attacks.attack_active(sched, 1e6)) and float(sched.duration) >= attacks.attacks.UNTIL_END


def test_multi_names_and_masks():
  sets = E.campaign_settings(("multi",), attacks.SENSOR_NAMES)
  assert [s.name for s in sets] == ["multi/gps+flow/overt", "multi/gps+mag/overt", "multi/gps+baro/overt",
                                    "multi/gps+gyro/overt"]
  for s, pair in zip(sets, E.MULTI_PAIRS):
    for i in range(4):
      mask = np.asarray(attacks.sample_attack(s.attack, jax.random.PRNGKey(i), jnp.float32(100.0)).mask)
      want = np.asarray([n in pair for n in attacks.SENSOR_NAMES], np.float32)
      np.testing.assert_array_equal(mask, want)
  rover = E.campaign_settings(("multi",), tuple(x for x in attacks.SENSOR_NAMES if x != "flow"))
  assert "multi/gps+flow/overt" not in [s.name for s in rover] and len(rover) == 3


def test_designed_ramp_rate():
  """The designed campaign ramps each mission's own bias at the sensor's designed rate, until the episode ends."""
  s = E.campaign_setting("designed", "baro", designed_rates={"baro": 0.25})
  assert s.name == "designed/baro/stealthy" and s.attack.until_end
  sched = attacks.sample_attack(s.attack, jax.random.PRNGKey(3), jnp.float32(100.0))
  mag = float(np.linalg.norm(np.asarray(sched.bias)[attacks.SENSOR_NAMES.index("baro")]))
  assert float(sched.ramp_time) == pytest.approx(mag / 0.25, rel=1e-5)
  assert int(sched.profile) == attacks.attacks.STEALTHY
  with pytest.raises(ValueError, match="no designed ramp rate"):
    E.campaign_setting("designed", "gyro", designed_rates={"baro": 0.25})


def _plan(*argv):
  return cli.plan(cli.parse_args(list(argv)))


def test_hard_suite_plan(monkeypatch):
  """All 10 worlds, the campaigns only, controllers by name from the registry (SpecGuard only with a run), and the
  variants hook (e.g. DeLorean per reconstruction mode) replacing the registered controller."""
  p = _plan("--suite", "hard")
  g = p["groups"]["main"]
  assert g["worlds"] == worlds_lib.PRESET_NAMES and len(g["worlds"]) == 10
  names = [s.name for s in g["settings"]]
  assert names[0] == "attack_free" and all(E.campaign_of(n) in ("long", "hazard", "multi") for n in names[1:])
  assert g["designed"] == attacks.SENSOR_NAMES and "designed" in p["campaigns"]
  assert "delorean" in g["controllers"] and not any(str(c).startswith("specguard") for c in g["controllers"])
  monkeypatch.setattr(cli, "HARD_VARIANTS", (("delorean_a", "delorean", (("detector_delay", 0.5),)),))
  ctrls = _plan("--suite", "hard")["groups"]["main"]["controllers"]
  assert "delorean" not in ctrls and ("variant", "delorean_a", "delorean", (("detector_delay", 0.5),)) in ctrls
  with pytest.raises(ValueError, match="unknown campaign"):
    _plan("--campaigns", "loud")


def test_false_alarm_group_plan():
  """--false-alarms: a group of zero-bias attacks (an oracle alarm on attack-free flights) in which every controller
  but no protection flies with the oracle detector; --suite paper has it on the GPS by default."""
  p = _plan("--controllers", "delorean,fallback", "--false-alarms", "gps,baro")
  g = p["groups"]["false_alarm"]
  assert [s.name for s in g["settings"]] == ["false_alarm/gps", "false_alarm/baro"]
  assert g["controllers"] == ["no_protection", ("variant", "delorean", "delorean", cli.FORCED_ALARM),
                              ("variant", "fallback", "fallback", cli.FORCED_ALARM)]
  sched = attacks.sample_attack(g["settings"][0].attack, jax.random.PRNGKey(0), jnp.float32(100.0))
  assert float(np.sum(sched.mask)) == 1.0 and float(np.abs(np.asarray(sched.bias)).max()) == 0.0
  assert float(sched.onset) < 1e8                                  # an attack window, with nothing injected
  assert "false_alarm" not in _plan("--controllers", "delorean")["groups"]
  assert [s.name for s in _plan("--suite", "paper")["groups"]["false_alarm"]["settings"]] == ["false_alarm/gps"]
  with pytest.raises(ValueError, match="--false-alarms: unknown sensor.s. radar"):
    _plan("--false-alarms", "radar")


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
  out = str(tmp_path_factory.mktemp("hard"))
  rc = evaluate_cli.main(["--suite", "hard", "--controllers", "no_protection", "--sensors", "gps,gyro",
                          "--profiles", "overt", "--worlds", "urban_park", "--missions", "2", "--mission-s", "30,40",
                          "--max-s", "90", "--designed-rates", "gps=1.1,gyro=0.005", "--traj", "0", "--no-figures",
                          "--no-progress", "--out", out])
  assert rc == 0
  with open(os.path.join(out, "report.json")) as f:
    yield out, json.load(f)
  E.clear_cache()


def test_hard_suite_end_to_end(hard):
  out, rep = hard
  g = rep["groups"]["main"]
  assert g["settings"] == ["attack_free", "long/gps/overt", "long/gyro/overt", "hazard/gps/overt",
                           "hazard/gyro/overt", "multi/gps+gyro/overt", "designed/gps/stealthy",
                           "designed/gyro/stealthy"]
  table = rep["experiments"]["hard"]
  assert list(table) == ["attack_free", "long", "hazard", "designed", "multi"]
  assert table["hazard"]["no_protection"]["missions"] == 4 and table["hazard"]["no_protection"]["settings"] == 2
  md = open(os.path.join(out, "report.md")).read()
  first = [line for line in md.splitlines() if line.startswith("## ")][0]
  assert first.startswith("## Hard suite") and "| hazard | no_protection | 4 |" in md
  rec = dict(np.load(os.path.join(out, "records/main__no_protection.npz")))
  names = g["settings"]
  for i, s in enumerate(names):
    r = {k: v[rec["setting"] == i] for k, v in rec.items()}
    if E.campaign_of(s) in ("long", "designed"):      # on until the episode ends
      assert (r["attack_end"] > r["t_end"] + 1e6).all(), s
    if E.campaign_of(s) == "hazard":                  # 2-5 s before a hazard point of the mission
      assert (r["hazard_kind"] >= 0).all() and ((r["hazard_t"] - r["onset"]) <= 5.0 + 1e-3).all()
    else:
      assert (r["hazard_kind"] == -1).all()
  # pairing: the same missions (worlds, plans) in every setting, the same hazard point in both hazard settings
  h = [names.index("hazard/gps/overt"), names.index("hazard/gyro/overt")]
  np.testing.assert_array_equal(rec["onset"][rec["setting"] == h[0]], rec["onset"][rec["setting"] == h[1]])
  assert rep["meta"]["campaigns"] == ["long", "hazard", "designed", "multi"]
  assert rep["meta"]["designed_rates"] == {"gps": 1.1, "gyro": 0.005}
  # where the violations happen: the three shares partition each campaign's attacked violators
  pooled = g["metrics"]["no_protection"]
  violators = 0
  for camp in ("long", "hazard", "designed", "multi"):
    vt = pooled[f"campaign/{camp}"]["violation_timing"]
    r = {k: v[np.isin(rec["setting"], [i for i, s in enumerate(names) if E.campaign_of(s) == camp])]
         for k, v in rec.items()}
    n = int(np.sum(M.violation(r) & r["attacked"]))
    assert sum(vt[k]["k"] for k in ("undetected", "outside", "alarm_window")) == vt["undetected"]["n"] == n, camp
    violators += n
  assert violators > 0 and "## Where the violations happen" in md
  # the critical violations the estimate never showed: per mission and spec, whether the estimate's signals failed
  assert rec["seen"].shape == (len(rec["setting"]), len(g["env"]["spec_names"])) and rec["seen"].dtype == bool
  crit = sum(pooled[f"campaign/{c}"]["blind_critical_rate"]["n"] for c in ("long", "hazard", "designed", "multi"))
  assert ("## Critical violations the estimate never showed" in md) == (crit > 0)


def test_designed_rates_flag(tmp_path):
  assert cli._parse_rates("gps=1.1,baro=nan", ("gps", "baro")) == {"gps": 1.1}
  path = tmp_path / "designed_rates.json"
  path.write_text(json.dumps({"gps": {"rate": 1.1, "feasible": True}, "mag": {"rate": None, "feasible": False}}))
  assert cli._parse_rates(str(path), attacks.SENSOR_NAMES) == {"gps": 1.1}
  with pytest.raises(ValueError, match="unknown sensor"):
    cli._parse_rates("lidar=1", ("gps",))
