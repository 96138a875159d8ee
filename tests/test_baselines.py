"""Prior-work baselines (specguard_jax.baselines): each builds at train_budget='ci' with our code and flies short
missions with and without an attack; SSR's software-sensor GPS tracks the truth under a GPS spoof and its force model
generalises; PID-Piper and UnRocker beat trivial predictors on held-out missions;
the survival reward; corrupt caches are one-line errors.
FTC trains with the PPO trainer (~3 min on 2 CPU cores): set BASELINES_FTC=1 to run its build-and-fly test."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import attacks, controllers
from specguard_jax.baselines import common

ONSET, BIAS, SECONDS = 8.0, 20.0, 14.0


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
  return controllers.BuildContext(cache_dir=str(tmp_path_factory.mktemp("baselines")), seed=0, train_budget="ci")


def fly(c: controllers.Controller, n_steps: int):
  """2 missions: attack-free and a 20 m GPS spoof from ONSET s; returns per-step arrays [T, 2, ...]."""
  env = common.make_env("drone", controllers.DEFAULT_WORLDS[:1], 40.0, **c.overrides())
  sched = [attacks.no_attack(), attacks.schedule_for("gps", [BIAS, 0.0, 0.0], onset=ONSET, duration=60.0)]
  sched = jax.tree.map(lambda *a: jnp.stack(a), *sched)

  @jax.jit
  def run(keys, params):
    s0 = jax.vmap(lambda k, a: env.reset_in_world(k, None, None, a))(keys, sched)

    def body(s, _):
      s = jax.vmap(env.step)(s, c.policy(params, s.obs))
      sim = s.info["sim"]
      out = {"obs": s.obs, "true": sim["truth"].pos, "ekf": sim["ekf"].pos, "gps": sim["readings"].gps_pos,
             "alarm": s.info["alarm"], "time": s.info["time"]}
      if "baseline" in sim and hasattr(sim["baseline"], "model"):
        out["model"] = sim["baseline"].model.pos
        out["active"] = sim["baseline"].active
      return s, out
    return jax.lax.scan(body, s0, None, length=n_steps)

  _, tr = run(jax.random.split(jax.random.PRNGKey(5), 2), c.params)
  return jax.tree.map(np.asarray, tr)


@pytest.fixture(scope="module")
def ssr_flight(ctx):
  return fly(controllers.build("ssr", ctx), int(SECONDS / 0.1))


def test_survival_reward():
  from specguard_jax.rewards import survival_reward
  np.testing.assert_array_equal(survival_reward(jnp.array([False, True])), [1.0, 0.0])


def test_baselines_registered():
  assert {"ssr", "ftc", "pid_piper", "unrocker", "delorean"} <= set(controllers.available())


def test_ssr_software_gps_tracks_truth_under_spoof(ssr_flight):
  tr = ssr_flight
  assert all(np.all(np.isfinite(v)) for v in tr.values())
  t = tr["time"][:, 1]
  alarm = tr["alarm"][:, 1] > 0
  assert not np.any(tr["alarm"][:, 0] > 0)          # attack-free mission: no alarm, no substitution
  rise = t[alarm.argmax()]
  assert alarm.any() and ONSET <= rise < ONSET + 1.0
  win = alarm & (t < rise + 2.0)
  err_sw = np.linalg.norm((tr["model"][:, 1] - tr["true"][:, 1])[:, :2], axis=-1)[win]
  err_gps = np.linalg.norm((tr["gps"][:, 1] - tr["true"][:, 1])[:, :2], axis=-1)[win]
  assert np.median(err_sw) < 3.0, np.median(err_sw)     # software sensor: near the truth
  assert np.median(err_gps) > 15.0                      # the spoofed GPS it replaces
  # recovery holds under the sustained spoof (the EKF-watching detector may go quiet) and the software GPS drifts
  # smoothly: no restart from a stale checkpoint (that jumped it back ~20-30 m)
  after = t > rise + 0.05     # the step after the alarm's (SSR acts from the tick after the detector's)
  assert np.all(tr["active"][after, 1]), tr["active"][after, 1]
  e = (tr["model"][after, 1] - tr["true"][after, 1])[:, :2]
  assert np.max(np.linalg.norm(np.diff(e, axis=0), axis=-1)) < 2.0


def test_ssr_force_model_generalises(ssr_flight, ctx):
  _, meta = common.load_tree(common.cache_path(ctx, "ssr", "msgpack"))
  # specific-force residual on held-out missions (m/s^2): same order as on the fitted ones, far below gravity
  assert np.all(np.asarray(meta["heldout_rms_m_s2"]) < 2.5), meta
  assert np.all(np.asarray(meta["heldout_rms_m_s2"]) < 3.0 * np.asarray(meta["rms_m_s2"]) + 0.2), meta


def test_pid_piper_generalises_and_flies(ctx):
  c = controllers.build("pid_piper", ctx)
  _, meta = common.load_tree(common.cache_path(ctx, "pid_piper", "msgpack"))
  # held-out missions (never trained on): the FFC must beat predicting their mean setpoint by 2x, not only fit the
  # training missions (the 'ci' budget trains on 6 missions x 30 s)
  assert meta["heldout_steps"] > 100 and meta["train_steps"] > 400, meta
  assert meta["heldout_rmse_m_s"] < 0.5 * meta["heldout_setpoint_rms_m_s"], meta
  assert meta["loss_curve"][-1] < 0.2 * meta["loss_curve"][0], meta
  tr = fly(c, int(SECONDS / 0.1))
  assert all(np.all(np.isfinite(v)) for v in tr.values())
  assert (tr["alarm"][:, 1] > 0).any()


def test_unrocker_denoises_heldout_and_flies(ctx):
  c = controllers.build("unrocker", ctx)
  _, meta = common.load_tree(common.cache_path(ctx, "unrocker", "msgpack"))
  # the vectorised attacked replays (12 attacks per mission) move the replayed EKF far off the truth ...
  assert meta["heldout_pos_rmse_m_identity"] > 3.0 and meta["pairs"] > 5e4, meta
  # ... and on held-out missions the DAE output is closer to the truth than its attacked input
  assert meta["heldout_loss"] < 0.7 * meta["heldout_loss_identity"], meta
  assert meta["heldout_vel_rmse_m_s"] < meta["heldout_vel_rmse_m_s_identity"], meta
  assert meta["loss_curve"][-1] < 0.2 * meta["loss_curve"][0], meta
  tr = fly(c, int(SECONDS / 0.1))
  assert all(np.all(np.isfinite(v)) for v in tr.values())
  assert (tr["alarm"][:, 1] > 0).any()


@pytest.mark.skipif(not os.environ.get("BASELINES_FTC"), reason="FTC trains with PPO (~3 min): BASELINES_FTC=1")
def test_ftc_builds_and_flies(ctx):
  c = controllers.build("ftc", ctx)
  assert dict(c.env_overrides)["reconstruction"] is False
  tr = fly(c, int(SECONDS / 0.1))
  assert all(np.all(np.isfinite(v)) for v in tr.values())


def test_corrupt_caches_are_one_line_errors(tmp_path):
  bad = controllers.BuildContext(cache_dir=str(tmp_path), train_budget="ci")
  for name in ("ssr", "unrocker", "pid_piper"):
    path = common.cache_path(bad, name, "msgpack")
    with open(path, "wb") as f:
      f.write(b"\x00not msgpack")
    with pytest.raises(ValueError) as e:
      controllers.build(name, bad)
    assert "corrupt baseline cache" in str(e.value) and "\n" not in str(e.value)
  run = common.cache_path(bad, "ftc", "")
  os.makedirs(run)
  for f in ("summary.json", "config.json"):
    with open(os.path.join(run, f), "w") as fh:
      fh.write("{")
  with pytest.raises(ValueError) as e:
    controllers.build("ftc", bad)
  assert "\n" not in str(e.value)
  with pytest.raises(ValueError):
    common.budget("huge")
