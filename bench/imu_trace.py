"""Per-mission closed-loop trace of one attack setting (zero policy = DeLorean), the missions of bench/gps_xcheck.py.

  python bench/imu_trace.py --sensor gyro --profile stealthy --seed 7 --missions 0,18,27 [--from -3 --to 12 |
      --alarm 3] [--every 2]

Mission j uses key j of jax.random.split(PRNGKey(seed), N) exactly as gps_xcheck.py does (N = its --missions, default
32; same plan, world, noise and attack), so its index is that script's '#j'. Prints, every `--every` env steps
(0.1 s) from onset + --from to onset + --to s (--alarm S: the first S s of the first alarm after onset): time, alarm,
diagnosis, sensors the reconstruction replaces (`rep`), true / reconstructed / autopilot-EKF roll-pitch-yaw (deg), the
detector's accelerometer-vs-model residual acc_e (m/s^2, body) and IMU complementary-filter innovations (GPS, aiding;
m/s), reconstructed horizontal position error (m), true horizontal speed (m/s), true height (m), the spec with the
lowest robustness so far and how many are violated, the applied bias, crash.
In a git worktree run it with PYTHONPATH=<worktree> (the editable install points at the main checkout).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import rollout
from specguard_jax import attacks
from specguard_jax import math3d

WORLDS = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  ap.add_argument("--sensor", default="gyro")
  ap.add_argument("--profile", default="stealthy", choices=attacks.PROFILES)
  ap.add_argument("--seed", type=int, default=7)
  ap.add_argument("--n", type=int, default=32, help="gps_xcheck.py's --missions (key split size)")
  ap.add_argument("--missions", default="0")
  ap.add_argument("--seconds", type=float, default=130.0)
  ap.add_argument("--from", dest="t0", type=float, default=-3.0)
  ap.add_argument("--to", dest="t1", type=float, default=12.0)
  ap.add_argument("--every", type=int, default=2)
  ap.add_argument("--alarm", type=float, default=0.0,
                  help="> 0: print only this long (s) from the first alarm after onset")
  a = ap.parse_args(argv)
  if a.sensor not in attacks.SENSOR_NAMES:
    ap.error(f"unknown sensor {a.sensor!r}")
  try:
    idx = [int(x) for x in a.missions.split(",") if x]
  except ValueError:
    ap.error(f"--missions must be comma-separated integers, got {a.missions!r}")
  if not idx or min(idx) < 0 or a.every < 1 or a.seconds <= 0:
    ap.error("--missions: indices >= 0; --every >= 1; --seconds > 0")
  env = envs.make("drone", worlds=WORLDS, control_mode="reactive", detector="residual", detector_delay=0.5,
                  reconstruction=True, override_residual=True, override_frame="body")
  keys = jax.random.split(jax.random.PRNGKey(a.seed), max(a.n, max(idx) + 1))[np.array(idx)]
  T = int(round(a.seconds / env.dt))

  def one(key):
    return rollout.draw_paired_episode(env, key, ((a.sensor, a.profile),), 0)

  @jax.jit
  def run(keys):
    s = jax.vmap(one)(keys)
    B = keys.shape[0]

    def body(s, _):
      nx = jax.vmap(env.step)(s, jnp.zeros((B, 3)))
      nx = jax.tree.map(lambda x, y: jnp.where(jnp.reshape(s.done > 0, s.done.shape + (1,) * (x.ndim - 1)), y, x),
                        nx, s)
      sim = nx.info["sim"]
      tr = sim["truth"]
      rec = dict(t=nx.info["time"], alarm=nx.info["alarm"], diag=nx.info["diagnosis"], done=nx.done,
                 blamed=sim["recon"].blamed, e_true=jax.vmap(math3d.quat_to_euler)(tr.quat),
                 e_rec=sim["x_rec"][:, 9:12], e_ekf=jax.vmap(math3d.quat_to_euler)(sim["ekf"].quat),
                 rec_err=jnp.linalg.norm(sim["x_rec"][:, :2] - tr.pos[:, :2], axis=-1),
                 speed=jnp.linalg.norm(tr.vel[:, :2], axis=-1), z=tr.pos[:, 2], rob=nx.info["spec_robustness"],
                 crash=nx.info["episode"]["crash"], acc_e=sim["det"].acc_e, xchk=sim["det"].xchk)
      return nx, rec

    _, recs = jax.lax.scan(body, s, None, length=T)
    return recs, s.info["attack"]

  recs, atk = jax.device_get(run(keys))
  names = list(attacks.SENSOR_NAMES)
  si = names.index(a.sensor)
  d = lambda x: np.round(np.rad2deg(x)).astype(int).tolist()
  for c, j in enumerate(idx):
    on, rt, b = float(atk.onset[c]), float(atk.ramp_time[c]), atk.bias[c][si]
    print(f"== {a.sensor} {a.profile} #{j}: onset {on:.1f} ramp {rt:.1f} dur {float(atk.duration[c]):.1f} "
          f"bias {np.round(b, 2).tolist()}")
    t = recs["t"][:, c]
    prev_min = None
    if a.alarm > 0:
      hit = (recs["alarm"][:, c] > 0) & (t >= on)
      t_al = float(t[np.argmax(hit)]) if hit.any() else np.inf
      a.t0, a.t1 = t_al - on, t_al - on + a.alarm
    for k in range(len(t)):
      if not (on + a.t0 <= t[k] <= on + a.t1) or (k > 0 and recs["done"][k - 1, c] > 0):
        continue
      rob = recs["rob"][k, c]
      j_min = int(np.argmin(rob))
      show = (k % a.every == 0) or (prev_min is not None and (rob < 0).sum() != prev_min)
      prev_min = int((rob < 0).sum())
      if not show:
        continue
      frac = np.clip((t[k] - on) / rt, 0, 1) if int(atk.profile[c]) == 1 else float(t[k] >= on)
      bl = "+".join(n for n, m in zip(names, recs["blamed"][k, c]) if m > 0.5) or "-"
      dg = names[int(recs["diag"][k, c])] if recs["diag"][k, c] >= 0 else "-"
      print(f"t {t[k]:6.1f} al {int(recs['alarm'][k, c])} dg {dg:5s} rep {bl:10s} true {d(recs['e_true'][k, c])} "
            f"rec {d(recs['e_rec'][k, c])} ekf {d(recs['e_ekf'][k, c])} "
            f"acc_e {np.round(recs['acc_e'][k, c], 2).tolist()} "
            f"e_gps/aid {np.round(recs['xchk'][k, c][2:4], 2).tolist()} perr {recs['rec_err'][k, c]:5.1f} "
            f"v {recs['speed'][k, c]:4.1f} z {recs['z'][k, c]:5.1f} min {env.spec_names[j_min]} {rob[j_min]:6.2f} "
            f"nviol {int((rob < 0).sum())} b {np.round(b * frac, 2).tolist()} crash {int(recs['crash'][k, c])}")


if __name__ == "__main__":
  main()
