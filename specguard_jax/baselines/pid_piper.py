"""PID-Piper baseline (Dash et al., DSN 2021): a feed-forward controller (FFC) trained to imitate the autopilot on
attack-free flights, switched in when the detector raises an alarm.

Here: an MLP (flax + optax, supervised) from the env's policy observation [24] (the attacked EKF state relative to
the target waypoint + mission context) to the navigator's velocity setpoint [3] (m/s, world frame: what the
autopilot's position controller is given), averaged over the env step's autopilot ticks. Data: attack-free autopilot
flights (common.flights), cruise/loiter steps only (the override channel acts only there). Deployment: reactive mode
(the FFC's setpoint REPLACES the navigator's while the residual detector's alarm is up: override_residual=False),
no state reconstruction. Imitation error on held-out flights (the last fifth) is stored in the cache's meta.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from specguard_jax import controllers
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.baselines import common

HIDDEN = (128, 128)


@dataclasses.dataclass(frozen=True)
class FFCPolicy:
  """Hashable policy(params, obs [B, 24]) -> world velocity setpoint [B, 3] (m/s)."""
  hidden: tuple = HIDDEN

  def __call__(self, params, obs):
    return common.mlp_apply(self.hidden, params, obs)


def step_samples(env, tr):
  """(obs [B, S, 24], target setpoint [B, S, 3], mask [B, S]) per env step from common.flights traces."""
  k = env.config.ticks_per_step
  obs = np.asarray(tr["obs"])
  b, s = obs.shape[:2]
  vel = np.asarray(tr["vel_nav"][:, : s * k]).reshape(b, s, k, 3).mean(2)
  ph = np.asarray(tr["phase"][:, : s * k]).reshape(b, s, k)
  mask = np.all((ph == nav_lib.CRUISE) | (ph == nav_lib.LOITER), -1)
  return obs, vel, mask


# observation layout (envs.base._observation): world-frame 3-vectors whose horizontal part turns with the world, and
# the Euler yaw; everything else (heights, distances, margins, roll, pitch) is invariant under a turn about z
_XY_PAIRS = ((0, 1), (3, 4), (6, 7), (12, 13), (15, 16))
_YAW = 11


@dataclasses.dataclass(frozen=True)
class YawAugment:
  """Minibatch augmentation (common.fit_mlp `augment`): turn each sample's world by a random angle about z. The
  navigator's guidance is equivariant under it (a turned mission gets the turned setpoint), so the FFC learns one
  behaviour for every direction instead of the few headings of the training missions."""

  def __call__(self, x, y, key):
    a = jax.random.uniform(key, (x.shape[0],), minval=-jnp.pi, maxval=jnp.pi)
    return common.turn_about_z(x, a, _XY_PAIRS, _YAW), common.turn_about_z(y, a, ((0, 1),), None)


def fit(env, tr, steps: int, batch: int, key, heldout: int | None = None):
  """(params, meta): train on all but the last `heldout` missions (default a fifth, at least one) with yaw
  augmentation; report RMSE (m/s) on the held-out ones against the spread of their setpoints (what predicting their
  mean would score) and the loss curve."""
  obs, vel, mask = step_samples(env, tr)
  b = obs.shape[0]
  n_train = b - (max(1, b // 5) if heldout is None else heldout) if b > 1 else 1
  tr_x, tr_y, tr_m = (a[:n_train].reshape((-1,) + a.shape[2:]) for a in (obs, vel, mask))
  params, losses = common.fit_mlp(jnp.asarray(tr_x), jnp.asarray(tr_y), jnp.asarray(tr_m, jnp.float32),
                                  HIDDEN, steps, batch, key, augment=YawAugment())
  te_x, te_y, te_m = (a[n_train:].reshape((-1,) + a.shape[2:]) for a in (obs, vel, mask))
  pred = np.asarray(FFCPolicy()(params, jnp.asarray(te_x)))
  err = np.linalg.norm(pred - te_y, axis=-1)[te_m]
  spread = np.linalg.norm(te_y - te_y[te_m].mean(0), axis=-1)[te_m]
  meta = {"heldout_rmse_m_s": float(np.sqrt(np.mean(err ** 2))), "heldout_setpoint_rms_m_s":
          float(np.sqrt(np.mean(spread ** 2))), "heldout_steps": int(te_m.sum()), "train_steps": int(tr_m.sum()),
          "final_loss": float(np.asarray(losses)[-50:].mean()), "loss_curve": common.loss_curve(losses)}
  return params, meta


def _template():
  x = jnp.zeros((4, 24))
  p, _ = common.fit_mlp(x, jnp.zeros((4, 3)), jnp.ones(4), HIDDEN, 1, 4, jax.random.PRNGKey(0))
  return p


ENV_OVERRIDES = (("control_mode", "reactive"), ("override_frame", "world"), ("override_residual", False),
                 ("detector", "residual"), ("detector_delay", 0.0), ("reconstruction", False))


def build(ctx):
  """Controller 'pid_piper': fit (or load from ctx.cache_dir) the FFC; fly it while the alarm is up."""
  path = common.cache_path(ctx, "pid_piper", "msgpack")
  if not os.path.exists(path):
    b = common.budget(ctx.train_budget)
    env, tr = common.flights(ctx.vehicle, tuple(ctx.worlds), ctx.train_budget, ctx.seed)
    params, meta = fit(env, tr, b.fit_steps, b.batch, jax.random.fold_in(jax.random.PRNGKey(ctx.seed), 0xFFC))
    common.save_tree(path, params, {"baseline": "pid_piper", "vehicle": ctx.vehicle, "budget": ctx.train_budget,
                                    "seed": ctx.seed, "hidden": list(HIDDEN), **meta})
  params, meta = common.load_tree(path, jax.tree.map(np.asarray, _template()))
  return controllers.Controller("pid_piper", ENV_OVERRIDES, FFCPolicy(), jax.tree.map(jnp.asarray, params),
                                f"PID-Piper: feed-forward controller imitating the autopilot (held-out RMSE "
                                f"{meta.get('heldout_rmse_m_s', float('nan')):.2f} m/s), flown while the alarm is up")
