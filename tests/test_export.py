"""Policy export: ONNX graph vs the JAX reference (onnxruntime), dynamic batch, run-directory save/load."""

import json
import os

import jax
import numpy as np
import onnx
import onnxruntime as ort
import pytest

from envs import observation as obs_lib
from specguard_jax import export as ex
from specguard_jax.ppo.networks import DIRECTIONS, Policy

N_OBS = 24
SPEEDS = np.array([2.0, 1.5, 0.75], np.float32)


def _normalizer(seed=1, n_obs=N_OBS):
  rng = np.random.default_rng(seed)
  return {"mean": rng.normal(0.0, 5.0, n_obs).astype(np.float32),
          "std": rng.uniform(0.05, 20.0, n_obs).astype(np.float32)}


def _policy(kind, hidden, activation="tanh", seed=0, final_gain=30.0, flax_init=False, n_obs=N_OBS, n=None):
  """Random policy params (Policy.init when flax_init, else numpy Gaussians with the same layout, which skips the
  init's XLA compile); the final layer is scaled up so logits/means are O(1) rather than O(0.01). n: the gaussian
  head's outputs (default 3; 6 with the attitude residual)."""
  pol = Policy(kind, 6 if kind == "discrete" else (n or 3), hidden=hidden, activation=activation)
  rng = np.random.default_rng(seed)
  if flax_init:
    params = jax.tree_util.tree_map(np.asarray, jax.jit(pol.init, static_argnums=1)(jax.random.PRNGKey(seed), n_obs))
  else:
    sizes = (n_obs,) + tuple(hidden) + (pol.n,)
    params = {"net": {f"dense_{i}": {"kernel": (rng.standard_normal((a, b)) / np.sqrt(a)).astype(np.float32),
                                     "bias": (0.1 * rng.standard_normal(b)).astype(np.float32)}
                      for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:]))}}
    params["net"][f"dense_{len(hidden)}"]["kernel"] *= 0.01
    if kind == "gaussian":
      params["log_std"] = np.full((pol.n,), -0.5, np.float32)
  last = params["net"][f"dense_{len(hidden)}"]
  last["kernel"] = last["kernel"] * final_gain
  last["bias"] = rng.normal(0, 0.1, pol.n).astype(np.float32)
  return pol, params


def _run_onnx(path, obs):
  sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
  return dict(zip([o.name for o in sess.get_outputs()], sess.run(None, {"obs": obs})))


@pytest.mark.parametrize("hidden", [(16, 16), (256, 256, 256)])
@pytest.mark.parametrize("kind", ["discrete", "gaussian"])
def test_export_parity_and_dynamic_batch(tmp_path, kind, hidden):
  pol, params = _policy(kind, hidden, flax_init=True)
  norm = _normalizer()
  path = str(tmp_path / "policy.onnx")
  res = ex.export_onnx(path, pol, params, norm, SPEEDS, metadata={"vehicle": "drone", "variant": "RC"},
                       latency_calls=200)
  assert res["path"] == path and os.path.exists(path) and not os.path.exists(path + ".tmp")
  assert res["max_abs_diff"] <= 1e-5 and res["argmax_equal"] and res["argmax_near_ties"] == 0
  assert res["opset"] <= 17 and res["latency_us_per_decision"] > 0

  model = onnx.load(path)
  assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) <= 17
  assert model.ir_version == 8
  assert [d.dim_param for d in model.graph.input[0].type.tensor_type.shape.dim] == ["B", ""]
  props = {p.key: p.value for p in model.metadata_props}
  assert props["vehicle"] == "drone" and props["variant"] == "RC" and props["kind"] == kind
  assert json.loads(props["speeds"]) == SPEEDS.tolist() and json.loads(props["clip"]) == 10.0

  fn = jax.jit(ex.jax_policy_fn(pol, params, norm, SPEEDS))
  main = "logits" if kind == "discrete" else "mean"
  rng = np.random.default_rng(7)
  for b in (1, 37):
    obs = (norm["mean"] + norm["std"] * 3 * rng.standard_normal((b, N_OBS))).astype(np.float32)
    got, ref = _run_onnx(path, obs), {k: np.asarray(v) for k, v in fn(obs).items()}
    assert sorted(got) == sorted(ref)
    assert got[main].shape == (b, pol.n) and got["setpoint"].shape == (b, 3)
    assert np.max(np.abs(got[main] - ref[main])) <= 1e-5
    assert np.max(np.abs(got["setpoint"] - ref["setpoint"])) <= 1e-5
    if kind == "discrete":
      assert got["action"].dtype == np.int64 and got["action"].shape == (b,)
      np.testing.assert_array_equal(got["action"], ref["action"])
      np.testing.assert_array_equal(got["action"], np.argmax(ref["logits"], -1))
      np.testing.assert_allclose(got["setpoint"], DIRECTIONS[got["action"]] * SPEEDS)
    else:
      np.testing.assert_allclose(got["setpoint"], np.tanh(ref["mean"]) * SPEEDS, atol=1e-6)


@pytest.mark.parametrize("activation", ["relu", "elu", "swish"])
def test_export_other_activations(tmp_path, activation):
  pol, params = _policy("discrete", (32, 32), activation)
  res = ex.export_onnx(str(tmp_path / "p.onnx"), pol, params, _normalizer(), SPEEDS, latency_calls=0)
  assert res["max_abs_diff"] <= 1e-5 and res["argmax_equal"] and res["latency_us_per_decision"] is None


def test_normalisation_matches_brax_running_statistics(tmp_path):
  """The folded normalisation is Brax's normalize (x - mean) / std followed by the clip; a RunningStatisticsState
  is accepted as the normaliser."""
  from brax.training.acme import running_statistics as rs

  rng = np.random.default_rng(3)
  data = (rng.normal(0, 1, (500, N_OBS)) * rng.uniform(0.1, 30, N_OBS) + rng.normal(0, 10, N_OBS))
  state = rs.update(rs.init_state(jax.numpy.zeros((N_OBS,))), jax.numpy.asarray(data, jax.numpy.float32))
  obs = np.concatenate([data[:50], data[:5] * 100]).astype(np.float32)
  for clip in (10.0, None):
    ref = rs.normalize(obs, state, max_abs_value=clip)
    np.testing.assert_array_equal(np.asarray(ex.normalize_obs(obs, state.mean, state.std, clip)), np.asarray(ref))
  pol, params = _policy("gaussian", (16, 16))
  res = ex.export_onnx(str(tmp_path / "p.onnx"), pol, params, state, SPEEDS, clip=5.0, latency_calls=0)
  assert res["max_abs_diff"] <= 1e-5


def test_parity_failure_raises_and_writes_nothing(tmp_path):
  pol, params = _policy("discrete", (16, 16))
  norm = _normalizer()
  path = str(tmp_path / "p.onnx")
  ex.export_onnx(path, pol, params, norm, SPEEDS, latency_calls=0)
  _, other = _policy("discrete", (16, 16), seed=5)
  with pytest.raises(ValueError, match="parity failed") as e:
    ex.check_parity(path, ex.jax_policy_fn(pol, other, norm, SPEEDS), ex.parity_obs(norm, 64))
  assert "\n" not in str(e.value)
  with pytest.raises(ValueError, match="parity failed"):  # same net, different normaliser folded in
    ex.check_parity(path, ex.jax_policy_fn(pol, params, _normalizer(seed=9), SPEEDS), ex.parity_obs(norm, 64))


def test_parity_tolerance_scales_with_output_size(tmp_path):
  """onnxruntime and XLA differ by ~5e-7 relative, so |logits| ~ 50 is checked to atol + rtol * 50, not 1e-5."""
  pol, params = _policy("discrete", (256, 256, 256), final_gain=3000.0)
  norm = _normalizer()
  res = ex.export_onnx(str(tmp_path / "p.onnx"), pol, params, norm, SPEEDS, latency_calls=0)
  assert res["max_abs_diff"] <= res["tol"] and res["tol"] > 2e-4 and res["argmax_equal"]
  fn = ex.jax_policy_fn(pol, params, norm, SPEEDS)
  assert ex.check_parity(res["path"], fn, ex.parity_obs(norm, 64), rtol=1e-6)["max_abs_diff"] < 1e-4
  with pytest.raises(ValueError, match="parity failed"):  # a bare 1e-6 abs check is below the rounding noise
    ex.check_parity(res["path"], fn, ex.parity_obs(norm, 64), atol=1e-6, rtol=0.0)


def test_bad_inputs_rejected(tmp_path):
  pol, params = _policy("discrete", (16, 16))
  norm = _normalizer()
  p = str(tmp_path / "p.onnx")
  with pytest.raises(ValueError, match="hidden"):
    ex.export_onnx(p, Policy("discrete", 6, hidden=(32, 16)), params, norm, SPEEDS)
  with pytest.raises(ValueError, match="n=6"):
    ex.export_onnx(p, Policy("discrete", 4, hidden=(16, 16)), params, norm, SPEEDS)
  with pytest.raises(ValueError, match="speeds"):
    ex.export_onnx(p, pol, params, norm, [1.0, 2.0])
  with pytest.raises(ValueError, match="std > 0"):
    ex.export_onnx(p, pol, params, {"mean": norm["mean"], "std": 0 * norm["std"]}, SPEEDS)
  with pytest.raises(ValueError, match="obs dims"):
    ex.export_onnx(p, pol, params, _normalizer(n_obs=N_OBS + 1), SPEEDS)
  with pytest.raises(ValueError, match="opset"):
    ex.export_onnx(p, pol, params, norm, SPEEDS, opset=18)
  with pytest.raises(ValueError, match="clashes"):
    ex.export_onnx(p, pol, params, norm, SPEEDS, metadata={"kind": "gaussian"})
  assert not os.listdir(tmp_path)


@pytest.mark.parametrize("kind", ["discrete", "gaussian"])
def test_save_load_round_trip(tmp_path, kind):
  pol, params = _policy(kind, (32, 16))
  norm = _normalizer()
  run = str(tmp_path / "run")
  ex.save_policy(run, pol, params, norm, SPEEDS, 7.5)
  assert sorted(os.listdir(run)) == ["policy.msgpack", "policy_config.json"]
  with open(os.path.join(run, "policy_config.json")) as f:
    cfg = json.load(f)
  assert cfg == {"kind": kind, "n": pol.n, "hidden": [32, 16], "activation": "tanh", "speeds": SPEEDS.tolist(),
                 "clip": 7.5, "n_obs": N_OBS}

  pol2, params2, norm2, speeds2, clip2 = ex.load_policy(run)
  assert pol2 == pol and clip2 == 7.5
  np.testing.assert_array_equal(speeds2, SPEEDS)
  for k in ("mean", "std"):
    np.testing.assert_array_equal(norm2[k], norm[k])
  assert jax.tree_util.tree_structure(params2) == jax.tree_util.tree_structure(params)
  jax.tree_util.tree_map(np.testing.assert_array_equal, params2, params)

  obs = ex.parity_obs(norm, 100)
  ref = jax.jit(ex.jax_policy_fn(pol, params, norm, SPEEDS, 7.5))(obs)
  got = jax.jit(ex.load_jax_policy(run))(obs)
  jax.tree_util.tree_map(np.testing.assert_array_equal, got, ref)
  # ... and the exported graph of the loaded policy agrees with it.
  res = ex.export_onnx(str(tmp_path / "p.onnx"), *ex.load_policy(run)[:4], clip=clip2, latency_calls=0)
  assert res["max_abs_diff"] <= 1e-5 and res["argmax_equal"]


def test_attitude_policy_saves_loads_and_exports_with_parity(tmp_path):
  """A policy of 6 outputs (EnvConfig.override_attitude): velocity [3] m/s and acceleration residual [3] m/s^2, each
  scaled by its entry of the 6 speeds; save/load, ONNX parity, and a scale count that does not fit is one line."""
  pol, params = _policy("gaussian", (32, 16), n=6)
  norm = _normalizer()
  scales = np.concatenate([SPEEDS, [3.0, 2.5, 1.0]]).astype(np.float32)
  run = str(tmp_path / "run")
  ex.save_policy(run, pol, params, norm, scales, 10.0)
  pol2, params2, norm2, scales2, _ = ex.load_policy(run)
  assert pol2 == pol and pol2.n == 6
  np.testing.assert_array_equal(scales2, scales)
  res = ex.export_onnx(str(tmp_path / "p.onnx"), pol2, params2, norm2, scales2, latency_calls=0)
  assert res["max_abs_diff"] <= 1e-5
  obs = ex.parity_obs(norm, 9)
  got = _run_onnx(str(tmp_path / "p.onnx"), obs)
  ref = jax.jit(ex.load_jax_policy(run))(obs)
  assert got["setpoint"].shape == (len(obs), 6)
  np.testing.assert_allclose(got["setpoint"], np.tanh(np.asarray(ref["mean"])) * scales, atol=1e-5)
  with pytest.raises(ValueError, match="3 speeds for a gaussian policy of 6 outputs"):
    ex.save_policy(str(tmp_path / "bad"), pol, params, norm, SPEEDS)
  with pytest.raises(ValueError, match="6 speeds for a discrete policy"):
    ex.export_onnx(str(tmp_path / "d.onnx"), *_policy("discrete", (16, 16)), norm, scales)


@pytest.mark.parametrize("layout", obs_lib.LAYOUTS)
def test_every_observation_layout_round_trips_and_exports_with_parity(tmp_path, layout):
  """A policy of each observation layout (the trainer's proximity ring of 8 sectors): policy_config.json records the
  layout, load_obs_layout reads it back, the ONNX graph (the layout in its metadata, as the runner writes it) agrees
  with the JAX policy; a layout whose size is not the policy's input is a clear error."""
  desc = obs_lib.describe(layout, 8)
  n_obs = obs_lib.size(layout, 8)
  pol, params = _policy("gaussian", (32, 16), n_obs=n_obs)
  norm = _normalizer(n_obs=n_obs)
  run = str(tmp_path / "run")
  ex.save_policy(run, pol, params, norm, SPEEDS, 10.0, obs_layout=desc)
  assert ex.load_obs_layout(run) == desc
  res = ex.export_onnx(str(tmp_path / "p.onnx"), *ex.load_policy(run)[:4], clip=10.0, latency_calls=0,
                       metadata={"obs_layout": desc})
  assert res["n_obs"] == n_obs and res["max_abs_diff"] <= 1e-5
  meta = {p.key: p.value for p in onnx.load(str(tmp_path / "p.onnx")).metadata_props}
  assert json.loads(meta["obs_layout"]) == desc
  other = next(x for x in obs_lib.LAYOUTS if obs_lib.size(x, 8) != n_obs)
  with pytest.raises(ValueError, match=f"has {obs_lib.size(other, 8)} inputs, the policy takes {n_obs}"):
    ex.save_policy(str(tmp_path / "bad"), pol, params, norm, SPEEDS, 10.0, obs_layout=obs_lib.describe(other, 8))


def test_corrupt_or_missing_files(tmp_path):
  pol, params = _policy("gaussian", (16, 16))
  run = str(tmp_path / "run")
  ex.save_policy(run, pol, params, _normalizer(), SPEEDS, 10.0)
  blob_path, cfg_path = os.path.join(run, "policy.msgpack"), os.path.join(run, "policy_config.json")
  with open(blob_path, "rb") as f:
    blob = f.read()
  with open(cfg_path) as f:
    cfg = f.read()

  def expect(fname):
    with pytest.raises(ValueError, match=fname) as e:
      ex.load_jax_policy(run)
    assert "\n" not in str(e.value)

  for bad in (blob[: len(blob) // 2], b"\x00garbage" * 10, b""):
    with open(blob_path, "wb") as f:
      f.write(bad)
    expect("policy.msgpack")
  os.remove(blob_path)
  expect("policy.msgpack")

  # weights that do not fit the config (other hidden sizes)
  ex.save_policy(str(tmp_path / "other"), *_policy("gaussian", (8, 8)), _normalizer(), SPEEDS, 10.0)
  os.replace(str(tmp_path / "other" / "policy.msgpack"), blob_path)
  expect("policy.msgpack")

  for bad in ("{not json", json.dumps({"kind": "gaussian"}),
              cfg.replace('"gaussian"', '"beta"'), cfg.replace('"hidden": [', '"hidden": "16", "x": ['), cfg.replace('"speeds": [', '"speeds": [1.0, ')):
    with open(cfg_path, "w") as f:
      f.write(bad)
    expect("policy_config.json")
  os.remove(cfg_path)
  expect("policy_config.json")
