"""End-to-end env tests: missions flown by the autopilot alone, termination, NaN safety, auto-reset, override."""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers.training import VmapWrapper

import envs
from envs import missions as missions_lib
from envs import rollout
from envs.base import ASSETS, check_physics_options
from envs.wrappers import AutoReset
from specguard_jax import ekf as ekf_lib

SHORT_DRONE = missions_lib.MissionConfig.drone(max_duration_s=50.0, min_duration_s=25.0, n_waypoints=(2, 4))
SHORT_ROVER = missions_lib.MissionConfig.rover(max_duration_s=50.0, min_duration_s=25.0, n_waypoints=(2, 4))


@pytest.fixture(scope="module")
def drone_env():
  return envs.make("drone", world="urban_park", mission=SHORT_DRONE)


@pytest.fixture(scope="module")
def drone_step(drone_env):
  return jax.jit(drone_env.step)  # compiled once for the tests below


@pytest.fixture(scope="module")
def drone_reset(drone_env):
  return jax.jit(drone_env.reset)  # compiled once (run eagerly, op by op, a reset takes ~50 s on a 2-core CPU)


@pytest.fixture(scope="module")
def drone_vreset(drone_env):
  """The drone env's reset vmapped over a [B] key batch, compiled once per batch size for the tests below."""
  return jax.jit(VmapWrapper(drone_env).reset)


@pytest.fixture(scope="module")
def rover_env():
  return envs.make("rover", world="urban_city_streets", mission=SHORT_ROVER)


def test_make_rejects_bad_input():
  with pytest.raises(ValueError, match="unknown vehicle 'boat'"):
    envs.make("boat")
  with pytest.raises(ValueError, match="unknown world 'moon'"):
    envs.make("drone", world="moon")
  with pytest.raises(ValueError, match="unknown env option"):
    envs.make("drone", wings=2)
  with pytest.raises(ValueError, match="control_mode"):
    envs.make("drone", control_mode="fly-by-wire")


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_physics_options_step_like_mjx_defaults(vehicle, tmp_path):
  """The assets' sparse mass matrix and disabled implicit Euler damping (faster on the GPU) step the vehicle as MJX's
  defaults do (dense M, implicit damping refactorisation): 50 physics steps (1 s) from a spinning, moving start under
  constant actuation agree to float32 rounding; and a model that adds joint damping is refused."""
  import mujoco
  from mujoco import mjx

  path = os.path.join(ASSETS, f"{vehicle}.xml")
  fast = mujoco.MjModel.from_xml_path(path)
  assert fast.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE
  assert fast.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
  assert not np.any(fast.dof_damping)
  default = mujoco.MjModel.from_xml_path(path)
  default.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
  default.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)

  def run(m):
    mx = mjx.put_model(m)
    d = mjx.make_data(mx)
    d = d.replace(qvel=jnp.linspace(-1.0, 1.0, m.nv))
    if m.nu:
      d = d.replace(ctrl=jnp.array([4.0, 3.5, 3.8, 3.6])[: m.nu])
    else:
      d = d.replace(qfrc_applied=jnp.array([10.0, -3.0, 0.5]))
    d = jax.jit(lambda d: jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), d, None, length=50)[0])(d)
    return np.asarray(d.qpos), np.asarray(d.qvel)

  (qf, vf), (qd, vd) = run(fast), run(default)
  assert np.all(np.isfinite(qf)) and np.abs(qd[:2]).max() > 0.2   # it moved
  np.testing.assert_allclose(qf, qd, rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(vf, vd, rtol=1e-4, atol=1e-4)

  src = open(path).read()
  src = (src.replace('<freejoint name="root"/>', '<joint name="root" type="free" damping="0.5"/>') if vehicle == "drone"
         else src.replace('<joint name="yaw" type="hinge"', '<joint name="yaw" type="hinge" damping="0.5"'))
  bad = tmp_path / f"{vehicle}.xml"
  bad.write_text(src)
  with pytest.raises(ValueError, match="joint damping needs the implicit Euler damping"):
    check_physics_options(mujoco.MjModel.from_xml_path(str(bad)), f"{vehicle}.xml")


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_physics_state_holds_all_that_mjx_step_reads(vehicle, drone_env, rover_env):
  """The env carries an envs.base.PhysicsState, not an mjx.Data, so mjx.step must read nothing of the Data but those
  fields and the tick's inputs: from a moving state, a Data whose every other field (kinematics, inertia, forces,
  qacc, constraint and contact arrays) holds garbage steps to bit-identically what the clean Data and
  env.physics_data(PhysicsState.of(data)) step to."""
  from mujoco import mjx

  from envs.base import PhysicsState
  env = drone_env if vehicle == "drone" else rover_env
  m = env.mjx_model
  nu, nv = env.mj_model.nu, env.mj_model.nv
  inputs = {"qfrc_applied": jnp.linspace(-2.0, 3.0, nv)}
  if nu:
    inputs["ctrl"] = jnp.linspace(3.0, 4.5, nu)
  step = jax.jit(lambda d: mjx.step(m, d))
  d = env.physics_data(PhysicsState.of(mjx.make_data(m)).replace(
      qpos=jnp.asarray(env.mj_model.qpos0, jnp.float32) + 0.1, qvel=jnp.linspace(-1.0, 1.0, nv)), **inputs)
  for _ in range(5):   # a state with non-zero velocities, forces and warm start
    d = step(d).replace(**inputs)
  kept = {f.name for f in dataclasses.fields(PhysicsState)} | set(inputs) | {
      "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata"}
  rng = np.random.default_rng(0)
  noise = lambda x: (jnp.asarray(rng.normal(size=x.shape) * 7.0, x.dtype)   # noqa: E731
                     if jnp.issubdtype(x.dtype, jnp.floating) else x)
  dirty = d.replace(**{f.name: jax.tree.map(noise, getattr(d, f.name)) for f in dataclasses.fields(d)
                       if f.name not in kept})
  assert not np.array_equal(np.asarray(dirty.xpos), np.asarray(d.xpos))   # the garbage is there
  outs = [step(x) for x in (d, dirty, env.physics_data(PhysicsState.of(d), **inputs))]
  for name in ("qpos", "qvel", "qacc", "qacc_warmstart", "time"):
    for o in outs[1:]:
      np.testing.assert_array_equal(np.asarray(getattr(o, name)), np.asarray(getattr(outs[0], name)), err_msg=name)
  assert float(jnp.max(jnp.abs(outs[0].qvel - d.qvel))) > 1e-4   # it moved


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_autopilot_completes_missions_compliantly(vehicle, drone_env, rover_env):
  """The autopilot alone completes every short mission with no collision, crash, stall or geofence entry, and every
  mission spec (online STL monitor over the whole episode) is satisfied."""
  env = drone_env if vehicle == "drone" else rover_env
  keys = jax.random.split(jax.random.PRNGKey(11), 4)
  state, traj, t = rollout.fly_batch(env, keys, 1200)
  s = rollout.summarize(state)
  assert s["complete"] == 4, s
  assert s["collision"] == s["crash"] == s["stall"] == s["fence_breach"] == s["nan"] == 0
  rob = np.asarray(state.info["spec_robustness"])
  assert rob.shape == (4, len(env.spec_names))
  assert np.all(rob >= 0), dict(zip(env.spec_names, rob.min(0)))
  ep = state.info["episode"]
  assert np.all(np.asarray(ep["min_obstacle_distance"]) > 5.0)       # S1/S6 margin with the world's clearance
  # The recorded trajectory ends near the last waypoint (or on the ground below it).
  pos = np.asarray(traj["pos"])[np.asarray(traj["valid"])]
  m0 = jax.tree.map(lambda x: np.asarray(x[0]), state.info["mission"])
  last = m0.waypoints[m0.n_waypoints - 1]
  assert np.linalg.norm((pos[-1] - last)[:2]) < 5.0
  # EKF stayed close to the truth on the way: within the GPS's slowly correlated error (metres, stationary σ per axis
  # in SensorConfig, which the EKF follows) of it, plus the EKF's own 1.5 m.
  sc = env.sensor_cfg
  gps_sigma = np.sqrt(2 * sc.gps_drift_sigma_h ** 2 + sc.gps_drift_sigma_v ** 2)     # m, 3-D
  assert np.sqrt(np.mean(np.sum((np.asarray(traj["est"]) - np.asarray(traj["pos"]))[np.asarray(traj["valid"])] ** 2,
                                axis=-1))) < 1.5 + 2.5 * gps_sigma


def test_reset_is_deterministic_and_signals_consistent(drone_env, drone_reset):
  env, reset = drone_env, drone_reset
  a, b, c = reset(jax.random.PRNGKey(1)), reset(jax.random.PRNGKey(1)), reset(jax.random.PRNGKey(2))
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  assert not np.allclose(a.info["mission"].waypoints, c.info["mission"].waypoints)
  sig = a.info["signals"]
  pos = a.info["sim"]["truth"].pos
  wp0 = a.info["mission"].waypoints[0]
  assert float(sig["dist_wp"]) == pytest.approx(float(jnp.linalg.norm(wp0 - pos)), abs=1e-3)
  assert float(sig["altitude"]) == pytest.approx(0.0, abs=1e-3)
  assert a.obs.shape == (env.observation_size,)
  assert np.all(np.isfinite(np.asarray(a.obs)))


def test_collision_terminates(drone_reset, drone_step):
  """An obstacle planted on the take-off point: obstacle distance < vehicle radius -> collision, episode ends."""
  s = drone_reset(jax.random.PRNGKey(3))
  w = s.info["world"]
  home = s.info["mission"].home
  cyl = w.cylinders.at[0].set(jnp.array([home[0], home[1], 2.0, 40.0]))
  s = s.replace(info=dict(s.info, world=w.replace(cylinders=cyl, cylinder_mask=w.cylinder_mask.at[0].set(True))))
  s2 = drone_step(s, jnp.zeros(3))
  assert float(s2.done) == 1.0
  assert float(s2.metrics["collision"]) == 1.0
  assert float(s2.info["signals"]["obstacle_distance"]) < 0


def test_progress_pays_each_metre_of_a_leg_once(drone_reset, drone_step):
  """The 'progress' metric (TrainConfig.progress_reward's pay): >= 0, the drop of the leg's closest approach to its
  goal, so over the take-off climb it telescopes to the distance closed; and nothing is paid for coming back to
  where the vehicle has already been (closest approach set to 0 m: no progress left on the leg)."""
  s = drone_reset(jax.random.PRNGKey(4))
  start = float(s.info["episode"]["closest"])
  paid = []
  for _ in range(30):   # 3 s of the take-off climb
    s = drone_step(s, jnp.zeros(3))
    paid.append(float(s.metrics["progress"]))
  ep = s.info["episode"]
  assert int(s.info["sim"]["nav"].phase) == 0 and float(s.done) == 0.0   # still the take-off leg
  assert min(paid) >= 0.0
  assert sum(paid) > 1.0, paid   # the climb closes metres on the take-off altitude
  np.testing.assert_allclose(sum(paid), start - float(ep["closest"]), rtol=1e-4, atol=1e-4)
  done_leg = s.replace(info=dict(s.info, episode=dict(ep, closest=jnp.zeros_like(ep["closest"]))))
  s2 = drone_step(done_leg, jnp.zeros(3))
  assert float(s2.metrics["progress"]) == 0.0 and float(s2.info["episode"]["closest"]) == 0.0


def test_step_obstacle_queries_land_where_the_separate_queries_would(drone_reset, drone_step):
  """The step's one-pass obstacle queries (worlds.obstacle_queries) feed each consumer its own point: the signals'
  obstacle distance is the SDF at the final true position, the observation's distance and direction are those at the
  EKF's estimate, and the episode's minimum covers the step's ticks (<= the final tick's distance)."""
  from envs import worlds
  s = drone_reset(jax.random.PRNGKey(5))
  w = s.info["world"]
  home = s.info["mission"].home
  cyl = w.cylinders.at[0].set(jnp.array([home[0] + 6.0, home[1] + 1.0, 1.0, 40.0]))
  s = s.replace(info=dict(s.info, world=w.replace(cylinders=cyl, cylinder_mask=w.cylinder_mask.at[0].set(True))))
  world = s.info["world"]
  for _ in range(3):
    s = drone_step(s, jnp.zeros(3))
    truth, est = s.info["sim"]["truth"].pos, s.info["sim"]["ekf"].pos
    d_true = float(worlds.obstacle_sdf(world, truth))
    assert d_true < 10.0      # the planted cylinder is the nearest obstacle, within the signals' cap
    assert float(s.info["signals"]["obstacle_distance"]) == pytest.approx(d_true, abs=1e-5)
    d_est, g_est = worlds.obstacle_sdf_and_grad(world, est)
    np.testing.assert_allclose(np.asarray(s.obs[15:19]), np.append(-np.asarray(g_est), float(d_est)), atol=1e-5)
    assert float(s.info["episode"]["min_obstacle_distance"]) <= d_true + 1e-5


def test_nan_physics_never_leaks(drone_reset, drone_step):
  """A NaN thrust gain blows up the physics: the step ends the episode, flags it, zero reward, finite obs/state."""
  s = drone_reset(jax.random.PRNGKey(4))
  dr = dict(s.info["sim"]["dr"], thrust_gain=jnp.asarray(jnp.nan))
  s = s.replace(info=dict(s.info, sim=dict(s.info["sim"], dr=dr)))
  s2 = drone_step(s, jnp.zeros(3))
  assert float(s2.done) == 1.0 and float(s2.metrics["nan"]) == 1.0
  assert float(s2.reward) == 0.0
  assert np.all(np.isfinite(np.asarray(s2.obs)))
  assert np.all(np.isfinite(np.asarray(s2.pipeline_state.qpos)))
  # the episode record and the STL monitor stay finite too (the minimum obstacle distance had taken the NaN)
  for x in jax.tree.leaves((s2.info["episode"], s2.info["signals"], s2.info["spec_robustness"])):
    assert np.all(np.isfinite(np.asarray(x))), s2.info["episode"]


def test_nan_step_under_autoreset_without_the_fallback(drone_env, drone_autoreset):
  """The trainer's env skips the NaN fallback (EnvConfig.nan_fallback=False, ppo/iteration.make_env): after a step
  whose physics went NaN, AutoReset gives the same state as with the fallback (the finished env takes a fresh pool
  entry either way), with no NaN anywhere; only the pre-reset observation differs (zeros instead of the last one)."""
  import copy
  env_nf = copy.copy(drone_env)
  env_nf.config = dataclasses.replace(drone_env.config, nan_fallback=False)
  _, reset, step = drone_autoreset
  s = reset(jax.random.split(jax.random.PRNGKey(6), 2))
  dr = s.info["sim"]["dr"]
  dr = dict(dr, thrust_gain=dr["thrust_gain"].at[0].set(jnp.nan))
  s = s.replace(info=dict(s.info, sim=dict(s.info["sim"], dr=dr)))
  act = jnp.zeros((2, 3))
  a = step(s, act)
  b = jax.jit(AutoReset(VmapWrapper(env_nf), pool_size=4, refresh=2).step)(s, act)
  assert np.asarray(b.done).tolist() == [1.0, 0.0] and np.asarray(b.metrics["nan"]).tolist() == [1.0, 0.0]
  assert float(b.reward[0]) == 0.0
  # Two programs (with and without the fallback), which XLA fuses and so rounds differently: floats to float32
  # rounding as one step carries it (once the SDFs were written on components, the healthy env's obs were 1 ulp and
  # its solver's accelerations 2.5e-6 relative apart), integers and flags exactly.
  same = lambda x, y, msg="": (np.testing.assert_allclose(x, y, rtol=2e-5, atol=1e-6, err_msg=msg)  # noqa: E731
                               if np.issubdtype(np.asarray(y).dtype, np.floating)
                               else np.testing.assert_array_equal(x, y, err_msg=msg))
  final_a, final_b = np.asarray(a.info["final_obs"]), np.asarray(b.info["final_obs"])
  same(final_a[1], final_b[1])
  assert np.all(np.isfinite(final_b))
  strip = lambda st: st.replace(info={k: v for k, v in st.info.items() if k != "final_obs"})  # noqa: E731
  for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(strip(a)), jax.tree.leaves(strip(b))):
    x, y = np.asarray(x), np.asarray(y)
    same(x, y, jax.tree_util.keystr(path))
    if np.issubdtype(y.dtype, np.floating):
      assert not np.any(np.isnan(y)), jax.tree_util.keystr(path)


def _time_limit(drone_env, s):
  """[B] s: each env's episode time limit, min(max_episode_s, 2 x nominal duration + 30 s)."""
  return jnp.minimum(drone_env.config.max_episode_s, 2.0 * s.info["mission"].nominal_duration + 30.0)


def _truncate_env0_next_step(drone_env, s):
  """s with env 0 just short of its time limit (and not stalled), so the next step truncates it."""
  t_end = _time_limit(drone_env, s)[0] - 0.01
  ep = dict(s.info["episode"], last_progress=s.info["episode"]["last_progress"].at[0].set(t_end))  # no stall
  return s.replace(info=dict(s.info, time=s.info["time"].at[0].set(t_end), episode=ep))


@pytest.fixture(scope="module")
def drone_autoreset(drone_env):
  """(AutoReset over 2 drone envs, its jitted reset, its jitted step), compiled once for the tests below."""
  env = AutoReset(VmapWrapper(drone_env), pool_size=4, refresh=2)
  return env, jax.jit(env.reset), jax.jit(env.step)


def test_autoreset_reset_is_the_envs_and_the_pool_reset_apart(drone_autoreset, drone_vreset):
  """AutoReset.reset resets the envs and the pool in one vmapped call: each env and pool entry is what resetting it
  alone from its key gives (the keys, and so a seed's episodes, are unchanged), to float rounding."""
  _, reset, _ = drone_autoreset
  keys = jax.random.split(jax.random.PRNGKey(5), 2)
  s = reset(keys)
  alone = drone_vreset
  k_pool, _ = jax.random.split(jax.random.fold_in(keys[0], 0x5eed))
  envs = alone(keys)
  for got, want in ((s.replace(info={k: v for k, v in s.info.items() if k in envs.info}), envs),
                    (s.info["reset_pool"], alone(jax.random.split(k_pool, 4)))):
    for (path, x), y in zip(jax.tree_util.tree_flatten_with_path(want)[0], jax.tree.leaves(got)):
      np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-6, atol=1e-5,
                                 err_msg=jax.tree_util.keystr(path))


def test_autoreset_starts_a_new_mission(drone_env, drone_autoreset):
  env, reset, step = drone_autoreset
  s = reset(jax.random.split(jax.random.PRNGKey(5), 2))
  s = _truncate_env0_next_step(drone_env, s)
  old_wp = np.asarray(s.info["mission"].waypoints)
  s2 = step(s, jnp.zeros((2, 3)))
  assert np.asarray(s2.done).tolist() == [1.0, 0.0]
  assert float(s2.info["truncation"][0]) == 1.0
  assert float(s2.info["time"][0]) == 0.0 and float(s2.info["time"][1]) > 0.0
  assert not np.allclose(np.asarray(s2.info["mission"].waypoints[0]), old_wp[0])
  np.testing.assert_allclose(np.asarray(s2.info["mission"].waypoints[1]), old_wp[1])
  # The GPS schedule `step` relies on (envs/base.py: the GPS rows are left out of the EKF update on the other ticks):
  # every step, including the one that auto-reset env 0, ends on a GPS-fresh tick, sensor tick = 1 mod the period.
  period = round(1.0 / (drone_env.config.tick_dt * drone_env.sensor_cfg.gps_rate))
  assert period == 5 and drone_env.config.ticks_per_step % period == 0
  for st in (s, s2):
    assert np.all(np.asarray(st.info["sim"]["sensors"].tick) % period == 1)
  assert np.all(np.asarray(s2.info["sim"]["readings"].gps_fresh) == 1.0)


def test_next_obs_is_the_next_steps_obs_unless_finished(drone_env, drone_autoreset):
  """What the trainer's bootstrap_values relies on: under AutoReset, a step's final_obs (before any reset) is
  bitwise the next step's obs for an env that did not finish, and no episode is truncated before
  EnvBase.min_truncated_episode_steps() steps."""
  env, reset, step = drone_autoreset
  s = reset(jax.random.split(jax.random.PRNGKey(6), 2))
  assert drone_env.min_truncated_episode_steps() * drone_env.dt < float(jnp.min(_time_limit(drone_env, s)))
  assert drone_env.min_truncated_episode_steps() >= 250      # 30 s at 10 steps per second, less slack
  s = _truncate_env0_next_step(drone_env, s)    # env 0 is truncated by the first step
  for t in range(3):
    s2 = step(s, jnp.zeros((2, 3)))
    for i in range(2):
      if float(s2.done[i]) == 0.0:
        np.testing.assert_array_equal(np.asarray(s2.info["final_obs"][i]), np.asarray(s2.obs[i]))
      else:
        assert t == 0 and i == 0 and float(s2.info["truncation"][i]) == 1.0
        assert not np.array_equal(np.asarray(s2.info["final_obs"][i]), np.asarray(s2.obs[i]))
    s = s2


def test_ekf_gps_rows_left_out_only_where_gps_is_stale(drone_env, drone_vreset):
  """The env step with the GPS rows left out of the EKF on its stale ticks equals the step that fuses every row on
  every tick (a GPS sample dropped by mistake would move the estimate). The skip is on by default off the CPU only."""
  import copy
  env_skip, env_full = copy.copy(drone_env), copy.copy(drone_env)
  env_skip._gps_period, env_full._gps_period = 5, None
  s = drone_vreset(jax.random.split(jax.random.PRNGKey(8), 2))
  a = jnp.zeros((2, 3))
  jaxpr_skip, jaxpr_full = (str(jax.make_jaxpr(jax.vmap(e.step))(s, a)) for e in (env_skip, env_full))
  # the 4 GPS-free ticks as a scan, the GPS tick after it: no lax.cond
  assert "length=4" in jaxpr_skip and "length=4" not in jaxpr_full and "cond" not in jaxpr_skip

  def three(env, s):   # a rolled loop: one copy of each env step in the program
    return jax.lax.fori_loop(0, 3, lambda _, s: jax.vmap(env.step)(s, a), s)
  out_skip, out_full = jax.jit(lambda s: (three(env_skip, s), three(env_full, s)))(s)
  # The same filter in two programs, which XLA fuses (and so rounds) differently: float32 rounding apart (a flow
  # innovation of 0.03 was 1.3e-7 apart on the CI machine), far below any difference a wrong GPS schedule makes.
  for name in ("pos", "vel", "quat", "P", "test_ratio", "accepted", "innov", "gps_pos_age"):
    np.testing.assert_allclose(np.asarray(getattr(out_skip.info["sim"]["ekf"], name)),
                               np.asarray(getattr(out_full.info["sim"]["ekf"], name)), rtol=2e-5,
                               atol=1e-9 if name == "P" else 1e-6, err_msg=name)
  np.testing.assert_allclose(np.asarray(out_skip.pipeline_state.qpos), np.asarray(out_full.pipeline_state.qpos),
                             rtol=1e-6, atol=1e-7)


def _eqns_named(jaxpr, name):
  """The equations of primitive `name` in a jaxpr and in every jaxpr nested in its equations' parameters."""
  out = []
  for e in jaxpr.eqns:
    if e.primitive.name == name:
      out.append(e)
    for v in e.params.values():
      for sub in (v if isinstance(v, (tuple, list)) else (v,)):
        sub = getattr(sub, "jaxpr", sub)
        if hasattr(sub, "eqns"):
          out += _eqns_named(sub, name)
  return out


def test_unrolled_ticks_run_the_same_ticks(drone_env):
  """EnvConfig.unroll_ticks unrolls the env step's tick scans (each scan's unroll is its length), the same ticks in
  the same order with the same GPS schedule, with and without the GPU's GPS grouping (a toy tick whose result depends
  on the order and on gps_due)."""
  import copy

  def tick(c, k, gps_due):   # c, k [3]; the "true position" output is the carry before the tick
    return c * 1.5 + k + (100.0 if gps_due else 0.0) + (7.0 if gps_due is None else 0.0), c

  c0, keys = jnp.array([1.0, -2.0, 0.5]), jnp.arange(15.0).reshape(5, 3)
  for period in (None, 5):
    outs, unrolls = [], []
    for unroll in (False, True):
      env = copy.copy(drone_env)
      env.config = dataclasses.replace(drone_env.config, unroll_ticks=unroll)
      env._gps_period = period
      fn = lambda c, k: env._tick_loop(tick, c, k)   # noqa: B023
      outs.append(jax.jit(fn)(c0, keys))
      scans = _eqns_named(jax.make_jaxpr(fn)(c0, keys).jaxpr, "scan")
      inner = [e for e in scans if e.params["length"] == (5 if period is None else 4)]
      assert len(inner) == 1, scans
      unrolls.append(inner[0].params["unroll"])
    assert unrolls == [1, 5 if period is None else 4]
    for a, b in zip(jax.tree.leaves(outs[0]), jax.tree.leaves(outs[1])):
      np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)
  assert envs.make("rover", unroll_ticks=True).config.unroll_ticks


def test_env_without_ekf_records_is_the_same_env(drone_env, drone_vreset):
  """EnvConfig.ekf_records=False (the trainer's env unless it trains with the residual detector) leaves the EKF's
  per-channel records at their reset values and changes nothing else: physics, estimate, P, observation, reward,
  STL monitor and episode record equal the env's with them (float32 rounding: two programs); the residual detector,
  which reads them, refuses the setting."""
  import copy
  env_off = copy.copy(drone_env)
  env_off.config = dataclasses.replace(drone_env.config, ekf_records=False)
  s = drone_vreset(jax.random.split(jax.random.PRNGKey(9), 2))
  a = jnp.tile(jnp.array([[0.5, -0.3, 0.2]]), (2, 1))

  def three(env, s):
    return jax.lax.fori_loop(0, 3, lambda _, s: jax.vmap(env.step)(s, a), s)
  on, off = jax.jit(lambda s: (three(drone_env, s), three(env_off, s)))(s)
  ekf0, ekf_on, ekf_off = (x.info["sim"]["ekf"] for x in (s, on, off))
  for name in ekf_lib.RECORD_FIELDS:
    np.testing.assert_array_equal(np.asarray(getattr(ekf_off, name)), np.asarray(getattr(ekf0, name)), name)
  # ... which the env with them updates (else this test could not tell the two apart)
  assert np.any(np.asarray(ekf_on.test_ratio) != np.asarray(ekf0.test_ratio))
  assert np.any(np.asarray(ekf_on.fresh) != np.asarray(ekf0.fresh))
  drop = lambda st: st.replace(info=dict(st.info, sim=dict(st.info["sim"], ekf=st.info["sim"]["ekf"].replace(  # noqa: E731
      **{n: jnp.zeros(()) for n in ekf_lib.RECORD_FIELDS}))))
  for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(drop(on)), jax.tree.leaves(drop(off))):
    x, y = np.asarray(x), np.asarray(y)
    if np.issubdtype(y.dtype, np.floating):
      np.testing.assert_allclose(x, y, rtol=2e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path))
    else:
      np.testing.assert_array_equal(x, y, err_msg=jax.tree_util.keystr(path))
  with pytest.raises(ValueError, match="ekf_records"):
    envs.make("drone", detector="residual", ekf_records=False)


def test_autoreset_bulk_refresh_equals_in_step_refresh(drone_env, drone_vreset):
  """refresh_in_step=False leaves the pool alone in step; refresh_pool(state, 1) then gives the state the in-step
  refresh gives (same entries, same keys), and refresh_pool(state, k) regenerates min(pool, refresh x k) entries."""
  keys = jax.random.split(jax.random.PRNGKey(6), 2)
  inline = AutoReset(VmapWrapper(drone_env), pool_size=4, refresh=1)
  bulk = AutoReset(VmapWrapper(drone_env), pool_size=4, refresh=1, refresh_in_step=False)
  s = jax.jit(inline.reset)(keys)
  a = jnp.zeros((2, 3))
  # one program for both steps (XLA shares the env step they have in common: one compile instead of two)
  s_inline, s_bulk = jax.jit(lambda s: (inline.step(s, a), bulk.step(s, a)))(s)
  pool0 = np.asarray(s.info["reset_pool"].info["mission"].waypoints)
  np.testing.assert_array_equal(np.asarray(s_bulk.info["reset_pool"].info["mission"].waypoints), pool0)
  assert int(s_bulk.info["pool_refresh"]) == 0
  refresh = jax.jit(bulk.refresh_pool, static_argnums=1)
  s_bulk1 = refresh(s_bulk, 1)
  # Same entries from the same keys; the two programs may round a float differently (XLA fuses the reset into
  # different neighbours in each, e.g. a domain-randomisation scale 1 ulp apart), so floats to 1e-6 relative, and
  # 1e-7 absolute for entries that are 0 up to rounding (an observed acceleration at rest came out 2e-9 apart).
  for x, y in zip(jax.tree.leaves(s_inline), jax.tree.leaves(s_bulk1)):
    x, y = np.asarray(x), np.asarray(y)
    if np.issubdtype(x.dtype, np.floating):
      np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)
    else:
      np.testing.assert_array_equal(x, y)
  assert int(s_inline.info["pool_refresh"]) == 1
  s_bulk3 = refresh(s_bulk, 3)
  wp3 = np.asarray(s_bulk3.info["reset_pool"].info["mission"].waypoints)
  changed = [not np.allclose(wp3[i], pool0[i]) for i in range(4)]
  assert changed == [True, True, True, False] and int(s_bulk3.info["pool_refresh"]) == 3
  # The whole pool from a pointer at 3 (reset in slot order, no scatter): entry j of the round robin in slot (3 + j) % 4
  s_all = refresh(s_bulk3, 4)
  assert int(s_all.info["pool_refresh"]) == 3
  _, sub = jax.random.split(s_bulk3.info["reset_key"])
  new = drone_vreset(jax.random.split(sub, 4))
  slot_of_entry = [(3 + j) % 4 for j in range(4)]
  # Two programs again: an observation entry that is 0 up to rounding (1e-8, a velocity at rest) came out 5e-9 apart
  # when XLA fuses the reset's neighbours differently, hence atol 1e-7.
  for x, y in zip(jax.tree.leaves(new), jax.tree.leaves(s_all.info["reset_pool"])):
    x, y = np.asarray(x), np.asarray(y)
    np.testing.assert_allclose(y[slot_of_entry], x, rtol=1e-6, atol=1e-7)
  assert not np.allclose(np.asarray(s_all.info["reset_pool"].info["mission"].waypoints)[3], wp3[3])


def test_velocity_setpoint_override():
  """In 'override' mode the action (world velocity setpoint) replaces the navigator's once airborne."""
  env = envs.make("drone", world="open_beach", mission=SHORT_DRONE, control_mode="override",
                  domain_randomization=False)

  def policy(obs, key):
    return jnp.broadcast_to(jnp.array([3.0, -2.0, 0.0]), obs.shape[:-1] + (3,))

  state, traj, t = rollout.fly_batch(env, jax.random.split(jax.random.PRNGKey(6), 2), 150, policy=policy)
  vel = np.asarray(state.info["sim"]["truth"].vel)
  assert np.all(np.asarray(state.info["sim"]["nav"].phase) == 1)   # cruising, under override
  np.testing.assert_allclose(vel[:, :2], [[3.0, -2.0]] * 2, atol=0.4)


def test_attitude_residual_reaches_the_attitude_loop():
  """EnvConfig.override_attitude: the action's entries 3:6 (m/s^2, world frame here) are added to the acceleration
  setpoint the attitude loop flies. From one cruising state, twice: +3 m/s^2 along x for 0.5 s speeds the drone up
  along x against the same velocity setpoint without it; the rover, with no attitude loop, refuses the option."""
  env = envs.make("drone", world="open_beach", mission=SHORT_DRONE, control_mode="override", override_attitude=True,
                  domain_randomization=False)
  assert env.action_size == 6
  cruise = jnp.array([3.0, -2.0, 0.0, 0.0, 0.0, 0.0])
  key = jax.random.PRNGKey(6)
  policy = lambda obs, k: jnp.broadcast_to(cruise, obs.shape[:-1] + (6,))  # noqa: E731
  state, _, _ = rollout.fly_batch(env, jnp.stack([key, key]), 150, policy=policy)
  assert np.all(np.asarray(state.info["sim"]["nav"].phase) == 1)   # both cruising, under override, the same state
  act = jnp.stack([cruise, cruise.at[3].set(3.0)])
  step = lambda s, _: (jax.vmap(env.step)(s, act), None)  # noqa: E731
  out = jax.jit(lambda s: jax.lax.scan(step, s, None, length=5)[0])(state)
  v0, v1 = np.asarray(out.info["sim"]["truth"].vel)
  assert v1[0] - v0[0] > 0.3, (v0, v1)               # the residual moved the vehicle along x ...
  assert abs(v1[1] - v0[1]) < 0.1, (v0, v1)          # ... and only along x
  with pytest.raises(ValueError, match="no attitude loop"):
    envs.make("rover", override_attitude=True)


def test_autoreset_in_chunks_equals_one_vmapped_reset(drone_env):
  """reset_chunk cuts the reset of the envs + pool (and the bulk pool refresh) into equal chunks run one after
  another: 6 envs + 4 pool entries in chunks of 3 (4 chunks of 3, the last padded) give the states one vmapped
  reset gives."""
  keys = jax.random.split(jax.random.PRNGKey(11), 6)
  whole = AutoReset(VmapWrapper(drone_env), pool_size=4, refresh=4, refresh_in_step=False)
  parts = AutoReset(VmapWrapper(drone_env), pool_size=4, refresh=4, refresh_in_step=False, reset_chunk=3)

  def both(env):
    s = env.reset(keys)
    return s, env.refresh_pool(s, 1)

  (s1, r1), (s3, r3) = jax.jit(lambda: (both(whole), both(parts)))()
  for a, b in zip(jax.tree.leaves((s1, r1.info["reset_pool"])), jax.tree.leaves((s3, r3.info["reset_pool"]))):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
  assert not np.allclose(np.asarray(r1.info["reset_pool"].info["mission"].waypoints),
                         np.asarray(s1.info["reset_pool"].info["mission"].waypoints))   # the refresh did regenerate
  with pytest.raises(ValueError, match="reset_chunk"):
    AutoReset(VmapWrapper(drone_env), reset_chunk=0)
  # what the chunks are for: the reset's temporaries are those of one chunk (XLA's buffer assignment)
  keys = jax.random.split(jax.random.PRNGKey(12), 56)    # 56 envs + the pool of 4: 60 resets, in chunks of 3 or not
  temp = lambda env: jax.jit(env.reset).lower(keys).compile().memory_analysis().temp_size_in_bytes  # noqa: E731
  assert temp(parts) < 0.25 * temp(whole)
