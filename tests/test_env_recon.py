"""State reconstruction inside the env (EnvConfig.reconstruction): under an overt GPS spoof the policy's observation
and the autopilot run on the reconstructed state, so the position the policy sees stays near the truth while the
autopilot's own EKF is dragged away, and the mission still completes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.missions import MissionConfig
from specguard_jax import attacks
from specguard_jax.estimation import model_file

ONSET, DURATION, BIAS = 10.0, 25.0, 20.0


@pytest.fixture(scope="module")
def flight():
  env = envs.make("drone", detector="oracle", reconstruction=True,
                  mission=MissionConfig.drone(min_duration_s=50.0, max_duration_s=70.0))
  sched = jax.tree.map(lambda a: jnp.stack([a] * 2),
                       attacks.schedule_for("gps", [BIAS, 0.0, 0.0], onset=ONSET, duration=DURATION))
  n = int(round((ONSET + DURATION + 5.0) / env.dt))

  @jax.jit
  def run(keys):
    s0 = jax.vmap(lambda k, a: env.reset_in_world(k, None, None, a))(keys, sched)

    def body(s, _):
      s = jax.vmap(env.step)(s, jnp.zeros((2, 3)))
      info = s.info
      target = jax.vmap(lambda m, nv: m.waypoints[nv.target])(info["mission"], info["sim"]["nav"])
      out = {"obs_pos": s.obs[:, :3] + target, "true_pos": info["sim"]["truth"].pos,
             "ekf_pos": info["sim"]["ekf"].pos, "time": info["time"], "done": s.done,
             "collision": info["episode"]["collision"], "spec_obs": s.obs[:, 18:23],
             "true_path": info["signals"]["path_deviation"]}
      bel = jax.vmap(env.believed_signals)(s)
      out["believed"] = jnp.stack([bel[k] for k in ("obstacle_distance", "fence_margin", "path_deviation",
                                                    "altitude", "speed_xy")], -1)
      return s, out
    return jax.lax.scan(body, s0, None, length=n)

  final, tr = run(jax.random.split(jax.random.PRNGKey(11), 2))
  return env, final, jax.tree.map(np.asarray, tr)


def test_reconstructed_observation_stays_near_truth_under_gps_spoof(flight):
  _, _, tr = flight
  t = tr["time"][:, 0]
  attacked = (t >= ONSET + 0.5) & (t < ONSET + DURATION)
  alive = tr["done"].cumsum(0) == 0
  for b in range(2):
    m = attacked & alive[:, b]
    assert m.sum() > 100
    err_obs = np.linalg.norm((tr["obs_pos"][:, b] - tr["true_pos"][:, b])[:, :2], axis=-1)[m]
    err_ekf = np.linalg.norm((tr["ekf_pos"][:, b] - tr["true_pos"][:, b])[:, :2], axis=-1)[m]
    # reconstructed: bounded, within half the spoof's bias. Not within a metre or two: it starts from the estimate at
    # onset (the GPS's metres of correlated error) and dead-reckons ~200 m on optical flow with a per-episode scale
    # error (sensors.SensorConfig.flow_scale_sigma, 5 %), which drifts metres.
    assert err_obs.max() < 0.5 * BIAS, err_obs.max()
    assert np.median(err_ekf) > 8.0, np.median(err_ekf)   # the spoofed EKF is dragged away (bias 20 m)


def test_believed_signals_are_the_observations_spec_entries(flight):
  """env.believed_signals (what evaluation's blind-violation count reads) holds the spec signals of the estimate the
  policy observes: obstacle distance, fence margin, path deviation, altitude, speed equal the observation's entries
  18-22 (as clipped there) at every live step; they are the estimate's, not the truth's (metres apart somewhere)."""
  _, _, tr = flight
  alive = tr["done"].cumsum(0) == 0
  bel = tr["believed"][alive]
  bel = np.stack([np.minimum(bel[:, 0], 50.0), np.clip(bel[:, 1], -50.0, 50.0), bel[:, 2], bel[:, 3], bel[:, 4]], -1)
  np.testing.assert_allclose(bel, tr["spec_obs"][alive], atol=1e-4)
  assert np.max(np.abs(tr["believed"][..., 2] - tr["true_path"])[alive]) > 0.5


def test_mission_survives_gps_spoof_with_reconstruction(flight):
  _, final, tr = flight
  assert not np.any(tr["collision"])
  assert np.all(np.asarray(final.info["episode"]["crash"]) == 0)
  assert np.all(np.asarray(final.info["episode"]["fence_breach"]) == 0)


def test_oracle_reconstruction_is_the_truth_while_active():
  """recon_mode 'oracle' (the bound delorean_oracle flies): while the reconstruction is active under an overt GPS
  spoof, x'_t (the policy's observation) and the estimate the navigator flies on are the truth; before the alarm
  they are the spoofed EKF's as in every mode."""
  env = envs.make("drone", detector="oracle", reconstruction=True, recon_mode="oracle",
                  mission=MissionConfig.drone(min_duration_s=50.0, max_duration_s=70.0))
  sched = attacks.schedule_for("gps", [BIAS, 0.0, 0.0], onset=ONSET, duration=DURATION)
  n = int(round((ONSET + 15.0) / env.dt))

  @jax.jit
  def run(key):
    def body(s, _):
      s = env.step(s, jnp.zeros(3))
      sim = s.info["sim"]
      return s, (s.info["time"], s.info["sim"]["recon"].active, sim["x_rec"][:3], sim["truth"].pos, sim["ekf"].pos)
    return jax.lax.scan(body, env.reset_in_world(key, None, None, sched), None, length=n)[1]

  t, active, x_pos, true_pos, ekf_pos = map(np.asarray, run(jax.random.PRNGKey(3)))
  assert active[t > ONSET + 1.0].all() and not active[t < ONSET].any()
  # the truth of the step's last tick, before its physics moved the vehicle one tick on (0.02 s, < 0.3 m)
  np.testing.assert_allclose(x_pos[active], true_pos[active], atol=0.3)
  # the autopilot's own EKF (which the oracle does not touch) is dragged by the spoof meanwhile
  assert np.median(np.linalg.norm((ekf_pos - true_pos)[active][:, :2], axis=-1)) > 5.0


def test_reconstruction_needs_detector_and_valid_model(tmp_path):
  with pytest.raises(ValueError, match="needs a detector"):
    envs.make("drone", reconstruction=True)
  bad = tmp_path / "m.json"
  bad.write_text("{\"w_lin\": [1, 2]}")
  with pytest.raises(ValueError, match="cannot load dynamics model"):
    envs.make("drone", detector="oracle", reconstruction=True, dynamics_model=str(bad))


def test_shipped_models_load():
  for vehicle, n_u in (("drone", 4), ("rover", 2)):
    p = model_file.load_params(model_file.default_path(vehicle), n_u)
    assert np.all(np.isfinite(np.asarray(p.w_lin))) and np.all(np.asarray(p.rms_lin) < 1.0)
