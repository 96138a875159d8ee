"""The per-lane covariance kernel (specguard_jax/ekf_lanes.py, `fused_ekf="lanes"`): its body equals ekf._cov_tick,
its Mosaic GPU kernel lowers for CUDA, its packed layouts of P and of the other inputs, and ekf_step / the env route a
vmapped batch through it with P kept packed (compiled, checked and timed on a GPU: the gpu-marked test here,
bench/ekf_lanes.py, BENCHMARKS.md sessions 35-36)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes
from test_ekf_kernel import DT, _batch, _check, _rollouts, _xla


def _cfg(vehicle):
  return ekf_lib.EKFConfig.drone() if vehicle == "drone" else ekf_lib.EKFConfig.rover()


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
@pytest.mark.parametrize("stale", [(), ("gps",)])
def test_lane_body_equals_xla_tick(vehicle, stale):
  cfg = _cfg(vehicle)
  args = _batch(cfg, 256, seed=5)
  # eager: ~10^4 small ops, quicker op by op on the CPU than one XLA compile of the straight-line code
  out = ekf_lanes.cov_tick_xla(ekf_lib._cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg), *args)
  _check(_xla(cfg, stale)(*args), out)


def _raw_batch(cfg, n, seed):
  """n random vehicles' inputs to `ekf_lanes.prep_tick`: P, the nominal state (some below the flow's minimum height),
  an IMU sample, observation rows near the state's (some far outside their gates), fresh flags, resets due."""
  rng = np.random.default_rng(seed)
  P = _batch(cfg, n, seed)[0]
  f = lambda *shape, s=1.0: (rng.normal(size=(n,) + shape) * s).astype(np.float32)
  quat = f(4)
  quat /= np.linalg.norm(quat, axis=1, keepdims=True)
  pos = np.c_[f(2, s=50.0), rng.uniform(0.0, 20.0, (n, 1))].astype(np.float32)
  vel = f(3, s=3.0)
  gyro, accel = f(3, s=0.5), f(3) + np.float32([0.0, 0.0, 9.81])
  yaw = np.arctan2(2 * (quat[:, 0] * quat[:, 3] + quat[:, 1] * quat[:, 2]), 1 - 2 * (quat[:, 2] ** 2 + quat[:, 3] ** 2))
  z = np.c_[pos + f(3, s=2.0), vel + f(3), pos[:, 2:] + f(1, s=2.0), yaw[:, None] + f(1, s=0.3), f(2),
            f(1, s=3.0), np.zeros((n, 2))].astype(np.float32)
  args = (P, quat, vel, pos, f(3, s=0.01), f(3, s=0.1), gyro, accel, z, rng.random((n, 13)) < 0.8,
          rng.random((n, 3)) < 0.5)
  return [jnp.asarray(x) for x in args]


@pytest.mark.parametrize("vehicle,stale", [("drone", ()), ("drone", ("gps",)), ("rover", ()), ("rover", ("gps",))])
def test_prep_body_equals_the_xla_tick(vehicle, stale):
  """The tick with its inputs prepared per lane (`prep_tick`'s body: the prediction, H, the innovations, then the
  covariance work) against ekf._tick_prep_xla (what ekf_step
  computes in XLA), eager on the CPU."""
  cfg = _cfg(vehicle)
  args = _raw_batch(cfg, 256, seed=6)
  out = ekf_lanes.prep_tick_xla(ekf_lib._cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg), *args,
                                flow_min_height=float(cfg.flow_min_height))
  ref = jax.jit(jax.vmap(lambda *x: ekf_lib._tick_prep_xla(cfg, DT, stale, *x)))(*args)
  _check(ref[:4], out[:4])
  for r, o in zip(ref[4:], out[4:]):     # innovations before the gates, the predicted pos, vel, quat
    np.testing.assert_allclose(np.asarray(o), np.asarray(r), rtol=1e-5, atol=1e-5)


def test_lane_body_catches_a_changed_tick():
  """The comparison above can fail: a lane body given another tick length differs from the reference."""
  cfg = _cfg("drone")
  args = _batch(cfg, 64, seed=5)
  out = ekf_lanes.cov_tick_xla(ekf_lib._cov_spec(cfg, 2 * DT, ()), ekf_lanes.resets_of(cfg), *args)
  with pytest.raises(AssertionError):
    _check(_xla(cfg, ())(*args), out)


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_kernel_lowers_for_cuda(vehicle):
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  cfg = _cfg(vehicle)
  args = _batch(cfg, 256, seed=0)
  spec = ekf_lib._cov_spec(cfg, DT, ())
  fn = jax.jit(lambda *x: ekf_lanes.cov_tick(spec, ekf_lanes.resets_of(cfg), *x))
  text = fn.trace(*args).lower(lowering_platforms=("cuda",)).as_text()
  assert "mosaic_gpu" in text


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_prep_kernel_lowers_for_cuda(vehicle):
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  cfg = _cfg(vehicle)
  args = _raw_batch(cfg, 256, seed=0)
  args[0] = ekf_lib.pack_p(args[0])
  spec = ekf_lib._cov_spec(cfg, DT, ("gps",))
  fn = jax.jit(lambda *x: ekf_lanes.prep_tick(spec, ekf_lanes.resets_of(cfg), *x,
                                              flow_min_height=float(cfg.flow_min_height)))
  text = fn.trace(*args).lower(lowering_platforms=("cuda",)).as_text()
  assert "mosaic_gpu" in text


def test_kernel_takes_and_returns_either_layout_of_P():
  """cov_tick's P packed [B, 121] (the env's layout with this kernel), square [B, 15, 15] or padded [B, 16, 16],
  returned in the same layout; checked through the kernel's plain-JAX body, which shares the wrapper (`_packed_io`).
  Mosaic GPU's CPU interpreter cannot run the kernel's shared-memory views (ref reshapes): its TMA plumbing is run on
  the GPU only (`test_kernel_on_gpu_equals_xla_tick`, bench/ekf_lanes.py)."""
  cfg = _cfg("rover")
  args = _batch(cfg, 40, seed=2)
  spec = ekf_lib._cov_spec(cfg, DT, ())
  square = ekf_lanes.cov_tick_xla(spec, ekf_lanes.resets_of(cfg), *args)
  packed = ekf_lanes.cov_tick_xla(spec, ekf_lanes.resets_of(cfg), ekf_lib.pack_p(args[0]), *args[1:])
  assert square[0].shape == (40, 15, 15) and packed[0].shape == (40, ekf_lib.N_PACKED)
  np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(packed[0])), np.asarray(square[0]))
  np.testing.assert_array_equal(np.asarray(packed[0][:, -1]), 0.0)
  for x, y in zip(square[1:], packed[1:]):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  padded = ekf_lanes.cov_tick_xla(spec, ekf_lanes.resets_of(cfg), ekf_lib.in_layout(args[0], "padded"), *args[1:])
  assert padded[0].shape == (40, 16, 16) and not np.any(np.asarray(padded[0])[:, 15])
  np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(padded[0])), np.asarray(square[0]))


def test_packed_layout_helpers_equal_the_square_ones():
  """What the env and the reconstruction do to P outside the tick (reset_block, add_to_diag, p_diag, p_entry,
  normalized-innovation variances), on P packed, equals the same on P square."""
  rng = np.random.default_rng(0)
  M = rng.normal(size=(15, 15)).astype(np.float32)
  P = jnp.asarray(M @ M.T + np.eye(15, dtype=np.float32))
  Pk = ekf_lib.pack_p(P)
  assert ekf_lib.p_layout(Pk) == "packed" and ekf_lib.p_layout(P) == "square"
  np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(Pk)), np.asarray(P))
  for do in (True, False):
    np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(ekf_lib.reset_block(Pk, [9, 10, 11], 0.25, do))),
                                  np.asarray(ekf_lib.reset_block(P, [9, 10, 11], 0.25, do)))
  d = jnp.arange(15, dtype=jnp.float32)
  np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(ekf_lib.add_to_diag(Pk, d))),
                                np.asarray(ekf_lib.add_to_diag(P, d)))
  np.testing.assert_array_equal(np.asarray(ekf_lib.p_diag(Pk)), np.diag(np.asarray(P)))
  assert float(ekf_lib.p_entry(Pk, 7, 2)) == float(P[2, 7])
  H = jnp.asarray(rng.normal(size=(13, 15)).astype(np.float32))
  np.testing.assert_allclose(np.asarray(ekf_lib._hph(H, Pk, 11)), np.asarray(ekf_lib._hph(H, P, 11)), rtol=1e-6)
  with pytest.raises(ValueError, match=r"P of shape \(14,\) is in none of the layouts"):
    ekf_lib.p_layout(jnp.zeros(14))


def test_an_outer_vmap_joins_the_kernels_batch(monkeypatch):
  """Under a second vmap (a sweep's members) the kernel still gets one flat batch: [members x B] vehicles, the
  results split back per member (the kernel stood in for by its plain-JAX body on the CPU)."""
  cfg = _cfg("drone")
  spec, resets = ekf_lib._cov_spec(cfg, DT, ()), ekf_lanes.resets_of(cfg)
  seen = []

  def fake(spec, resets, P, *args, stage, in_place):
    seen.append(P.shape)
    return ekf_lanes.cov_tick_xla(spec, resets, P, *args, stage=stage)

  monkeypatch.setattr(ekf_lanes, "_kernel", fake)
  members = [_batch(cfg, 16, seed=s) for s in (1, 2, 3)]
  stacked = [jnp.stack(x) for x in zip(*members)]
  stacked[0] = ekf_lib.pack_p(stacked[0])
  out = jax.vmap(lambda *a: ekf_lanes.cov_tick(spec, resets, *a))(*stacked)
  assert seen[-1] == (48, ekf_lib.N_PACKED)    # (custom_vmap first traces the unbatched call: [16, 121])
  for m, args in enumerate(members):
    _check(ekf_lanes.cov_tick_xla(spec, resets, *args), (ekf_lib.as_square(out[0][m]),) + tuple(x[m] for x in out[1:]))


def test_aux_block_places_inputs_at_the_layout_offsets():
  """pack_aux: each input in its `Layout` row of the vehicle-minor block the kernel reads."""
  cfg = _cfg("drone")
  P, A, B, H, innov, enable, due = _batch(cfg, 7, seed=3)
  spec = ekf_lib._cov_spec(cfg, DT, ())
  lay = ekf_lanes.Layout(spec)
  aux = np.asarray(ekf_lanes.pack_aux(spec, A, B, H, innov, enable, due))
  assert aux.shape == (lay.n_aux, 7)
  np.testing.assert_array_equal(aux[lay.B:lay.B + 9].T, np.asarray(B).reshape(7, 9))
  i, c = spec.h_entries()[3]
  np.testing.assert_array_equal(aux[lay.H + 3], np.asarray(H)[:, i, c])
  np.testing.assert_array_equal(aux[lay.en:lay.en + 13].T, np.asarray(enable, np.float32))
  np.testing.assert_array_equal(aux[lay.due:lay.due + 3].T, np.asarray(due, np.float32))


@pytest.mark.gpu
@pytest.mark.skipif(jax.default_backend() != "gpu", reason="the Mosaic GPU kernel needs an NVIDIA Hopper GPU")
@pytest.mark.parametrize("stale", [(), ("gps",)])
def test_kernel_on_gpu_equals_xla_tick(stale):
  """The compiled kernel (300 vehicles: 3 programs, the last one part padding) against the reference."""
  cfg = _cfg("drone")
  args = _batch(cfg, 300, seed=4)
  out = ekf_lanes.cov_tick(ekf_lib._cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg), *args)
  _check(_xla(cfg, stale)(*args), out)


@pytest.fixture
def lanes_on_cpu(monkeypatch):
  """ekf_lanes.cov_tick replaced by the XLA reference for the batch (the kernel itself needs a GPU): what is tested
  is the routing around it. Returns the list of P shapes it was called with; `calls.cfgs` are the filters'
  EKFConfigs it may be called for (the one whose spec and resets match the call's is used)."""
  calls = []

  def fake(spec, resets, P, A, B, H, innov, enable, due, stage="full"):
    calls.append(P.shape)
    stale = () if spec.used[0] else ("gps",)
    cfg = next(c for c in calls.cfgs
               if ekf_lib._cov_spec(c, spec.dt, stale) == spec and ekf_lanes.resets_of(c) == resets)
    noise, gate = ekf_lib._noise_and_gates(cfg)
    return jax.vmap(lambda *x: ekf_lib._cov_tick(cfg, *x[:3], spec.dt, *x[3:5], jnp.asarray(noise) ** 2,
                                                 jnp.asarray(gate), *x[5:], stale, unrolled=True))(
        P, A, B, H, innov, enable, due)      # P packed in, packed out (`_cov_tick` keeps P's layout)

  def fake_prep(spec, resets, P, *args, flow_min_height):
    calls.append(P.shape)
    stale = () if spec.used[0] else ("gps",)
    cfg = next(c for c in calls.cfgs
               if ekf_lib._cov_spec(c, spec.dt, stale) == spec and ekf_lanes.resets_of(c) == resets)
    return jax.vmap(lambda *x: ekf_lib._tick_prep_xla(cfg, spec.dt, stale, *x))(P, *args)

  calls = type("Calls", (list,), {})()
  calls.cfgs = [_cfg("drone")]
  monkeypatch.setattr(ekf_lanes, "cov_tick", fake)
  monkeypatch.setattr(ekf_lanes, "prep_tick", fake_prep)
  return calls


def test_env_routes_the_batch_through_the_lanes_kernel(lanes_on_cpu):
  """A drone env with fused_ekf="lanes" (the kernel stood in for on the CPU) keeps P packed [121] from reset on,
  hands the kernel the whole vmapped batch, and steps as the XLA env does: 6 steps of 3 vehicles."""
  import envs
  ref_env, env = envs.make("drone"), envs.make("drone")
  env._fused_ekf = env._fused_shadow = "lanes"     # (envs.make(fused_ekf="lanes") would need a Hopper GPU)
  (_, ref), (_, out) = _rollouts(ref_env, env, 6)
  assert lanes_on_cpu and all(shape == (3, ekf_lib.N_PACKED) for shape in lanes_on_cpu)
  assert out.info["sim"]["ekf"].P.shape == (6, 3, ekf_lib.N_PACKED)
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(np.asarray(ekf_lib.as_square(out.info["sim"]["ekf"].P)),
                             np.asarray(ref.info["sim"]["ekf"].P), rtol=1e-4, atol=1e-8)


def test_phase2_env_with_the_lanes_kernel_follows_the_xla_env(lanes_on_cpu):
  """The whole phase-2 env (autopilot EKF and the reconstruction's shadow filter on the kernel, stood in for on the
  CPU; both P packed from reset on) against the XLA env: 8 closed-loop steps (40 ticks) of 3 vehicles, no attack
  (what the reconstruction does to P under attack, on packed P: test_packed_layout_helpers_equal_the_square_ones)."""
  import envs
  kw = dict(control_mode="reactive", detector="residual", reconstruction=True)
  ref_env, env = envs.make("drone", **kw), envs.make("drone", **kw)
  env._fused_ekf = env._fused_shadow = "lanes"
  lanes_on_cpu.cfgs.append(env.recon_cfg.ekf_cfg())
  (_, ref), (s0, out) = _rollouts(ref_env, env, 8)
  sim = s0.info["sim"]
  assert sim["ekf"].P.shape == (3, ekf_lib.N_PACKED) and sim["recon"].shadow.P.shape == (3, ekf_lib.N_PACKED)
  assert len(lanes_on_cpu) == 2     # the autopilot's and the shadow's EKF (on the CPU every tick is the full one)
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), rtol=1e-3, atol=1e-3)
  np.testing.assert_allclose(np.asarray(out.reward), np.asarray(ref.reward), rtol=1e-3, atol=1e-4)
  for get in (lambda o: o.info["sim"]["ekf"], lambda o: o.info["sim"]["recon"].shadow):
    np.testing.assert_allclose(np.asarray(ekf_lib.as_square(get(out).P)), np.asarray(get(ref).P), rtol=1e-2,
                               atol=1e-6)


def test_fused_ekf_names_a_kernel():
  from envs.base import ekf_kernel_kind
  assert [ekf_kernel_kind(v) for v in (False, None, "", True, "triton", "lanes")] == ["", "", "", "triton",
                                                                                       "triton", "lanes"]
  with pytest.raises(ValueError, match="fused_ekf must be false, true or one of triton, lanes; got 'cuda'"):
    ekf_kernel_kind("cuda")


def test_train_defaults_to_the_lanes_kernel_on_a_hopper_gpu(monkeypatch):
  """train.py's GPU defaults pick fused_ekf="lanes" on a Hopper or newer GPU (faked here) with jax >= 0.11, XLA on
  older GPUs, with jax 0.10 and on the CPU; --fused-ekf xla turns the kernel off."""
  import train as train_cli
  from specguard_jax.ppo import runner

  class Dev:
    device_kind, compute_capability = "NVIDIA H200", "9.0"

  assert runner.default_sizes("gpu")["env"].fused_ekf is False          # this CPU machine
  assert "env" not in runner.default_sizes("cpu")
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(jax, "devices", lambda *a: [Dev()])
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 11))
  assert runner.default_sizes("gpu")["env"].fused_ekf == "lanes"
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 10))    # lowered there, never run on a GPU: opt-in
  assert runner.default_sizes("gpu")["env"].fused_ekf is False
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 11))
  Dev.compute_capability = "8.0"
  assert runner.default_sizes("gpu")["env"].fused_ekf is False
  monkeypatch.undo()
  assert train_cli.build_config(train_cli.parse_args(["--fused-ekf", "xla"])).env.fused_ekf is False
  assert train_cli.build_config(train_cli.parse_args([])).env.fused_ekf is False          # the CPU's default


def test_lanes_kernel_needs_a_hopper_gpu(monkeypatch):
  """A clear one-line error before any compile: no GPU, or a GPU older than Hopper (faked here on the CPU)."""
  from envs.base import check_ekf_kernel
  with pytest.raises(ValueError, match="fused_ekf needs a GPU"):
    check_ekf_kernel("lanes")

  class Ampere:
    device_kind, compute_capability = "NVIDIA A100-SXM4-80GB", "8.0"

  class Hopper:
    device_kind, compute_capability = "NVIDIA H200", "9.0"

  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(jax, "devices", lambda *a: [Ampere()])
  with pytest.raises(ValueError, match=r"'lanes' needs an NVIDIA Hopper GPU .* is 8.0: use fused_ekf='triton'"):
    check_ekf_kernel("lanes")
  assert check_ekf_kernel("triton") == "triton"
  monkeypatch.setattr(jax, "devices", lambda *a: [Hopper()])
  assert check_ekf_kernel(True) == "triton" and check_ekf_kernel("lanes") == "lanes"


def test_a_run_trained_with_the_kernel_evaluates_on_the_cpu(tmp_path):
  """A GPU run's config.json with fused_ekf="lanes" (train.py's default on Hopper GPUs) loads for evaluation on a
  machine without the kernel (the choice is dropped: evaluation builds XLA envs); resuming it here is a one-line
  error naming the kernel (its checkpointed env state holds P in the kernel's packed layout)."""
  import json
  from specguard_jax import controllers
  from specguard_jax.ppo import config, runner
  (tmp_path / "config.json").write_text(json.dumps(config.TrainConfig().with_env(fused_ekf="lanes").to_dict()))
  cfg = controllers.load_run_config(str(tmp_path))
  assert cfg.env.fused_ekf is False and cfg.vehicle == "drone"
  with pytest.raises(ValueError, match="fused_ekf needs a GPU"):
    runner.load_run_config(str(tmp_path))
