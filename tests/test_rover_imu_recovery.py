"""Rover gyroscope recovery, closed loop in the env (RC + residual detector + reconstruction, zero override = the
autopilot driving on the reconstruction; issue #5): missions drawn exactly as the former bench/gps_xcheck.py (git
history) drew them with --vehicle rover --sensors gyro,accel --missions 32 --seed 7, picked from those whose
reconstruction read all zeros.
A gyro x/y bias (not an IMU-model channel on the rover) gave the checkpoint a few rad/s of roll rate; the shadow's
replay through the rover's fitted angular model (no roll / pitch dynamics) blew up to NaN within 5 ticks of the
alarm, and the shadow state read zeros for the whole alarm (100-200 m reconstruction error, the rover lost; the
diagnosis was right). Now the reconstruction must stay finite and within a few metres of the truth.
One compile of a 3-mission batch, 31 s of driving."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import rollout
from specguard_jax import attacks

SEED, N_KEYS = 7, 32
WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")   # the former gps_xcheck
# (profile, bench mission index): gyro overt #14 / #1 (blamed on the gyro from the first tick), gyro stealthy #5
# (accel for one tick, then the gyro); before: rec err 179 / 200 / 164 m
ROWS = (("overt", 14), ("overt", 1), ("stealthy", 5))
SECONDS = 31.0
ERR_MAX = 15.0   # m, horizontal |x_rec - truth| over the alarm (after: ~1 / ~1 / 5.3 m; before: 179 / 200 / 164 m)


@pytest.fixture(scope="module")
def drives():
  env = envs.make("rover", worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5,
                  reconstruction=True, override_residual=True, override_frame="body")
  keys = jax.random.split(jax.random.PRNGKey(SEED), N_KEYS)[np.array([j for _, j in ROWS])]
  overt = jnp.asarray([p == "overt" for p, _ in ROWS])

  def one(key, ov):   # the former bench/gps_xcheck.py's mission / attack / world draw for a gyro attack
    return rollout.draw_paired_episode(env, key, (("gyro", "overt"), ("gyro", "stealthy")),
                                       jnp.where(ov, 0, 1))

  @jax.jit
  def run(keys, overt):
    s = jax.vmap(one)(keys, overt)
    zero = jnp.zeros((keys.shape[0], 3))

    def body(s, _):
      nx = jax.vmap(env.step)(s, zero)
      sim = nx.info["sim"]
      err = jnp.linalg.norm(sim["x_rec"][:, :2] - sim["truth"].pos[:, :2], axis=-1)
      return nx, dict(t=nx.info["time"], alarm=nx.info["alarm"] > 0, diag=nx.info["diagnosis"], done=nx.done > 0,
                      err=err, finite=jnp.all(jnp.isfinite(sim["recon"].shadow.accel_bias), axis=-1)
                      & jnp.all(jnp.isfinite(sim["recon"].rate), axis=-1))

    s, out = jax.lax.scan(body, s, None, length=int(round(SECONDS / env.dt)))
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out), s.info["attack"].onset

  out, onset = jax.device_get(run(keys, overt))
  return out, onset


@pytest.mark.parametrize("i", range(len(ROWS)))
def test_rover_gyro_reconstruction_stays_with_the_truth(drives, i):
  out, onset = drives
  on = out["alarm"][i] & (out["t"][i] >= onset[i]) & ~out["done"][i]
  assert on.sum() >= 20, f"{ROWS[i]}: alarm up {on.sum()} steps after onset {onset[i]:.1f} s"
  k = int(np.argmax(on))
  assert int(out["diag"][i][k + 12]) == attacks.SENSOR_NAMES.index("gyro"), (ROWS[i], out["diag"][i][k:k + 13])
  assert out["finite"][i][on].all(), f"{ROWS[i]}: shadow state not finite in the alarm"
  err = float(np.max(out["err"][i][on]))
  assert err < ERR_MAX, f"{ROWS[i]}: reconstruction error {err:.1f} m in the alarm"
