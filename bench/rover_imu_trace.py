"""Per-mission traces of the rover's accelerometer-vs-model evidence (detector `acc_e`, body x/y/z m/s^2) under gyro /
accelerometer attacks and attack-free (closed loop, zero policy = DeLorean, same setup and pairing as
bench/gps_xcheck.py). Prints, per attacked mission, |acc_e| per axis and the IMU filters' drift (xchk[2:4], m/s)
0.1 / 0.5 / 1.2 s after the first alarm at or after onset with the diagnosis then; for attack-free missions the
per-mission max |acc_e| per axis after the detector's warm-up (quantiles).

  python bench/rover_imu_trace.py --missions 32 --free 32 --seed 7
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))   # this checkout, not an installed one

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import envs  # noqa: E402
from envs import rollout  # noqa: E402
from specguard_jax import attacks  # noqa: E402

WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--missions", type=int, default=32)
  ap.add_argument("--free", type=int, default=32)
  ap.add_argument("--seconds", type=float, default=130.0)
  ap.add_argument("--seed", type=int, default=7)
  ap.add_argument("--sensors", default="gyro,accel")
  a = ap.parse_args(argv)
  if a.missions < 1 or a.free < 0 or a.seconds <= 0:
    ap.error("--missions >= 1, --free >= 0, --seconds > 0")
  sensors = tuple(x for x in a.sensors.split(",") if x)
  if not sensors or any(x not in attacks.SENSOR_NAMES for x in sensors):
    ap.error(f"--sensors: choose from {', '.join(attacks.SENSOR_NAMES)}")
  settings = tuple((x, p) for x in sensors for p in ("stealthy", "overt"))
  env = envs.make("rover", worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5,
                  reconstruction=True, override_residual=True, override_frame="body")
  n, T = a.missions, int(round(a.seconds / env.dt))
  keys = jax.random.split(jax.random.PRNGKey(a.seed), max(n, a.free))
  rows = [(s, p, j) for s, p in settings for j in range(n)] + [(None, None, j) for j in range(a.free)]

  def one(key, si):
    return rollout.draw_paired_episode(env, key, tuple(settings) + (None,), si)

  @jax.jit
  def run(keys, sid):
    s = jax.vmap(one)(keys, sid)
    B = keys.shape[0]

    def body(s, _):
      nx = jax.vmap(env.step)(s, jnp.zeros((B, 3)))
      nx = jax.tree.map(lambda x, y: jnp.where(jnp.reshape(s.done > 0, s.done.shape + (1,) * (x.ndim - 1)), y, x),
                        nx, s)
      d = nx.info["sim"]["det"]
      return nx, dict(alarm=nx.info["alarm"] > 0, diag=nx.info["diagnosis"], t=nx.info["time"], acc_e=d.acc_e,
                      drift=d.xchk[:, 2:4], warm=d.airborne_time >= 3.0, done=nx.done > 0)

    s, recs = jax.lax.scan(body, s, None, length=T)
    return recs, s.info["attack"]

  sid = np.array([len(settings) if s is None else settings.index((s, p)) for s, p, _ in rows], np.int32)
  recs, atk = jax.device_get(run(keys[np.array([j for _, _, j in rows])], jnp.asarray(sid)))
  names = list(attacks.SENSOR_NAMES)
  for si, (s, p) in enumerate(settings):
    print(f"== {s} {p}: |acc_e| x y z (m/s^2), drift gps aid (m/s), diag at alarm +0.1 / +0.5 / +1.2 s")
    for c, i in enumerate(np.flatnonzero(sid == si)):
      t = recs["t"][:, i]
      after = recs["alarm"][:, i] & (t >= atk.onset[i])
      if not after.any():
        print(f"  #{c:2d} not detected")
        continue
      k = int(np.argmax(after))
      parts = []
      for dk in (1, 5, 12):
        j = min(k + dk, T - 1)
        parts.append(f"{np.round(np.abs(recs['acc_e'][j, i]), 2).tolist()} {np.round(recs['drift'][j, i], 2).tolist()} "
                     f"{names[int(recs['diag'][j, i])] if recs['diag'][j, i] >= 0 else '-'}")
      b = atk.bias[i][names.index(s)]
      print(f"  #{c:2d} bias {np.round(b, 2).tolist()} | " + " | ".join(parts))
  free = np.flatnonzero(sid == len(settings))
  if len(free):
    m = recs["warm"][:, free] & ~recs["done"][:, free]
    mx = np.max(np.where(m[..., None], np.abs(recs["acc_e"][:, free]), 0.0), axis=0)   # [M, 3]
    print("attack-free per-mission max |acc_e| x y z: quantiles 50/90/100 %:",
          np.round(np.percentile(mx, [50, 90, 100], axis=0), 3).tolist())


if __name__ == "__main__":
  main()
