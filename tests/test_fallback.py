"""The rule-based fallback (specguard_jax.autopilot.fallback, EnvConfig.recovery_rule='fallback', controller
`fallback`): the rule on constructed inputs, and in the env: no effect while the alarm is down, a hold under an alarm
when the uncertainty exceeds the spec margin."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.missions import MissionConfig
from envs.rollout import fly_batch
from specguard_jax import attacks
from specguard_jax import controllers as C
from specguard_jax import ekf
from specguard_jax import specs
from specguard_jax.autopilot import fallback as F

CFG = F.FallbackConfig(margin=5.0, min_speed=4.0, speed_margin=1.0)
CFG0 = F.FallbackConfig(margin=5.0, min_speed=0.0, speed_margin=0.0)   # no speed floor
V = jnp.array([6.0, 2.0, -0.5])
FAR = (jnp.asarray(50.0), jnp.array([1.0, 0.0, 0.0]))


def test_rule_is_the_navigator_setpoint_while_the_alarm_is_down():
  for sigma in (0.0, 2.0, 50.0):
    out = F.apply(CFG, V, jnp.asarray(sigma), jnp.asarray(1.0), jnp.array([0.0, 1.0, 0.0]), jnp.asarray(False))
    np.testing.assert_array_equal(np.asarray(out), np.asarray(V))


def test_rule_slows_in_proportion_and_holds_past_the_margin():
  up = jnp.asarray(True)
  np.testing.assert_allclose(F.apply(CFG0, V, jnp.asarray(0.0), *FAR, up), V)            # certain: unchanged
  np.testing.assert_allclose(F.apply(CFG0, V, jnp.asarray(2.0), *FAR, up), [3.6, 1.2, -0.5], rtol=1e-6)  # 1 - 2/5
  for cfg in (CFG0, CFG):
    for sigma in (5.0, 8.0):                                                             # hold; vertical kept
      np.testing.assert_allclose(F.apply(cfg, V, jnp.asarray(sigma), *FAR, up), [0.0, 0.0, -0.5], atol=1e-7)
  assert float(F.speed_scale(CFG, 2.5)) == pytest.approx(0.5)
  # the slow-down stops 1 m/s above the minimum-speed spec (4 m/s), in the setpoint's direction; slower setpoints
  # are kept
  out = np.asarray(F.apply(CFG, V, jnp.asarray(2.0), *FAR, up))
  assert np.linalg.norm(out[:2]) == pytest.approx(5.0) and out[0] / out[1] == pytest.approx(3.0) and out[2] == -0.5
  slow = jnp.array([3.0, 0.0, 0.0])
  np.testing.assert_allclose(F.apply(CFG, slow, jnp.asarray(2.0), *FAR, up), slow)


def test_rule_widens_clearance():
  """Obstacle ahead (+x), 6 m away, sigma 2 m: clearance 5 + 2 = 7 m > 6 m, so no approach and a 0.5 m/s push back;
  without uncertainty 6 m is outside the 5 m margin and only the (unscaled) setpoint remains."""
  away = jnp.array([-1.0, 0.0, 0.0])                      # SDF gradient: away from the obstacle, i.e. towards -x
  out = F.apply(CFG0, V, jnp.asarray(2.0), jnp.asarray(6.0), away, jnp.asarray(True))
  np.testing.assert_allclose(out, [-0.5, 1.2, -0.5], rtol=1e-6, atol=1e-7)
  out = F.apply(CFG0, V, jnp.asarray(0.0), jnp.asarray(6.0), away, jnp.asarray(True))
  np.testing.assert_allclose(out, V)


def test_position_sigma_reads_the_shadow_covariance():
  P = jnp.zeros((15, 15)).at[0, 0].set(9.0).at[1, 1].set(16.0).at[2, 2].set(100.0)
  rec = types.SimpleNamespace(shadow=types.SimpleNamespace(P=P))   # a ReconState's shadow EKFState, P square
  assert float(F.position_sigma(rec)) == pytest.approx(5.0)
  packed = jnp.asarray(np.r_[[P[i, j] for i, j in ekf.TRI], 0.0])     # the lanes kernel's layout
  assert float(F.position_sigma(types.SimpleNamespace(shadow=types.SimpleNamespace(P=packed)))) == pytest.approx(5.0)


def test_controller_registered_beside_delorean():
  c, d = C.build("fallback", C.BuildContext()), C.build("delorean", C.BuildContext())
  assert c.overrides() == dict(d.overrides(), recovery_rule="fallback") and c.policy is d.policy
  with pytest.raises(ValueError, match="reconstruction"):
    envs.make("drone", recovery_rule="fallback")


ONSET, DT = 20.0, 0.1


def test_env_holds_under_an_alarm_and_is_unchanged_before_it():
  """A GPS attack from 20 s with the oracle detector, and the same mission attack-free, in one fallback env: until
  the onset (alarm down) the two fly bit for bit alike; with a spec margin (S1's CP_DIST) below the reconstruction's
  uncertainty the attacked one then holds, while the attack-free one (alarm down: DeLorean, hence the autopilot)
  flies on. The rule's output is the navigator's setpoint whenever the alarm is down (test above)."""
  env = envs.make("drone", recovery_rule="fallback", control_mode="reactive", override_frame="body",
                  override_residual=True, detector="oracle", reconstruction=True, world="open_beach",
                  mission=MissionConfig.drone(min_duration_s=60, max_duration_s=70), max_episode_s=100.0,
                  specs=specs.drone_specs({"CP_DIST": 0.01}))
  keys = jax.random.split(jax.random.PRNGKey(4), 1)
  steps = int((ONSET + 15.0) / DT)
  pos = {}
  for name, atk in (("attacked", attacks.schedule_for("gps", [30.0, 0.0, 0.0], onset=ONSET, duration=40.0)),
                    ("free", attacks.schedule_for("gps", [0.0, 0.0, 0.0], onset=1e9, duration=0.0))):
    _, traj, _ = fly_batch(env, keys, steps, attacks=jax.tree.map(lambda x: x[None], atk))
    pos[name] = np.asarray(traj["pos"])
  pre = int(ONSET / DT) - 1
  np.testing.assert_array_equal(pos["attacked"][:pre], pos["free"][:pre])
  speed = {k: np.linalg.norm(np.diff(p[:, :2], axis=0), axis=-1) / DT for k, p in pos.items()}
  late = slice(int((ONSET + 5.0) / DT), steps - 1)
  assert speed["free"][late].mean() > 2.0, speed["free"][late].mean()
  assert speed["attacked"][late].mean() < 0.5, speed["attacked"][late].mean()
