"""Detector wired into the env tick, and the reactive (SpecGuard-RC) switch driven by its alarm."""

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import missions as missions_lib
from envs import rollout
from specguard_jax import attacks

MISSION = missions_lib.MissionConfig.drone(max_duration_s=60.0, min_duration_s=40.0)


def _pair(s):
  return jax.tree.map(lambda x: jnp.stack([x, x]), s)


def test_config_errors():
  with pytest.raises(ValueError, match="unknown detector 'radar'"):
    envs.make("drone", detector="radar")
  with pytest.raises(ValueError, match="reactive' needs a detector"):
    envs.make("drone", control_mode="reactive")


def test_residual_detector_in_env_flags_and_names_gps_spoof():
  """The alarm and diagnosis in info, and the same in the policy's recovery context and mission phase (the `context`
  layout = `recovery` + phase; envs.observation), with two frames of history after the current one."""
  env = envs.make("drone", world="open_beach", mission=MISSION, detector="residual", domain_randomization=False,
                  obs_layout="context", obs_history=3)
  sched = attacks.schedule_for("gps", [30.0, 0.0, 0.0], onset=15.0, duration=100.0)
  state, _, _ = rollout.fly_batch(env, jax.random.split(jax.random.PRNGKey(7), 2), 170, attacks=_pair(sched))
  # 17 s flown: the overt spoof started at 15 s; the alarm is up and names the GPS (index 0).
  gps = attacks.SENSOR_NAMES.index("gps")
  assert np.all(np.asarray(state.info["alarm"]) == 1.0)
  assert np.all(np.asarray(state.info["diagnosis"]) == gps)
  assert np.all(np.asarray(state.info["episode"]["detected"]) == 1.0)
  frames = np.asarray(state.obs)
  F = 24 + 1 + 6 + 1 + 4 + 8 + 4
  assert frames.shape == (2, env.observation_size) and env.observation_size == 3 * F
  obs = frames[:, :F]   # the current frame first
  alarm, diagnosed, since, std, ranges = obs[:, 24], obs[:, 25:31], obs[:, 31], obs[:, 32:36], obs[:, 36:44]
  phase = np.asarray(state.info["sim"]["nav"].phase)
  assert np.all(phase == 1)   # cruising at 17 s
  np.testing.assert_array_equal(obs[:, 44:], np.eye(4)[phase])
  assert np.all(alarm == 1.0) and np.all(diagnosed[:, gps] == 1.0)
  np.testing.assert_array_equal(diagnosed, np.asarray(state.info["sim"]["det"].mask))
  # raised within the 2 s since the onset, counted in env steps of 0.1 s
  assert np.all((since > 0.0) & (since <= 2.0)) and np.allclose(since * 10, np.round(since * 10), atol=1e-3)
  assert np.all(std > 0.0) and np.all(std[:, 0] < 50.0)
  assert np.all((ranges >= 0.0) & (ranges <= 20.0))
  # the frames before, newest first: one and two env steps (0.1 s) earlier
  for k in (1, 2):
    np.testing.assert_allclose(frames[:, k * F + 31], np.maximum(since - 0.1 * k, 0.0), atol=1e-4)
    assert np.all(frames[:, k * F + 44:(k + 1) * F] == obs[:, 44:])            # still cruising
  assert not np.allclose(frames[:, F:F + 3], obs[:, :3])                       # it moved in 0.1 s
  # the first 24 entries are the paper layout's observation of the same state
  paper = copy.copy(env)
  paper.config = dataclasses.replace(env.config, obs_layout="paper24")
  one = jax.tree.map(lambda x: x[0], state.info)
  obs24 = jax.jit(lambda i: paper._observation(i["world"], i["mission"], i["sim"]))(one)
  np.testing.assert_allclose(obs[0, :24], np.asarray(obs24), rtol=1e-6, atol=1e-6)


def test_reactive_override_follows_oracle_alarm():
  """RC: the policy's setpoint is used only while the (oracle, 1 s delay) alarm is up; before it the navigator
  flies, after it ends the recovery switch hands control back. Detector 'mixed' (the trainer's): each episode is the
  oracle's with probability oracle_share, else the residual detector's, which a zero bias never alarms."""
  env = envs.make("drone", world="open_beach", mission=MISSION, control_mode="reactive", detector="mixed",
                  oracle_share=0.5, detector_delay=1.0, domain_randomization=False)
  sched = attacks.schedule_for("baro", [0.0], onset=12.0, duration=5.0)   # a zero bias: flight unchanged

  def policy(obs, key):
    return jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0]), obs.shape[:-1] + (3,))  # hover when in control

  n = 4
  step = jax.jit(jax.vmap(env.step))
  state = jax.jit(jax.vmap(env.reset_in_world))(jax.random.split(jax.random.PRNGKey(8), n), None, None,
                                               jax.tree.map(lambda x: jnp.stack([x] * n), sched))
  oracle = np.asarray(state.info["sim"]["det_oracle"])
  assert 0 < oracle.sum() < n, oracle    # both kinds of episode in this batch
  active, alarm = [], []
  for _ in range(200):
    state = step(state, policy(state.obs, None))
    active.append(np.asarray(state.info["override_active"]))
    alarm.append(np.asarray(state.info["alarm"]))
  active, alarm = np.array(active), np.array(alarm)    # [steps, n]
  np.testing.assert_array_equal(np.asarray(state.info["sim"]["det_oracle"]), oracle)   # drawn once per episode
  assert alarm[:, ~oracle].max() == 0.0
  alarm, active = alarm[:, np.argmax(oracle)], active[:, np.argmax(oracle)]
  t = (np.arange(200) + 1) * env.dt
  assert alarm[(t > 13.2) & (t < 17.8)].min() == 1.0 and alarm[t < 12.9].max() == 0.0 and alarm[t > 18.2].max() == 0
  # The override of a step follows the alarm at the start of that step.
  np.testing.assert_array_equal(active[1:], alarm[:-1])
  speed = np.linalg.norm(np.asarray(state.info["sim"]["truth"].vel)[np.argmax(oracle), :2])
  assert speed > 3.0   # back under the autopilot, cruising again after the alarm cleared
