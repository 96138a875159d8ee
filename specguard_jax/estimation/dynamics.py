"""System-identification model of the vehicle dynamics x_{t+1} = f(x_t, u_t), fitted by ridge least squares.

State x = (pos [3] world m, vel [3] world m/s, quat [4] body->world, rate [3] body rad/s).  Controls u [n_u]:
rotor thrusts (N) for the drone, (throttle, steer) for the rover.

The model is linear in parameters over physically meaningful features (so the fit is one jitted, closed-form solve):
  * specific force in the BODY frame (what an accelerometer reads, m/s^2)
        f_b = W_lin @ phi_lin,  phi_lin = [u, u |v_b|, v_b, |v_b| v_b, omega x v_b, 1]
    -> collective thrust / mass along body z (drone), traction and cornering forces (rover), linear + quadratic drag;
    world acceleration a = R f_b + g, g = (0, 0, -9.81);
  * body angular acceleration (rad/s^2)
        alpha = W_ang @ phi_ang,  phi_ang = [u, u |v_b|, omega, |omega| omega, v_b, 1]
    -> rotor-thrust differences / reaction torques over inertia, rotational damping, steering yaw moment.
Why least squares and not an MLP: the true dynamics are linear in these features up to the per-episode randomisation
(mass/inertia +-10 %, thrust gain +-8 %, drag +-30 %, wind), so LS reaches the noise floor with a closed-form, exact,
milliseconds-long jitted fit and extrapolates sanely under attack-induced manoeuvres; an MLP needs training, can
extrapolate wildly outside the flight envelope, and (measured in tests) is not needed to reach small error.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from specguard_jax import math3d
from specguard_jax.sensors import GRAVITY

G = jnp.array([0.0, 0.0, -GRAVITY])


@struct.dataclass
class DynState:
  """Kinematic state the model propagates. pos [3] m, vel [3] m/s (world), quat [4] (w,x,y,z), rate [3] rad/s."""
  pos: jnp.ndarray
  vel: jnp.ndarray
  quat: jnp.ndarray
  rate: jnp.ndarray


@struct.dataclass
class DynParams:
  """Fitted weights. w_lin [3, F_lin], w_ang [3, F_ang]; rms_lin / rms_ang [3]: training residual RMS."""
  w_lin: jnp.ndarray
  w_ang: jnp.ndarray
  rms_lin: jnp.ndarray
  rms_ang: jnp.ndarray


def _features(s: DynState, u):
  r = math3d.quat_to_rot(s.quat)
  vb = math3d.matvec_t(r, s.vel)
  sp = math3d.norm(vb)
  w = s.rate
  one = jnp.ones((1,))
  phi_lin = jnp.concatenate([u, u * sp, vb, sp * vb, jnp.cross(w, vb), one])
  phi_ang = jnp.concatenate([u, u * sp, w, jnp.abs(w) * w, vb, one])
  return r, phi_lin, phi_ang


def specific_force(p: DynParams, s: DynState, u):
  """[3] predicted body-frame specific force (m/s^2), i.e. what a bias-free accelerometer would read."""
  return math3d.matvec(p.w_lin, _features(s, u)[1])


def derivatives(p: DynParams, s: DynState, u):
  """(world acceleration [3] m/s^2, body angular acceleration [3] rad/s^2) predicted at state s under controls u."""
  r, phi_lin, phi_ang = _features(s, u)
  # component-wise products (math3d): under vmap a `w @ phi` per step was a small GEMM kernel of its own, ~20 per
  # autopilot tick in the reconstruction's replay
  return math3d.matvec(r, math3d.matvec(p.w_lin, phi_lin)) + G, math3d.matvec(p.w_ang, phi_ang)


def step(p: DynParams, s: DynState, u, dt, specific_force=None) -> DynState:
  """One explicit step of dt (s): semi-implicit Euler on velocity/rate, exponential map on the attitude.
  specific_force: optional [3] body specific force (m/s^2) to use instead of the fitted one (the angular model stays)."""
  acc, alpha = derivatives(p, s, u)
  if specific_force is not None:
    acc = math3d.matvec(math3d.quat_to_rot(s.quat), specific_force) + G
  rate = s.rate + alpha * dt
  quat = math3d.normalize_quat(math3d.quat_mul(s.quat, math3d.rotvec_to_quat(0.5 * (s.rate + rate) * dt)))
  vel = s.vel + acc * dt
  pos = s.pos + 0.5 * (s.vel + vel) * dt
  return DynState(pos=pos, vel=vel, quat=quat, rate=rate)


def rollout(p: DynParams, s0: DynState, controls, dt) -> DynState:
  """Open-loop multi-step prediction: controls [T, n_u] -> states [T] (state after each control)."""
  def body(s, u):
    s = step(p, s, u, dt)
    return s, s
  return jax.lax.scan(body, s0, controls)[1]


def states_from_trace(tr, source: str = "ekf") -> DynState:
  """DynState [.., T] from a trace (specguard_jax.estimation.traces): 'ekf' (trusted estimate: EKF pos/vel/quat,
  gyro minus estimated bias) or 'truth'."""
  if source == "truth":
    t = tr["truth"]
    return DynState(pos=t.pos, vel=t.vel, quat=t.quat, rate=t.ang_vel)
  e, rd = tr["ekf"], tr["readings"]
  return DynState(pos=e.pos, vel=e.vel, quat=e.quat, rate=rd.gyro - e.gyro_bias)


def ridge(phi, y, w, lam):
  """Weighted ridge solve: phi [N, F], y [N, 3], w [N] 0/1 -> weights [3, F] and residual RMS [3]."""
  scale = jnp.sqrt(jnp.sum(w[:, None] * phi ** 2, 0) / jnp.maximum(jnp.sum(w), 1.0)) + 1e-6
  x = phi / scale
  a = (x * w[:, None]).T @ x + lam * jnp.eye(x.shape[1])
  b = (x * w[:, None]).T @ y
  coef = jnp.linalg.solve(a, b) / scale[:, None]
  res = (phi @ coef - y) * w[:, None]
  rms = jnp.sqrt(jnp.sum(res ** 2, 0) / jnp.maximum(jnp.sum(w), 1.0))
  return coef.T, rms


@jax.jit
def _fit(pos, vel, quat, rate, controls, f_meas, valid, dt, lam):
  s = DynState(pos=pos, vel=vel, quat=quat, rate=rate)
  n = pos.shape[0] * pos.shape[1]
  flat = jax.tree.map(lambda a: a.reshape((n,) + a.shape[2:]), s)
  u_all = controls.reshape(n, -1)
  _, phi_lin, phi_ang = jax.vmap(_features)(flat, u_all)
  # specific force of tick k was produced by controls[k] (applied during tick k-1) at the state of tick k-1.
  sp = jax.tree.map(lambda a: a[:, :-1], s)
  sp = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), sp)
  u_next = controls[:, 1:].reshape(-1, controls.shape[-1])
  _, phi_lin, phi_ang = jax.vmap(_features)(sp, u_next)
  y_lin = f_meas[:, 1:].reshape(-1, 3)
  y_ang = ((rate[:, 1:] - rate[:, :-1]) / dt).reshape(-1, 3)
  w = (valid[:, 1:] & valid[:, :-1]).reshape(-1).astype(jnp.float32)
  w_lin, rms_lin = ridge(phi_lin, y_lin, w, lam)
  w_ang, rms_ang = ridge(phi_ang, y_ang, w, lam)
  del flat, u_all
  return DynParams(w_lin=w_lin, w_ang=w_ang, rms_lin=rms_lin, rms_ang=rms_ang)


def fit_dynamics(traces, dt: float = 0.02, source: str = "ekf", lam: float = 1e-3, airborne_only: bool = True
                 ) -> DynParams:
  """Fit the model on attack-free traces (leaves [B, T, ...], `envs.record` of traces.RECORD_FIELDS) by ridge least
  squares.

  source: 'ekf' (deployable: trusted estimates + accelerometer minus estimated bias) or 'truth'.
  airborne_only: drop ticks on the ground (contact forces are not in the model) -- samples with height < 0.5 m.
  Returns DynParams (training residual RMS in rms_lin m/s^2 and rms_ang rad/s^2).
  """
  s = states_from_trace(traces, source)
  if source == "truth":
    t = traces["truth"]
    r = math3d.quat_to_rot(t.quat)
    f_meas = jnp.einsum("btji,btj->bti", r, t.acc - G)
  else:
    f_meas = traces["readings"].accel - traces["ekf"].accel_bias
  valid = jnp.ones(s.pos.shape[:2], bool)
  if airborne_only:
    valid = traces["truth"].pos[..., 2] > 0.5
  return _fit(s.pos, s.vel, s.quat, s.rate, traces["controls"], f_meas, valid, dt, lam)
