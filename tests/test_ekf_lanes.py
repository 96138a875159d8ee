"""The lanes EKF kernel (specguard_jax/ekf_lanes.py, `ekf_kernel="lanes"`): its body equals the XLA filter's tick,
its Mosaic GPU kernel lowers for CUDA, P's packed layout, the choice of kernel (`resolve_ekf_kernel`), and the env
routes a vmapped batch through it with P kept packed (compiled and checked on a GPU: the gpu-marked test here)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes

DT = 0.02


def _cfg(vehicle):
  return ekf_lib.EKFConfig.drone() if vehicle == "drone" else ekf_lib.EKFConfig.rover()


def _spd(n, seed):
  """[n, 15, 15] random symmetric positive definite covariances."""
  rng = np.random.default_rng(seed)
  L = rng.normal(size=(n, 15, 15)).astype(np.float32) * 0.3
  return np.einsum("bij,bkj->bik", L, L) + np.eye(15, dtype=np.float32) * 0.01


def _check(ref, out):
  """(P, dx, ratio, accept) of the kernel's arithmetic against the XLA reference's, P square."""
  P_r, dx_r, ratio_r, acc_r = [np.asarray(x) for x in ref]
  P, dx, ratio, acc = [np.asarray(x) for x in out]
  assert np.array_equal(acc, acc_r)
  assert 0 < acc.mean() < 1            # both accepted and rejected rows in the batch
  np.testing.assert_allclose(ratio, ratio_r, rtol=2e-5, atol=1e-7)
  # per vehicle, relative to the size of its own P / dx
  scale_P = np.max(np.abs(P_r), axis=(1, 2), keepdims=True)
  assert np.max(np.abs(P - P_r) / scale_P) < 2e-5
  scale_dx = np.max(np.abs(dx_r), axis=1, keepdims=True) + 1e-12
  assert np.max(np.abs(dx - dx_r) / scale_dx) < 1e-4     # GPU: fused multiply-adds round differently
  assert np.array_equal(P, np.swapaxes(P, 1, 2))      # exactly symmetric


def _rollouts(ref_env, env, steps: int):
  """Both envs' (reset states, stacked step states) over `steps` zero-action steps of the same 3 vehicles, jitted."""
  keys = jax.random.split(jax.random.PRNGKey(3), 3)

  def rollout(e):
    s0 = jax.vmap(e.reset)(keys)
    step = lambda s, _: (jax.vmap(e.step)(s, jnp.zeros((3, 3))),) * 2
    return s0, jax.lax.scan(step, s0, None, length=steps)[1]

  return jax.jit(lambda: rollout(ref_env))(), jax.jit(lambda: rollout(env))()


def _prep_xla(cfg, stale, args, dt=DT):
  return ekf_lanes.prep_tick_xla(ekf_lanes.cov_spec(cfg, dt, stale), ekf_lanes.resets_of(cfg), *args,
                                 flow_min_height=float(cfg.flow_min_height))


def _reference(cfg, stale, args):
  return jax.jit(jax.vmap(lambda *x: ekf_lanes.reference_tick(cfg, DT, stale, *x)))(*args)


def _raw_batch(cfg, n, seed):
  """n random vehicles' inputs to `ekf_lanes.prep_tick`: P, the nominal state (some below the flow's minimum height),
  an IMU sample, observation rows near the state's (some far outside their gates), fresh flags, resets due."""
  rng = np.random.default_rng(seed)
  P = _spd(n, seed)
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
  covariance work) against ekf_lanes.reference_tick (what ekf.ekf_step computes in XLA), eager on the CPU."""
  cfg = _cfg(vehicle)
  args = _raw_batch(cfg, 256, seed=6)
  out = ekf_lanes.prep_tick_xla(ekf_lanes.cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg), *args,
                                flow_min_height=float(cfg.flow_min_height))
  ref = jax.jit(jax.vmap(lambda *x: ekf_lanes.reference_tick(cfg, DT, stale, *x)))(*args)
  _check(ref[:4], out[:4])
  for r, o in zip(ref[4:], out[4:]):     # innovations before the gates, the predicted pos, vel, quat
    np.testing.assert_allclose(np.asarray(o), np.asarray(r), rtol=1e-5, atol=1e-5)


def test_lane_body_catches_a_changed_tick():
  """The comparison above can fail: a lane body given another tick length differs from the reference."""
  cfg = _cfg("drone")
  args = _raw_batch(cfg, 64, seed=5)
  with pytest.raises(AssertionError):
    _check(_reference(cfg, (), args)[:4], _prep_xla(cfg, (), args, dt=2 * DT)[:4])


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_prep_kernel_lowers_for_cuda(vehicle):
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  cfg = _cfg(vehicle)
  args = _raw_batch(cfg, 256, seed=0)
  args[0] = ekf_lib.pack_p(args[0])
  spec = ekf_lanes.cov_spec(cfg, DT, ("gps",))
  fn = jax.jit(lambda *x: ekf_lanes.prep_tick(spec, ekf_lanes.resets_of(cfg), *x,
                                              flow_min_height=float(cfg.flow_min_height)))
  text = fn.trace(*args).lower(lowering_platforms=("cuda",)).as_text()
  assert "mosaic_gpu" in text


def test_kernel_takes_and_returns_either_layout_of_P():
  """prep_tick's P packed [B, 121] (the env's layout with this kernel) or square [B, 15, 15], returned in the same
  layout; checked through the kernel's plain-JAX body, which shares the wrapper (`_packed_io`). Mosaic GPU's CPU
  interpreter cannot run the kernel's shared-memory views (ref reshapes): its TMA plumbing is run on the GPU only
  (`test_kernel_on_gpu_equals_xla_tick`)."""
  cfg = _cfg("rover")
  args = _raw_batch(cfg, 40, seed=2)
  square = _prep_xla(cfg, (), args)
  packed = _prep_xla(cfg, (), [ekf_lib.pack_p(args[0])] + args[1:])
  assert square[0].shape == (40, 15, 15) and packed[0].shape == (40, ekf_lib.N_PACKED)
  np.testing.assert_array_equal(np.asarray(ekf_lib.as_square(packed[0])), np.asarray(square[0]))
  np.testing.assert_array_equal(np.asarray(packed[0][:, -1]), 0.0)
  for x, y in zip(square[1:], packed[1:]):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


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


def _fake_lanes_call(seen):
  """ekf_lanes._lanes_call's stand-in on the CPU: the kernel's body on [B] vectors, rows in a dict (no TMA)."""
  def fake(P, aux, n_rows, n_out, body, in_place):
    seen.append(P.shape)
    mem, p_out = dict(enumerate(aux)), dict(enumerate(P.T))

    def p_store(i, j, v):
      p_out[ekf_lib.TRI_INDEX[(i, j)]] = v

    body(lambda i, j: P[:, ekf_lib.TRI_INDEX[(i, j)]], p_store, mem.__getitem__, mem.__setitem__)
    return (jnp.stack([p_out[k] for k in range(ekf_lib.N_PACKED)], axis=1),
            jnp.stack([jnp.broadcast_to(mem[k], (P.shape[0],)) for k in range(n_out)]))
  return fake


def test_an_outer_vmap_joins_the_kernels_batch(monkeypatch):
  """Under a second vmap (a sweep's members) the kernel still gets one flat batch: [members x B] vehicles, the
  results split back per member (the kernel call stood in for by its plain-JAX body on the CPU)."""
  cfg = _cfg("drone")
  spec, resets = ekf_lanes.cov_spec(cfg, DT, ()), ekf_lanes.resets_of(cfg)
  seen = []
  monkeypatch.setattr(ekf_lanes, "_lanes_call", _fake_lanes_call(seen))
  members = [_raw_batch(cfg, 16, seed=s) for s in (1, 2, 3)]
  stacked = [jnp.stack(x) for x in zip(*members)]
  stacked[0] = ekf_lib.pack_p(stacked[0])
  fmh = float(cfg.flow_min_height)
  # op by op (prep_tick's jit off too): compiled, the body's ~8,600 ops on [B] vectors take XLA over a minute; the
  # vmap still goes through the kernel call's custom_vmap rule
  with jax.disable_jit():
    out = jax.vmap(lambda *a: ekf_lanes.prep_tick(spec, resets, *a, flow_min_height=fmh))(*stacked)
  assert seen[-1] == (48, ekf_lib.N_PACKED)    # (custom_vmap first traces the unbatched call: [16, 121])
  # the reference on the members' vehicles side by side (one batch of 48), split back per member
  ref = _prep_xla(cfg, (), [jnp.concatenate(x) for x in zip(*members)])[:4]
  for m in range(len(members)):
    _check([x[16 * m:16 * (m + 1)] for x in ref], (ekf_lib.as_square(out[0][m]),) + tuple(x[m] for x in out[1:4]))


def test_aux_block_places_inputs_at_the_layout_offsets():
  """pack_prep: each input in its `PrepLayout` row of the vehicle-minor block the kernel reads."""
  cfg = _cfg("drone")
  args = _raw_batch(cfg, 7, seed=3)
  lay = ekf_lanes.PrepLayout()
  aux = np.asarray(ekf_lanes.pack_prep(*args[1:]))
  assert aux.shape == (lay.n_in, 7)
  np.testing.assert_array_equal(aux[lay.inp["vel"]:lay.inp["vel"] + 3].T, np.asarray(args[2]))
  np.testing.assert_array_equal(aux[lay.inp["z"]:lay.inp["z"] + 13].T, np.asarray(args[8]))
  np.testing.assert_array_equal(aux[lay.inp["en"]:lay.inp["en"] + 13].T, np.asarray(args[9], np.float32))
  np.testing.assert_array_equal(aux[lay.inp["due"]:lay.inp["due"] + 3].T, np.asarray(args[10], np.float32))


@pytest.mark.gpu
@pytest.mark.skipif(jax.default_backend() != "gpu", reason="the Mosaic GPU kernel needs an NVIDIA Hopper GPU")
@pytest.mark.parametrize("stale", [(), ("gps",)])
def test_kernel_on_gpu_equals_xla_tick(stale):
  """The compiled kernel (300 vehicles: 3 programs, the last one part padding) against the reference."""
  cfg = _cfg("drone")
  args = _raw_batch(cfg, 300, seed=4)
  out = ekf_lanes.prep_tick(ekf_lanes.cov_spec(cfg, DT, stale), ekf_lanes.resets_of(cfg), *args,
                            flow_min_height=float(cfg.flow_min_height))
  ref = _reference(cfg, stale, args)
  _check(ref[:4], out[:4])
  for r, o in zip(ref[4:], out[4:]):
    np.testing.assert_allclose(np.asarray(o), np.asarray(r), rtol=1e-5, atol=1e-5)


@pytest.fixture
def lanes_on_cpu(monkeypatch):
  """ekf_lanes.prep_tick replaced by the XLA reference for the batch (the kernel itself needs a GPU): what is tested
  is the routing around it. Returns the list of P shapes it was called with; `calls.cfgs` are the filters'
  EKFConfigs it may be called for (the one whose spec and resets match the call's is used)."""
  def fake_prep(spec, resets, P, *args, flow_min_height):
    calls.append(P.shape)
    stale = () if spec.used[0] else ("gps",)
    cfg = next(c for c in calls.cfgs
               if ekf_lanes.cov_spec(c, spec.dt, stale) == spec and ekf_lanes.resets_of(c) == resets)
    return jax.vmap(lambda *x: ekf_lanes.reference_tick(cfg, spec.dt, stale, *x))(P, *args)

  calls = type("Calls", (list,), {})()
  calls.cfgs = [_cfg("drone")]
  monkeypatch.setattr(ekf_lanes, "prep_tick", fake_prep)
  return calls


def test_phase2_env_with_the_lanes_kernel_follows_the_xla_env(lanes_on_cpu):
  """The whole phase-2 env (autopilot EKF and the reconstruction's shadow filter on the kernel, stood in for on the
  CPU) against the XLA env: both P kept packed [121] from reset on, the kernel handed the whole vmapped batch, 8
  closed-loop steps (40 ticks) of 3 vehicles, no attack (what the reconstruction does to P under attack, on packed P:
  test_packed_layout_helpers_equal_the_square_ones)."""
  import envs
  kw = dict(control_mode="reactive", detector="residual", reconstruction=True)
  ref_env, env = envs.make("drone", **kw), envs.make("drone", **kw)
  env._ekf_kernel = env._shadow_kernel = "lanes"
  lanes_on_cpu.cfgs.append(env.recon_cfg.ekf_cfg())
  (_, ref), (s0, out) = _rollouts(ref_env, env, 8)
  sim = s0.info["sim"]
  assert sim["ekf"].P.shape == (3, ekf_lib.N_PACKED) and sim["recon"].shadow.P.shape == (3, ekf_lib.N_PACKED)
  assert len(lanes_on_cpu) == 2     # the autopilot's and the shadow's EKF (on the CPU every tick is the full one)
  assert all(shape == (3, ekf_lib.N_PACKED) for shape in lanes_on_cpu)   # the whole batch in one call
  assert out.info["sim"]["ekf"].P.shape == (8, 3, ekf_lib.N_PACKED)     # kept packed through the steps
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), rtol=1e-3, atol=1e-3)
  np.testing.assert_allclose(np.asarray(out.reward), np.asarray(ref.reward), rtol=1e-3, atol=1e-4)
  for get in (lambda o: o.info["sim"]["ekf"], lambda o: o.info["sim"]["recon"].shadow):
    np.testing.assert_allclose(np.asarray(ekf_lib.as_square(get(out).P)), np.asarray(get(ref).P), rtol=1e-2,
                               atol=1e-6)


def test_resolve_ekf_kernel():
  """The one place the kernel is chosen: "xla" stays, "auto" is XLA on the CPU, an unknown name is a one-line error;
  ekf_lanes.ekf_step takes only a resolved kernel."""
  assert ekf_lanes.resolve_ekf_kernel("xla") == "xla" and ekf_lanes.resolve_ekf_kernel("auto") == "xla"
  for bad in ("cuda", True, False, "triton"):
    with pytest.raises(ValueError, match="ekf_kernel must be one of auto, xla, lanes; got"):
      ekf_lanes.resolve_ekf_kernel(bad)
  with pytest.raises(ValueError, match="kernel must be 'xla' or 'lanes'"):
    ekf_lanes.ekf_step(_cfg("drone"), None, None, DT, kernel="auto")


def test_auto_picks_the_lanes_kernel_on_a_hopper_gpu(monkeypatch):
  """"auto" is the lanes kernel on a Hopper or newer GPU (faked here) with jax >= 0.11, XLA on older GPUs, with jax
  0.10 and on the CPU; train.py's default is "auto", --ekf-kernel xla turns the kernel off."""
  from specguard_jax.cli import train as train_cli

  class Dev:
    device_kind, compute_capability = "NVIDIA H200", "9.0"

  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(jax, "devices", lambda *a: [Dev()])
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 11))
  assert ekf_lanes.resolve_ekf_kernel("auto") == "lanes"
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 10))    # lowered there, never run on a GPU: opt-in
  assert ekf_lanes.resolve_ekf_kernel("auto") == "xla" and ekf_lanes.resolve_ekf_kernel("lanes") == "lanes"
  monkeypatch.setattr(ekf_lanes, "JAX_VERSION", (0, 11))
  Dev.compute_capability = "8.0"
  assert ekf_lanes.resolve_ekf_kernel("auto") == "xla"
  monkeypatch.undo()
  assert train_cli.build_config(train_cli.parse_args(["--ekf-kernel", "xla"])).env.ekf_kernel == "xla"
  assert train_cli.build_config(train_cli.parse_args([])).env.ekf_kernel == "auto"


def test_lanes_kernel_needs_a_hopper_gpu(monkeypatch):
  """A clear one-line error before any compile: no GPU, or a GPU older than Hopper (faked here on the CPU)."""
  import envs
  with pytest.raises(ValueError, match="ekf_kernel='lanes' needs a GPU"):
    ekf_lanes.resolve_ekf_kernel("lanes")
  with pytest.raises(ValueError, match="ekf_kernel='lanes' needs a GPU"):
    envs.make("drone", ekf_kernel="lanes")

  class Ampere:
    device_kind, compute_capability = "NVIDIA A100-SXM4-80GB", "8.0"

  class Hopper:
    device_kind, compute_capability = "NVIDIA H200", "9.0"

  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  monkeypatch.setattr(jax, "devices", lambda *a: [Ampere()])
  with pytest.raises(ValueError, match=r"'lanes' needs an NVIDIA Hopper GPU .* is 8.0: use ekf_kernel='xla'"):
    ekf_lanes.resolve_ekf_kernel("lanes")
  monkeypatch.setattr(jax, "devices", lambda *a: [Hopper()])
  assert ekf_lanes.resolve_ekf_kernel("lanes") == "lanes"


def test_a_run_trained_with_the_kernel_evaluates_on_the_cpu(tmp_path):
  """A GPU run's config.json with ekf_kernel="lanes" (what "auto" resolves to on Hopper GPUs) loads for evaluation on
  a machine without the kernel (the choice is dropped: evaluation builds XLA envs); resuming it here is a one-line
  error naming the kernel (its checkpointed env state holds P in the kernel's packed layout)."""
  import json
  from specguard_jax import controllers
  from specguard_jax.ppo import config, runner
  (tmp_path / "config.json").write_text(json.dumps(config.TrainConfig().with_env(ekf_kernel="lanes").to_dict()))
  cfg = controllers.load_run_config(str(tmp_path))
  assert cfg.env.ekf_kernel == "xla" and cfg.vehicle == "drone"
  with pytest.raises(ValueError, match="ekf_kernel='lanes' needs a GPU"):
    runner.load_run_config(str(tmp_path))


def test_an_older_runs_fused_ekf_loads_as_ekf_kernel():
  """config.json of runs from before ekf_kernel hold fused_ekf: False / "xla" -> "xla", "lanes" -> "lanes",
  True / "triton" (the removed Triton kernel) -> "auto"; anything else is a one-line error naming the key."""
  from specguard_jax.ppo import config
  d = config.TrainConfig().to_dict()
  del d["env"]["ekf_kernel"]
  for old, new in ((False, "xla"), ("xla", "xla"), ("lanes", "lanes"), (True, "auto"), ("triton", "auto")):
    assert config.from_dict(dict(d, fused_ekf=old)) == config.TrainConfig().with_env(ekf_kernel=new)
  for bad in (1, "cuda", None):
    with pytest.raises(ValueError, match="config key 'fused_ekf' must be false, true"):
      config.from_dict(dict(d, fused_ekf=bad))
