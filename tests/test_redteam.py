"""The red-team campaign (specguard_jax.ppo.redteam, evaluate.py --campaigns redteam / --train-redteam): an attack
agent trains against a frozen controller, is saved and reloaded with the same actions, its rollout records the
sensor, onset and duration it chose, and the campaign's row and log reach the report. Tiny sizes: one short world,
2 missions, a few PPO iterations."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evaluate as evaluate_cli
from envs.missions import MissionConfig
from specguard_jax import controllers as C
from specguard_jax import evaluation as E
from specguard_jax.ppo import attacker as attacker_lib
from specguard_jax.ppo import redteam as RT
from specguard_jax.ppo.config import PPOConfig
from specguard_jax.types import SENSOR_NAMES

SENSORS = ("gps", "gyro")
# The env overrides evaluate.py passes for CLI_ARGS below (mission_file and params_file: its defaults), so its
# evaluation finds this module's env (evaluation.make_env caches it per overrides) and so its compiled rollout.
BASE = {"worlds": ("urban_park",), "max_episode_s": 60.0, "mission_file": "", "params_file": "",
        "mission": MissionConfig.drone(min_duration_s=30.0, max_duration_s=40.0)}
CFG = RT.RedteamConfig(num_envs=4, unroll_length=8, steps=64, sensors=SENSORS, max_duration_s=20.0,
                       violation_penalty=1.0, ppo=PPOConfig(ent_coef=0.01, num_minibatches=4, update_epochs=2))
# The settings evaluate.py builds for --sensors gps,gyro --profiles overt --campaigns redteam (the CLI test below
# then reuses this module's compiled rollout).
SETTINGS = (E.setting(None), E.setting("gps", "overt"), E.setting("gyro", "overt"), E.redteam_setting(SENSORS))
CLI_ARGS = ["--controllers", "no_protection", "--sensors", ",".join(SENSORS), "--profiles", "overt", "--worlds",
            "urban_park", "--missions", "2", "--mission-s", "30,40", "--max-s", "60", "--traj", "0", "--no-progress"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
  out = str(tmp_path_factory.mktemp("redteam_eval"))
  ctrl = C.build("no_protection", C.BuildContext())
  env = E.make_env("drone", **{**BASE, **ctrl.overrides()})
  agent, params, history = RT.train(env, ctrl.policy, ctrl.params, CFG)
  RT.save(os.path.join(out, "redteam", "no_protection"), agent, params, CFG, history)
  return out, ctrl, env, agent, params, history


def test_trains_saves_and_reloads_with_the_same_actions(trained):
  out, _, env, agent, params, history = trained
  assert len(history) == CFG.iterations == 2
  assert float(jnp.max(jnp.abs(params["mean"]))) > 0   # the observation normaliser saw the rollouts: updates ran
  assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(params))
  agent2, params2, meta = RT.load(os.path.join(out, "redteam", "no_protection"))
  assert agent2 == agent and agent2.dt == env.dt and agent2.attack.sensors == SENSORS
  assert jax.tree.structure(params2) == jax.tree.structure(params)
  obs = jax.random.normal(jax.random.PRNGKey(3), (16, attacker_lib.N_OBS)) * 3.0
  np.testing.assert_array_equal(np.asarray(agent.raw_action(params, obs)), np.asarray(agent2.raw_action(params2, obs)))
  assert meta["training"]["steps"] == CFG.steps and len(meta["history"]) == 2
  assert meta["training"]["violation_penalty"] == 1.0


def _always_gyro(params):
  """params whose agent attacks the gyro as early as it may (output biases: gyro score and launch high)."""
  params = jax.tree.map(lambda x: x, params)
  net = params["policy"]["net"]
  last = max(net)   # the output layer (dense_<last>)
  net[last] = dict(net[last], kernel=jnp.zeros_like(net[last]["kernel"]),
                   bias=jnp.zeros(attacker_lib.N_ACT).at[SENSOR_NAMES.index("gyro")].set(5.0).at[9].set(5.0)
                   .at[6].set(1.0))
  return params


def test_rollout_records_sensor_onset_and_duration(trained):
  _, ctrl, env, agent, params, _ = trained
  rec, _, _ = E.rollout(env, ctrl.policy, ctrl.params, SETTINGS, missions=2, max_s=60.0, attacker=agent,
                        attacker_params=_always_gyro(params))
  red = rec["setting"] == len(SETTINGS) - 1
  assert np.all(rec["redteam_sensor"][~red] == -1)
  assert np.all(rec["redteam_sensor"][red] == SENSOR_NAMES.index("gyro"))
  assert np.all(rec["attacked"][red]) and not np.any(rec["attacked"][rec["setting"] == 0])
  # on from the first step at or after the minimum onset (after take-off), the gyro alone (the other score is 0)
  assert np.all((rec["onset"][red] >= CFG.min_onset_s) & (rec["onset"][red] <= CFG.min_onset_s + env.dt + 1e-4))
  np.testing.assert_array_equal(rec["redteam_mask"][red], np.eye(6)[[SENSOR_NAMES.index("gyro")] * int(red.sum())])
  dur = rec["attack_end"][red] - rec["onset"][red]
  # on until the 20 s budget is used up or the episode ends, whichever comes first (one step's slack)
  assert np.all(dur <= CFG.max_duration_s + env.dt + 1e-4)
  assert np.all(dur >= np.minimum(CFG.max_duration_s, rec["t_end"][red] - rec["onset"][red]) - env.dt - 1e-4)
  # the scripted settings keep their sampled schedules
  assert np.all(rec["onset"][rec["setting"] == 1] < 1e8)


def test_redteam_setting_needs_an_attacker(trained):
  _, ctrl, env, _, _, _ = trained
  with pytest.raises(ValueError, match="attack agent"):
    E.rollout(env, ctrl.policy, ctrl.params, SETTINGS, missions=2, max_s=60.0)


def test_campaign_row_and_log_in_the_report(trained):
  out = trained[0]
  assert evaluate_cli.main(CLI_ARGS + ["--campaigns", "redteam", "--out", out]) == 0
  with open(os.path.join(out, "report.json")) as f:
    rep = json.load(f)
  name = f"redteam/{'+'.join(SENSORS)}/agent"
  assert name in rep["groups"]["main"]["settings"]
  assert "no_protection" in rep["experiments"]["hard"]["redteam"]
  log = rep["redteam"]["no_protection"]
  assert log["setting"] == name and len(log["missions"]) == 2
  assert log["agent"]["trained"] is False and log["agent"]["dir"].endswith(os.path.join("redteam", "no_protection"))
  for m in log["missions"]:
    assert set(m) >= {"sensor", "onset_s", "duration_s", "violated"}
    assert m["sensor"] is None or m["sensor"] in SENSORS
  assert os.path.isfile(os.path.join(out, "figures", "redteam.png"))
  with open(os.path.join(out, "report.md")) as f:
    assert "## Red-team campaign" in f.read()


def test_missing_agent_is_refused_up_front(tmp_path, capsys):
  assert evaluate_cli.main(CLI_ARGS + ["--campaigns", "redteam", "--out", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert "no red-team agent" in err and "--train-redteam" in err


@pytest.mark.parametrize("argv, needle", [(["--train-redteam", "--redteam-steps", "0"], "--redteam-steps 0"),
                                          (["--campaigns", "redteam", "--redteam-seed", "-1"], "--redteam-seed -1")])
def test_bad_redteam_budget_is_one_line_exit_2(argv, needle, tmp_path, capsys):
  assert evaluate_cli.main(CLI_ARGS + argv + ["--out", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert needle in err and err.count("\n") == 1


def test_log_counts_sensor_sets_crashes_and_says_the_verdict():
  """report.redteam_log on constructed records: a two-sensor attack counts for both sensors and as its set, the
  crash share is logged, and the verdict names the best controller and says when none keeps half its missions."""
  from specguard_jax import report
  name = "redteam/gps+gyro/agent"
  results = {"groups": {"main": {"settings": ["attack_free", name]}}}
  gyro, mag = SENSOR_NAMES.index("gyro"), SENSOR_NAMES.index("mag")

  def rec(crash):
    n = len(crash)
    mask = np.zeros((2 * n, 6), np.float32)
    mask[n:, gyro] = 1.0
    mask[n:n + 2, mag] = 1.0                     # two missions spoof gyro + mag, the rest the gyro alone
    return {"setting": np.repeat([0, 1], n), "redteam_sensor": np.r_[np.full(n, -1), np.full(n, gyro)],
            "redteam_mask": mask, "onset": np.r_[np.full(n, 1e9), np.full(n, 10.0)],
            "attack_end": np.r_[np.zeros(n), np.full(n, 10.5)], "mission": np.r_[np.arange(n), np.arange(n)],
            "world": np.zeros(2 * n, int), "violated": np.zeros((2 * n, 12), bool),
            "complete": np.r_[np.ones(n, bool), ~np.asarray(crash)], "crash": np.r_[np.zeros(n, bool), crash],
            "collision": np.zeros(2 * n, bool)}
  records = {("main", "no_protection"): rec([True, True, True, False]),
             ("main", "delorean"): rec([True, False, False, False])}
  log = report.redteam_log(results, records)
  s = log["no_protection"]["summary"]
  assert s["sensors"] == {"gyro": 4, "mag": 2} and s["combinations"] == {"gyro+mag": 2, "gyro": 2}
  assert s["crash"] == 0.75 and s["any_violation"] == 0.75 and s["duration_s"]["median"] == 0.5
  assert log["delorean"]["summary"]["crash"] == 0.25
  v = report.redteam_verdict(log)
  assert "best controller is delorean with 25.0 %" in v and "crashes 25.0-75.0 %" in v and "Kept" in v
  records[("main", "delorean")] = rec([True, True, False, True])
  assert "No controller keeps more than half" in report.redteam_verdict(report.redteam_log(results, records))
  assert "| gyro+mag 2, gyro 2 |" in "\n".join(report.redteam_markdown(log))
  # records written before the mask was recorded: the agent's first sensor only
  old = {k: {f: v for f, v in r.items() if f != "redteam_mask"} for k, r in records.items()}
  assert report.redteam_log(results, old)["delorean"]["summary"]["sensors"] == {"gyro": 4}
