"""PID-Piper's feed-forward controller (FFC) and its in-tick hook (`FFCHook`; specguard_jax.baselines.pid_piper trains
and registers it). Dash et al., DSN 2021: an LSTM over a window of recent sensor readings and mission targets predicts
what the autopilot's PID controller outputs; a monitor accumulates (CUSUM) the deviation between the FFC's and the
PID's outputs and, once it exceeds a threshold, the FFC's output replaces the PID's until the deviation subsides.

Here (multicopter only): the PID is the velocity PID of the PX4 cascade (autopilot/px4.py), whose output, the
acceleration setpoint [3] (world, m/s^2, gravity excluded), becomes the attitude setpoint and collective thrust
(`px4.attitude_cascade`): the FFC's output reaches the attitude loop. Features per tick (`tick_features`, [N_FEAT]),
horizontal vectors in the heading frame (turned by minus the estimated yaw, so one model serves every flight
direction): the mission target as the plan's leg velocity (the active leg's direction x the cruise speed in cruise,
zero in loiter) [3], estimated velocity [3], estimated roll and pitch [2], gyroscope [3] (rad/s, body),
accelerometer [3] (m/s^2, body). The window holds the last WINDOW ticks (oldest first); the output is predicted in
the heading frame and turned back to the world.

The target is the plan's, not the navigator's velocity setpoint: that setpoint corrects the estimated position's
offset from the leg, so under a spoofed position it moves with the spoof and an FFC fed it moves with the PID (the
monitor never fires). PID-Piper's FFC has no such error feedback: it follows the mission's targets, so a PID pulled
away by a spoofed estimate parts from it and the monitor switches the FFC in. The estimated velocity stays an input
(the released FFC reads the velocity estimate too).
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp

from specguard_jax import ekf as ekf_lib
from specguard_jax import math3d
from specguard_jax.autopilot import navigator as nav_lib
from specguard_jax.estimation import tree_file
from specguard_jax.estimation.estimator import Estimator

N_FEAT = 14
WINDOW = 16      # ticks of history (0.32 s at the 50 Hz tick)
HIDDEN = 64      # LSTM units
INPUTS = "plan_target,vel,roll_pitch,gyro,accel"   # tick_features' layout, kept in the cache's meta


def heading_turn(v, yaw):
  """v [..., 3] world -> heading frame (horizontal part turned by -yaw [...]); vertical unchanged."""
  c, s = jnp.cos(yaw), jnp.sin(yaw)
  return jnp.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)


def heading_unturn(v, yaw):
  """Inverse of heading_turn: heading frame -> world."""
  return heading_turn(v, -yaw)


def plan_target(leg_vel, phase):
  """The FFC's target [..., 3] (world m/s): the plan's leg velocity leg_vel [..., 3] in cruise, zero otherwise (a
  loiter holds its waypoint). phase [...] the navigator's."""
  return jnp.where((phase == nav_lib.CRUISE)[..., None], leg_vel, 0.0)


def tick_features(target, vel, euler, gyro, accel):
  """[..., N_FEAT] features of one tick (module doc). target (plan_target), vel [..., 3] world m/s; euler [..., 3] rad
  (roll, pitch, yaw); gyro [..., 3] rad/s and accel [..., 3] m/s^2 as read (body)."""
  yaw = euler[..., 2]
  return jnp.concatenate([heading_turn(target, yaw), heading_turn(vel, yaw), euler[..., :2], gyro, accel], -1)


class FFCNet(nn.Module):
  """LSTM over the window [..., WINDOW, N_FEAT] (standardised) -> acceleration setpoint [..., 3] (heading frame,
  standardised), read from the last step's hidden state."""
  hidden: int = HIDDEN

  @nn.compact
  def __call__(self, x):
    h = nn.RNN(nn.OptimizedLSTMCell(self.hidden))(x)
    return nn.Dense(3)(nn.tanh(nn.Dense(self.hidden)(h[..., -1, :])))


def ffc_apply(params, window, yaw):
  """params {'net', 'x_mean', 'x_std', 'y_mean', 'y_std'}; window [..., WINDOW, N_FEAT]; yaw [...] rad -> world
  acceleration setpoint [..., 3] (m/s^2)."""
  net = FFCNet(HIDDEN)
  y = net.apply(params["net"], (window - params["x_mean"]) / params["x_std"]) * params["y_std"] + params["y_mean"]
  return heading_unturn(y, yaw)


@dataclasses.dataclass(frozen=True)
class MonitorConfig:
  """PID-Piper's deviation monitor: CUSUM S <- max(0, S + |a_ffc - a_pid| - drift) per tick (m/s^2; S in m/s^2
  ticks); the FFC takes over when S reaches the threshold and hands back when S has fallen to 0 (the deviation
  stayed below the drift long enough to drain it). S is capped at the threshold, so after an attack of any length
  the PID is back within threshold / drift ticks of agreeing with the FFC again. Both from attack-free training flights
  (baselines/pid_piper.py)."""
  drift: float
  threshold: float


def monitor_step(cfg: MonitorConfig, s, active, deviation, in_scope):
  """(S, active) after one tick. deviation [] m/s^2; in_scope [] bool (FFC allowed in this phase): out of scope the
  sum restarts and the PID flies."""
  s = jnp.where(in_scope, jnp.clip(s + deviation - cfg.drift, 0.0, cfg.threshold), 0.0)
  active = jnp.where(active, s > 0.0, s >= cfg.threshold) & in_scope
  return s, active


def template(hidden: int = HIDDEN):
  """Parameter pytree of the FFC (zeros; the shapes load_tree restores)."""
  net = FFCNet(hidden)
  p = net.init(jax.random.PRNGKey(0), jnp.zeros((1, WINDOW, N_FEAT)))
  z = lambda n: jnp.zeros(n)   # noqa: E731
  return {"net": p, "x_mean": z(N_FEAT), "x_std": z(N_FEAT) + 1.0, "y_mean": z(3), "y_std": z(3) + 1.0}


def load_ffc(path: str):
  """(params, MonitorConfig) from a file written by specguard_jax.baselines.pid_piper.build; one-line ValueError if
  corrupt."""
  _, meta = tree_file.load_tree(path)
  try:
    mon = MonitorConfig(drift=float(meta["monitor_drift"]), threshold=float(meta["monitor_threshold"]))
    if int(meta["window"]) != WINDOW or int(meta["hidden"]) != HIDDEN:
      raise ValueError(f"window {meta['window']} / hidden {meta['hidden']}, expected {WINDOW} / {HIDDEN}")
    if meta.get("inputs") != INPUTS:
      raise ValueError(f"inputs {meta.get('inputs', 'vel_sp,...')!r} from an older version, expected {INPUTS!r}")
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f"corrupt baseline cache {path}: bad FFC meta ({e})") from None
  tree, _ = tree_file.load_tree(path, template())
  return jax.tree.map(jnp.asarray, tree), mon


@dataclasses.dataclass(eq=False)
class FFCHook(Estimator):
  """The in-tick PID-Piper: keeps the feature window and the monitor in sim['baseline'] and, while the monitor is
  up, replaces the velocity PID's acceleration setpoint with the FFC's (`acc_setpoint`). Cruise and loiter only
  (the phases the attack-free training flights cover densely; take-off, descent and landing stay with the PID)."""
  params: dict
  monitor: MonitorConfig

  @classmethod
  def create(cls, env, model_path: str = ""):
    if env.vehicle != "drone":
      raise ValueError("recovery_estimator='ffc' (PID-Piper) acts at the multicopter's attitude loop: drone only")
    if not model_path:
      raise ValueError("recovery_estimator='ffc' needs recovery_model= an FFC file (specguard_jax.baselines.pid_piper)")
    params, mon = load_ffc(model_path)
    return cls(params, mon)

  def init(self, ekf, readings):
    del ekf, readings
    return {"window": jnp.zeros((WINDOW, N_FEAT)), "filled": jnp.zeros((), bool), "cusum": jnp.zeros(()),
            "active": jnp.zeros((), bool), "acc_ffc": jnp.zeros(3)}

  def acc_setpoint(self, sim, acc_sp, vel_sp, leg_vel):
    del vel_sp   # the FFC follows the plan, not the navigator's estimate-driven setpoint (module doc)
    st, est, rd, nav = sim["baseline"], sim["ekf"], sim["readings"], sim["nav"]
    euler = ekf_lib.ekf_euler(est)
    f = tick_features(plan_target(leg_vel, nav.phase), est.vel, euler, rd.gyro, rd.accel)
    # the first tick fills the whole window with its features (as the training windows repeat a mission's first tick)
    window = jnp.where(st["filled"], jnp.concatenate([st["window"][1:], f[None]]),
                       jnp.broadcast_to(f, st["window"].shape))
    window = jnp.nan_to_num(window)
    acc_ffc = ffc_apply(self.params, window, euler[2])
    in_scope = (nav.phase == nav_lib.CRUISE) | (nav.phase == nav_lib.LOITER)
    cusum, active = monitor_step(self.monitor, st["cusum"], st["active"], math3d.norm(acc_ffc - acc_sp), in_scope)
    st = {"window": window, "filled": jnp.ones((), bool), "cusum": cusum, "active": active, "acc_ffc": acc_ffc}
    return dict(sim, baseline=st), jnp.where(active, acc_ffc, acc_sp)
