"""The policy's observation layouts (envs.observation): the proximity ring's ray casts against the geometry, its noise,
the layouts' sizes, and the layout a run records in policy_config.json (export, evaluate.py's controllers)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import geometry as geo
from envs import observation as obs_lib
from envs import worlds
from specguard_jax import controllers, export
from specguard_jax.ppo.networks import Policy


def _march(inside, p, d, max_range=60.0, step=0.002):
  """Reference range (numpy): the first point along p + t d (t on a fine grid) that `inside` holds for."""
  t = np.arange(0.0, max_range, step)
  hit = inside(p[None, :2] + t[:, None] * d[None, :])
  return float(t[np.argmax(hit)]) if hit.any() else geo.FAR


def _in_box(q, box):
  c, s = np.cos(box[4]), np.sin(box[4])
  x, y = q[:, 0] - box[0], q[:, 1] - box[1]
  return (np.abs(c * x + s * y) <= box[2]) & (np.abs(-s * x + c * y) <= box[3])


def test_ray_casts_equal_a_fine_march_along_the_beam():
  rng = np.random.default_rng(0)
  n = 40
  p = np.c_[rng.uniform(-10, 10, (n, 2)), np.full(n, 3.0)].astype(np.float32)
  cyl = np.c_[rng.uniform(-15, 15, (n, 2)), rng.uniform(0.5, 4, n), np.full(n, 10.0)].astype(np.float32)
  box = np.c_[rng.uniform(-15, 15, (n, 2)), rng.uniform(0.5, 5, (n, 2)), rng.uniform(-3, 3, n),
              np.full(n, 10.0)].astype(np.float32)

  def beams(centres):   # roughly at the shape: about half the beams hit it
    a = np.arctan2(centres[:, 1] - p[:, 1], centres[:, 0] - p[:, 0]) + rng.uniform(-0.8, 0.8, n)
    return np.c_[np.cos(a), np.sin(a)].astype(np.float32)

  d_c, d_b = beams(cyl), beams(box)
  got_c = np.asarray(jax.jit(jax.vmap(geo.ray_cylinder))(p, d_c, cyl))
  got_b = np.asarray(jax.jit(jax.vmap(geo.ray_box))(p, d_b, box))
  hits = 0
  for i in range(n):
    ref_c = _march(lambda q: np.hypot(q[:, 0] - cyl[i, 0], q[:, 1] - cyl[i, 1]) <= cyl[i, 2], p[i], d_c[i])
    ref_b = _march(lambda q: _in_box(q, box[i]), p[i], d_b[i])
    for got, ref in ((got_c[i], ref_c), (got_b[i], ref_b)):
      hits += ref < geo.FAR
      assert (got == pytest.approx(ref, abs=0.005)) if ref < geo.FAR else got == geo.FAR
  assert 10 < hits < 2 * n - 10     # both hits and misses were checked
  # above an obstacle the horizontal beam misses it; inside it reads 0
  assert float(geo.ray_cylinder(np.float32([0, 0, 12]), np.float32([1, 0]), np.float32([5, 0, 1, 10]))) == geo.FAR
  assert float(geo.ray_box(np.float32([5, 0, 2]), np.float32([1, 0]), np.float32([5, 0, 1, 1, 0.3, 10]))) == 0.0
  rect = np.float32([-10, 20, -5, 5])
  assert float(geo.ray_rect_exit(np.float32([0, 0]), np.float32([1, 0]), rect)) == pytest.approx(20.0)
  assert float(geo.ray_rect_exit(np.float32([0, 0]), np.float32([0, -1]), rect)) == pytest.approx(5.0)
  assert float(geo.ray_rect_exit(np.float32([30, 0]), np.float32([1, 0]), rect)) == 0.0


def _world(**kw):
  z = lambda n, w: (jnp.zeros((n, w)), jnp.zeros(n, bool))  # noqa: E731
  cyl, cm = z(worlds.MAX_CYLINDERS, 4)
  box, bm = z(worlds.MAX_BOXES, 6)
  fen, fm = z(worlds.MAX_FENCES, 6)
  args = dict(cylinders=cyl, cylinder_mask=cm, boxes=box, box_mask=bm, fences=fen, fence_mask=fm,
              boundary=jnp.float32([-100, 100, -100, 100]), boundary_on=False, ceiling=1e3, wind_mean=jnp.zeros(3),
              gust_std=0.0, preset_id=-1)
  args.update(kw)
  return worlds.make_world(**args)


def test_proximity_ring_reads_each_sector_in_the_body_frame():
  cyl = jnp.zeros((worlds.MAX_CYLINDERS, 4)).at[0].set(jnp.float32([10, 0, 2, 20]))
  mask = jnp.zeros(worlds.MAX_CYLINDERS, bool).at[0].set(True)
  fen = jnp.zeros((worlds.MAX_FENCES, 6)).at[0].set(jnp.float32([0, -6, 30, 1, 0, worlds.FENCE_HEIGHT]))
  fmask = jnp.zeros(worlds.MAX_FENCES, bool).at[0].set(True)
  w = _world(cylinders=cyl, cylinder_mask=mask, fences=fen, fence_mask=fmask,
             boundary=jnp.float32([-50, 15, -100, 100]), boundary_on=True)
  pos = jnp.float32([0, 0, 5])
  r = np.asarray(worlds.proximity_ranges(w, pos, 0.0, 4, 20.0))
  # ahead (+x): the cylinder's surface at 8 m; left (+y): nothing within 20 m; behind: nothing; right: the fence
  np.testing.assert_allclose(r, [8.0, 20.0, 20.0, 5.0], atol=1e-4)
  # the vehicle turned to face +y: sector 0 now looks left, sector 3 (its right) at the cylinder
  r = np.asarray(worlds.proximity_ranges(w, pos, np.pi / 2, 4, 20.0))
  np.testing.assert_allclose(r, [20.0, 20.0, 5.0, 8.0], atol=1e-4)
  # the boundary's edge 15 m ahead once the cylinder is gone
  w2 = _world(boundary=jnp.float32([-50, 15, -100, 100]), boundary_on=True)
  assert float(worlds.proximity_ranges(w2, pos, 0.0, 4, 20.0)[0]) == pytest.approx(15.0)


def test_range_noise_has_the_datasheet_sigma():
  cfg = obs_lib.RangeSensorConfig()
  keys = jax.random.split(jax.random.PRNGKey(0), 4000)
  r = np.asarray(jax.vmap(lambda k: obs_lib.noisy_ranges(jnp.float32([2.0, 10.0]), k, 20.0, cfg))(keys))
  sigma = cfg.sigma_m + cfg.sigma_frac * np.array([2.0, 10.0])
  assert np.all(np.abs(r.mean(0) - [2.0, 10.0]) < 4 * sigma / np.sqrt(4000))
  np.testing.assert_allclose(r.std(0), sigma, rtol=0.06)
  capped = np.asarray(obs_lib.noisy_ranges(jnp.float32([20.0]), jax.random.PRNGKey(1), 20.0, cfg))
  assert capped[0] <= 20.0


def test_layout_sizes_and_description():
  assert obs_lib.size("paper24", 8) == 24
  assert obs_lib.size("recovery", 8) == 44 and obs_lib.size("recovery", 6) == 42
  d = obs_lib.describe("recovery", 6)
  assert d["name"] == "recovery" and d["version"] == obs_lib.LAYOUT_VERSION and obs_lib.sectors_of(d) == 6
  assert obs_lib.sectors_of(obs_lib.describe("paper24", 8)) == 0
  assert obs_lib.size("context", 8) == 48 and obs_lib.fields("context", 8)[:-1] == obs_lib.fields("recovery", 8)
  np.testing.assert_array_equal(obs_lib.phase_one_hot(jnp.int32([0, 1, 2, 3, 4])),
                                np.vstack([np.eye(4), np.zeros(4)]))   # done (4): no phase
  with pytest.raises(ValueError, match="unknown observation layout 'radar'"):
    obs_lib.size("radar", 8)
  # history: the frame, then the frames before it as one field; the first step repeats its frame
  h = obs_lib.describe("context", 8, 3)
  assert h["fields"][-1] == ["previous_frames", 96] and obs_lib.size("context", 8, 3) == 144
  assert obs_lib.history_of(h) == 3 and obs_lib.history_of(obs_lib.describe("context", 8)) == 1
  assert obs_lib.sectors_of(h) == 8 and obs_lib.frame_size("context", 8) == 48
  f0, f1, f2 = (jnp.full(4, float(i)) for i in range(3))
  o0 = obs_lib.with_history(f0, None, 3)
  o2 = obs_lib.with_history(f2, obs_lib.with_history(f1, o0, 3), 3)
  np.testing.assert_array_equal(o0, np.zeros(12))
  np.testing.assert_array_equal(o2, [2.0] * 4 + [1.0] * 4 + [0.0] * 4)
  assert obs_lib.with_history(f1, o0, 1) is f1


def _save(run_dir, n_obs, layout):
  pol = Policy(kind="gaussian", n=3, hidden=(8,), activation="tanh")
  params = pol.init(jax.random.PRNGKey(0), n_obs)
  export.save_policy(str(run_dir), pol, params, {"mean": np.zeros(n_obs), "std": np.ones(n_obs)}, (4.0, 4.0, 2.0),
                     obs_layout=layout)


def test_a_run_records_its_layout_and_evaluation_builds_it(tmp_path):
  _save(tmp_path / "new", 42, obs_lib.describe("recovery", 6))
  assert export.load_obs_layout(str(tmp_path / "new")) == obs_lib.describe("recovery", 6)
  assert controllers.obs_overrides(str(tmp_path / "new")) == (("obs_layout", "recovery"), ("proximity_sectors", 6))
  _save(tmp_path / "hist", 3 * 48, obs_lib.describe("context", 8, 3))
  assert controllers.obs_overrides(str(tmp_path / "hist")) == (("obs_layout", "context"), ("proximity_sectors", 8),
                                                                ("obs_history", 3))
  # a policy saved before layouts were recorded: the paper's 24 inputs
  _save(tmp_path / "old", 24, None)
  assert "obs_layout" not in json.loads((tmp_path / "old" / export.CONFIG_FILE).read_text())
  assert export.load_obs_layout(str(tmp_path / "old")) is None
  assert controllers.obs_overrides(str(tmp_path / "old")) == (("obs_layout", "paper24"),)
  # a layout that does not add up to the policy's inputs is refused when saving and when loading
  with pytest.raises(ValueError, match="obs_layout 'recovery' has 44 inputs, the policy takes 24"):
    _save(tmp_path / "bad", 24, obs_lib.describe("recovery", 8))
  cfg_path = tmp_path / "new" / export.CONFIG_FILE
  cfg = json.loads(cfg_path.read_text())
  cfg["obs_layout"]["fields"][-1][1] = 7
  cfg_path.write_text(json.dumps(cfg))
  with pytest.raises(ValueError, match="policy_config.json: bad obs_layout .*has 43 inputs, the policy takes 42"):
    export.load_obs_layout(str(tmp_path / "new"))
  # a layout this version does not build: one line, not a shape error in the rollout
  cfg["obs_layout"] = {"name": "lidar360", "version": 3, "fields": [["scan", 42]]}
  cfg_path.write_text(json.dumps(cfg))
  with pytest.raises(controllers.NotAvailable, match="layout 'lidar360' version 3 .42 inputs., which this version"):
    controllers.obs_overrides(str(tmp_path / "new"))


def test_an_old_run_config_keeps_the_paper_layout(tmp_path):
  """A run's config.json written before layouts existed has no env.obs_layout: resuming or evaluating it builds the
  24-input observation its checkpoint was trained on, where a new config file gets the trainer's default."""
  from specguard_jax.ppo import config as config_lib
  d = config_lib.TrainConfig().to_dict()
  assert d["env"]["obs_layout"] == "recovery"
  del d["env"]["obs_layout"]
  path = tmp_path / "config.json"
  path.write_text(json.dumps(d))
  assert config_lib.load_config_file(str(path), run=True).env.obs_layout == "paper24"
  assert config_lib.load_config_file(str(path)).env.obs_layout == "recovery"
  d["env"]["obs_layout"] = "recovery"
  path.write_text(json.dumps(d))
  assert config_lib.load_config_file(str(path), run=True).env.obs_layout == "recovery"
