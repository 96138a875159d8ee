"""Rover gyroscope vs accelerometer diagnosis and the accelerometer-replaced reconstruction, closed loop in the env
(RC + residual detector + reconstruction, zero override = the autopilot driving on the reconstruction; issue #5):
missions drawn exactly as the former bench/gps_xcheck.py (git history) drew them with --vehicle rover --sensors
gyro,accel --missions 32 --seed 7.

* A stealthy gyro x/y ramp tilts the rover's EKF attitude: gravity leaks into its horizontal prediction and the GPS
  and odometry velocity innovations move together, the aiding pattern of an accelerometer bias. It was blamed on the
  accelerometer first (gyro stealthy #5: for 0.3 s, then gyro, then accelerometer again, a spec violation; #1: then
  the GPS, lost 319 m from the goal). The accelerometer still reads gravity on body z and the centripetal force on
  body y (detector `acc_e`), so it is the gyro's from the first tick now.
* An overt accelerometer bias with a vertical component was blamed on the gyro 0.6 s after the alarm (accel overt
  #17: the shadow's manoeuvres tripped the bicycle-model gyro z channel); the accelerometer off gravity on z keeps it
  the accelerometer's. Its shadow, flying on the model specific force, must then stay with the truth (the rover's
  fitted linear force model ran away to hundreds of m/s within 2 s: kilometres of reconstruction error).
One compile of a 3-mission batch, 32 s of driving."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import rollout
from specguard_jax import attacks

SEED, N_KEYS = 7, 32
WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")   # the former gps_xcheck
# (sensor, profile, bench mission index)
ROWS = (("gyro", "stealthy", 5), ("gyro", "stealthy", 1), ("accel", "overt", 17))
SECONDS = 32.0
ERR_MAX = 3.0   # m, horizontal |x_rec - truth| over the alarm (after: 1.6 / 0.8 / ~0.5 m; before: 5.3 / 62 / 1949 m)
_SETTINGS = (("gyro", "stealthy"), ("accel", "overt"))


@pytest.fixture(scope="module")
def drives():
  env = envs.make("rover", worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5,
                  reconstruction=True, override_residual=True, override_frame="body")
  keys = jax.random.split(jax.random.PRNGKey(SEED), N_KEYS)[np.array([j for _, _, j in ROWS])]
  sid = jnp.asarray([_SETTINGS.index((s, p)) for s, p, _ in ROWS])

  def one(key, si):   # the former bench/gps_xcheck.py's mission / attack / world draw
    return rollout.draw_paired_episode(env, key, _SETTINGS, si)

  @jax.jit
  def run(keys, sid):
    s = jax.vmap(one)(keys, sid)
    zero = jnp.zeros((keys.shape[0], 3))

    def body(s, _):
      nx = jax.vmap(env.step)(s, zero)
      sim = nx.info["sim"]
      err = jnp.linalg.norm(sim["x_rec"][:, :2] - sim["truth"].pos[:, :2], axis=-1)
      return nx, dict(t=nx.info["time"], alarm=nx.info["alarm"] > 0, diag=nx.info["diagnosis"], done=nx.done > 0,
                      err=err)

    s, out = jax.lax.scan(body, s, None, length=int(round(SECONDS / env.dt)))
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out), s.info["attack"].onset

  return jax.device_get(run(keys, sid))


# With the realistic aiding errors (sensors.SensorConfig) a stealthy rover gyro x/y ramp is blamed on the GPS, at
# once or after the gyro, and the reconstruction then drives on the ramped gyro. The cause is not isolated yet; the
# suspects are the GPS-vs-odometry cross-checks, now sized for u-blox-class GPS wander and odometry scale and slip.
_GPS_BLAME = pytest.mark.xfail(reason="stealthy rover gyro ramp blamed on the GPS with the realistic aiding errors: "
                               "the rover diagnosis (detection/detector.py) has to adapt", strict=False)


@pytest.mark.parametrize("i", [pytest.param(i, marks=_GPS_BLAME) if i in (0, 1) else i
                               for i in range(len(ROWS))])
def test_rover_imu_attack_blamed_on_its_sensor_and_reconstructed(drives, i):
  out, onset = drives
  sensor = ROWS[i][0]
  on = out["alarm"][i] & (out["t"][i] >= onset[i]) & ~out["done"][i]
  assert on.sum() >= 20, f"{ROWS[i]}: alarm up {on.sum()} steps after onset {onset[i]:.1f} s"
  k = int(np.argmax(on))
  names = attacks.SENSOR_NAMES
  first = out["diag"][i][k:k + 13]
  # the attacked sensor is blamed first and the other IMU sensor never in the first 1.2 s (gyro stealthy #1 turns to
  # the GPS after 0.5 s, with the gyro replaced until the hand-back: `recon.sticky_gyro`)
  other = names.index("accel" if sensor == "gyro" else "gyro")
  assert int(first[0]) == names.index(sensor), (ROWS[i], [names[d] if d >= 0 else "-" for d in first])
  assert not np.any(first == other), (ROWS[i], [names[d] if d >= 0 else "-" for d in first])
  err = float(np.max(out["err"][i][on]))
  assert err < ERR_MAX, f"{ROWS[i]}: reconstruction error {err:.1f} m in the alarm"
