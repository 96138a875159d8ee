"""PX4-style cascade and ArduRover controller on the MJX models, with true-state feedback (no sensor noise)."""

import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from envs.base import ASSETS
from specguard_jax import math3d
from specguard_jax.autopilot import px4

DT = 0.02


@pytest.fixture(scope="module")
def drone():
  m = mujoco.MjModel.from_xml_path(os.path.join(ASSETS, "drone.xml"))
  return m, mjx.put_model(m), px4.Airframe.from_mjcf(m)


def test_airframe_from_mjcf(drone):
  m, _, af = drone
  assert af.n_rotors == 4
  assert af.mass == pytest.approx(1.5)
  assert af.thrust_max == pytest.approx(7.07)
  # Hover thrust: m g shared by 4 rotors of 7.07 N.
  assert af.hover_thrust == pytest.approx(1.5 * 9.81 / (4 * 7.07))
  # The allocation inverts the effectiveness: unit wrench components come back.
  e, a = af.effectiveness, af.alloc
  np.testing.assert_allclose(e @ a, np.eye(4), atol=1e-9)


def test_hover_thrust_is_mg(drone):
  """Equal rotor thrusts summing to m*g leave the MJX body unaccelerated; 10% more accelerates it at 0.1 g."""
  _, mx, af = drone
  d = mjx.make_data(mx)
  rot = px4.mix(af, jnp.zeros(3), af.hover_thrust)
  np.testing.assert_allclose(np.sum(rot), 1.5 * 9.81, rtol=1e-5)
  np.testing.assert_allclose(rot, rot[0], rtol=1e-5)
  d1 = mjx.forward(mx, d.replace(ctrl=rot))
  np.testing.assert_allclose(d1.qacc, 0.0, atol=1e-4)
  d2 = mjx.forward(mx, d.replace(ctrl=rot * 1.1))
  assert float(d2.qacc[2]) == pytest.approx(0.981, rel=1e-3)


def test_mixer_produces_requested_torque(drone):
  """Unsaturated: rotor thrusts realise tau = tau_norm * torque_scale and the collective thrust exactly."""
  _, mx, af = drone
  tau_n = jnp.array([0.05, -0.04, 0.03])
  rot = px4.mix(af, tau_n, 0.5)
  wrench = af.effectiveness @ np.asarray(rot)
  np.testing.assert_allclose(wrench[:3], np.asarray(tau_n) * af.torque_scale, rtol=1e-4, atol=1e-6)
  np.testing.assert_allclose(wrench[3], 0.5 * 4 * af.thrust_max, rtol=1e-5)
  # Saturated yaw gives way first: rotors stay in range and roll/pitch survive.
  rot = np.asarray(px4.mix(af, jnp.array([0.1, 0.0, 1.0]), 0.9))
  assert rot.min() >= 0 and rot.max() <= af.thrust_max + 1e-6
  w = af.effectiveness @ rot
  assert w[0] == pytest.approx(0.1 * af.torque_scale[0], rel=1e-3)


def _fly(drone, vel_sp_fn, steps, yaw_sp=0.0, z0=10.0):
  _, mx, af = drone
  p = px4.MulticopterParams()
  d = mjx.make_data(mx).replace(qpos=jnp.array([0.0, 0.0, z0, 1.0, 0.0, 0.0, 0.0]))

  def body(carry, t):
    d, cs = carry
    vel, quat, rate = d.qvel[:3], d.qpos[3:7], d.qvel[3:6]
    cs, rot, _ = px4.mc_control(p, af, cs, vel_sp_fn(t), yaw_sp, vel, quat, rate, DT, jnp.array(True))
    d = mjx.step(mx, d.replace(ctrl=rot))
    return (d, cs), (d.qpos[:3], d.qvel[:3], math3d.quat_to_euler(d.qpos[3:7]))

  run = jax.jit(lambda: jax.lax.scan(body, (d, px4.MCControlState.zeros()), jnp.arange(steps) * DT)[1])
  return jax.tree.map(np.asarray, run())


def test_hover_holds_altitude(drone):
  pos, vel, eul = _fly(drone, lambda t: jnp.zeros(3), 250)
  assert np.max(np.abs(pos[-100:, 2] - 10.0)) < 0.05
  assert np.max(np.abs(eul[-100:, :2])) < 0.01


def test_velocity_step_response(drone):
  """8 m/s forward + 1 m/s climb from hover (a raw step, no trajectory smoothing): within 0.4 m/s after 4 s and
  0.2 m/s after 7 s, tilt within the 45 deg limit, settled, yaw held. (The horizontal velocity integrator may use the
  tilt authority beyond MPC_ACC_HOR_MAX, for headwinds: its overshoot on this raw 8 m/s step is about 0.35 m/s
  (4.4 %) at 4 s, and the integrator unwinds it slowly: about 0.15 m/s at 7 s, 0.12 at 8 s.)"""
  target = jnp.array([8.0, 0.0, 1.0])
  pos, vel, eul = _fly(drone, lambda t: target, 400)
  assert np.all(np.abs(vel[200:] - np.asarray(target)) < 0.4)
  assert np.all(np.abs(vel[350:] - np.asarray(target)) < 0.2)
  assert np.max(np.abs(eul[:, :2])) < np.deg2rad(45.5)
  assert np.max(np.abs(eul[:, 2])) < np.deg2rad(3)
  # Settled: the last 2 s vary less than the first overshoot region.
  assert np.std(vel[300:, 0]) < 0.05


def test_yaw_tracking(drone):
  pos, vel, eul = _fly(drone, lambda t: jnp.zeros(3), 250, yaw_sp=1.0)
  assert abs(eul[-1, 2] - 1.0) < 0.02
  assert np.max(np.abs(pos[:, :2])) < 0.3


def test_rover_speed_and_turn():
  """ArduRover controller on the planar rover env physics: tracks 8 m/s; a constant heading demand is reached."""
  import envs
  env = envs.make("rover", domain_randomization=False)
  from specguard_jax.autopilot import ardurover

  def run():
    state = env.reset(jax.random.PRNGKey(0))
    sim, data = state.info["sim"], state.pipeline_state
    sim = dict(sim, ctrl=ardurover.RoverControlState.zeros())

    def body(carry, t):
      data, sim = carry
      heading = jnp.where(t < 8.0, 0.0, jnp.pi / 2)
      vel_sp = 8.0 * jnp.array([jnp.cos(heading), jnp.sin(heading), 0.0])
      # Truth-fed estimate for this unit test.
      ekf = sim["ekf"].replace(pos=sim["truth"].pos, vel=sim["truth"].vel, quat=sim["truth"].quat)
      data, sim = env._vehicle_tick(data, dict(sim, ekf=ekf), state.info["mission"], vel_sp, jnp.zeros(3))
      yaw = data.qpos[2]
      u = jnp.cos(yaw) * data.qvel[0] + jnp.sin(yaw) * data.qvel[1]
      return (data, sim), (u, yaw)

    return jax.lax.scan(body, (data, sim), jnp.arange(800) * DT)[1]

  u, yaw = jax.tree.map(np.asarray, jax.jit(run)())
  wrap = lambda a: np.arctan2(np.sin(a), np.cos(a))
  assert abs(u[350:400].mean() - 8.0) < 0.5          # speed loop holds 8 m/s
  assert abs(wrap(yaw[395] - 0.0)) < 0.1             # heading 0 reached before t = 8 s
  assert abs(wrap(yaw[-1] - np.pi / 2)) < 0.1        # then the 90 deg heading change
  assert u.max() < 12.5                               # never beyond the rover's top speed


def _cascade_reference(p, af, cs, vel_sp, yaw_sp, vel, quat, rate, dt, armed):
  """The PX4 cascade of px4.mc_control in float64 numpy with vector/matrix products (one vehicle): the oracle of the
  component-wise implementation."""
  kp = np.array([p.xy_vel_p, p.xy_vel_p, p.z_vel_p])
  ki = np.array([p.xy_vel_i, p.xy_vel_i, p.z_vel_i])
  kd = np.array([p.xy_vel_d, p.xy_vel_d, p.z_vel_d])
  err = vel_sp - vel
  acc = kp * err + cs["vel_int"] - kd * (vel - cs["prev_vel"]) / dt
  h = np.linalg.norm(acc[:2]) + 1e-9
  sat = h > p.acc_hor_max
  acc[:2] *= min(1.0, p.acc_hor_max / h)
  lim = np.array([p.vel_int_lim, p.vel_int_lim, p.vel_int_lim_z])
  vel_int = np.clip(cs["vel_int"] + np.array([1.0 - sat, 1.0 - sat, 1.0]) * ki * err * dt, -lim, lim)
  lift = max(9.81 + acc[2], 0.981)
  z = np.array([acc[0], acc[1], lift]) / np.linalg.norm([acc[0], acc[1], lift])
  tilt = np.arccos(np.clip(z[2], -1, 1))
  if tilt > p.tilt_max:
    hz = np.linalg.norm(z[:2]) + 1e-9
    z = np.array([z[0] / hz * np.sin(p.tilt_max), z[1] / hz * np.sin(p.tilt_max), np.cos(p.tilt_max)])
  thrust = np.clip(lift / 9.81 * af.hover_thrust / max(z[2], 0.3), p.thr_min, p.thr_max)
  y = np.cross(z, [np.cos(yaw_sp), np.sin(yaw_sp), 0.0])
  y = y / (np.linalg.norm(y) + 1e-9)
  r_des = np.stack([np.cross(y, z), y, z], axis=1)
  r = np.asarray(math3d.quat_to_rot(jnp.asarray(quat, jnp.float32)), np.float64)
  m = r_des.T @ r - r.T @ r_des
  k = np.array([p.roll_p, p.pitch_p, p.yaw_p])
  rlim = np.array([p.rollrate_max, p.pitchrate_max, p.yawrate_max])
  rate_sp = np.clip(-k * 0.5 * np.array([m[2, 1], m[0, 2], m[1, 0]]), -rlim, rlim)
  g = np.array([p.rollrate_pid, p.pitchrate_pid, p.yawrate_pid])
  rerr = rate_sp - rate
  torque = np.clip(g[:, 0] * rerr + cs["rate_int"] - g[:, 2] * (rate - cs["prev_rate"]) / dt, -1, 1)
  tau = torque * af.torque_scale
  u_rp = af.alloc[:, :2] @ tau[:2] / af.thrust_max
  u_y = af.alloc[:, 2] * tau[2] / af.thrust_max
  u_rp = u_rp * min(1.0, 1.0 / max(u_rp.max() - u_rp.min(), 1e-9))
  base = af.alloc[:, 3] * thrust * af.n_rotors + u_rp
  base = base + max(0.0, -base.min()) - max(0.0, base.max() - 1.0)
  room = np.where(u_y > 0, (1 - base) / np.maximum(u_y, 1e-9), base / np.maximum(-u_y, 1e-9))
  s_y = np.clip(np.min(np.where(np.abs(u_y) > 1e-9, room, 1.0)), 0, 1)
  rotors = np.clip(base + s_y * u_y, 0, 1) * af.thrust_max * armed
  return rotors, acc, rate_sp, vel_int * armed


def test_cascade_equals_the_vector_form_reference(drone):
  """px4.mc_control (written component-wise: no reductions or small matmuls, which on a GPU are kernels of their
  own) equals the float64 vector/matrix form of the same cascade on random states, tilt-limited ones included."""
  _, _, af = drone
  p = px4.MulticopterParams()
  rng = np.random.default_rng(0)
  n = 256
  f = lambda *s, sc=1.0: (rng.normal(size=(n,) + s) * sc).astype(np.float32)  # noqa: E731
  q = f(4)
  q /= np.linalg.norm(q, axis=1, keepdims=True)
  cs = {"vel_int": f(3), "rate_int": f(3, sc=0.2), "prev_vel": f(3, sc=5), "prev_rate": f(3, sc=2)}
  vel_sp, yaw_sp, vel, rate = f(3, sc=5), f(sc=3), f(3, sc=5), f(3, sc=2)
  armed = rng.random(n) < 0.8
  step = jax.jit(jax.vmap(lambda c, vs, ys, v, qq, r, a: px4.mc_control(
      p, af, px4.MCControlState(**c), vs, ys, v, qq, r, DT, a)))
  new_cs, rotors, dbg = step(cs, vel_sp, yaw_sp, vel, q, rate, armed)
  n_tilted = 0
  for i in range(n):
    ref = _cascade_reference(p, af, {k: v[i].astype(np.float64) for k, v in cs.items()}, vel_sp[i], yaw_sp[i],
                             vel[i], q[i], rate[i], DT, armed[i])
    n_tilted += np.arctan2(np.linalg.norm(ref[1][:2]), max(9.81 + ref[1][2], 0.981)) > p.tilt_max
    np.testing.assert_allclose(np.asarray(rotors[i]), ref[0], atol=2e-4 * af.thrust_max)
    np.testing.assert_allclose(np.asarray(dbg["acc_sp"][i]), ref[1], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(dbg["rate_sp"][i]), ref[2], atol=1e-4)
    np.testing.assert_allclose(np.asarray(new_cs.vel_int[i]), ref[3], atol=1e-5)
  assert n_tilted > 10   # the tilt limit is exercised


def test_small_vector_helpers_equal_jnp():
  """math3d.norm / hypot / dot / matvec / matvec_t / with_component / scale_head equal their jnp forms, batched."""
  rng = np.random.default_rng(1)
  v, w = rng.normal(size=(5, 3)).astype(np.float32), rng.normal(size=(5, 3)).astype(np.float32)
  m = rng.normal(size=(5, 3, 3)).astype(np.float32)
  np.testing.assert_allclose(math3d.norm(v), np.linalg.norm(v, axis=-1), rtol=1e-6)
  np.testing.assert_allclose(math3d.norm(v[:, :2]), np.linalg.norm(v[:, :2], axis=-1), rtol=1e-6)
  np.testing.assert_allclose(math3d.hypot(v[:, 0], w[:, 1]), np.hypot(v[:, 0], w[:, 1]), rtol=1e-6)
  np.testing.assert_allclose(math3d.dot(v, w), np.sum(v * w, -1), rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(math3d.matvec(m, v), np.einsum("bij,bj->bi", m, v), rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(math3d.matvec_t(m, v), np.einsum("bji,bj->bi", m, v), rtol=1e-5, atol=1e-6)
  np.testing.assert_array_equal(math3d.with_component(v, 2, w[:, 0]), np.asarray(jnp.asarray(v).at[:, 2].set(w[:, 0])))
  np.testing.assert_array_equal(math3d.scale_head(v, 2, w[:, 1]),
                                np.asarray(jnp.asarray(v).at[:, :2].multiply(w[:, 1:2])))
