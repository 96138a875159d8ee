"""The per-lane covariance kernel (specguard_jax/ekf_lanes.py, `fused_ekf="lanes"`): its body equals ekf._cov_tick,
its Mosaic GPU kernel lowers for CUDA and runs its blocks in Mosaic GPU's CPU interpreter, and ekf_step / the env
route a vmapped batch through it (compiled and timed only on a GPU: bench/ekf_lanes.py, BENCHMARKS.md session 35)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_lanes
from test_ekf_kernel import DT, _batch, _check, _xla


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


@pytest.mark.parametrize("triangle", [True, False])
def test_kernel_blocks_in_mosaic_interpreter(triangle):
  """The kernel's plumbing (transposes, padding to whole blocks, each program's TMA copies at its own offset: P's
  upper triangle as 15 row ranges mirrored on the way out, or all 225 rows; P and the outputs written in place) in
  Mosaic GPU's interpreter on the CPU, with the copy stage (P and out copied from P and aux): 300 vehicles, 3
  programs. The full body's arithmetic is checked above (interpreted it takes minutes per program)."""
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  params = pytest.importorskip("jax._src.pallas.mosaic_gpu.interpret.params")
  cfg = _cfg("drone")
  P, A, B, H, innov, enable, due = _batch(cfg, 300, seed=1)
  spec = ekf_lib._cov_spec(cfg, DT, ("gps",))
  P_out, dx, ratio, _ = ekf_lanes.cov_tick(spec, ekf_lanes.resets_of(cfg), P, A, B, H, innov, enable, due,
                                           stage="copy", interpret=params.InterpretGPUParams(),
                                           triangle=triangle)
  np.testing.assert_array_equal(np.asarray(P_out), np.asarray(P))
  ab = np.concatenate([np.asarray(A).reshape(300, 9), np.asarray(B).reshape(300, 9)], axis=1)
  np.testing.assert_array_equal(np.asarray(dx), ab[:, :15])
  np.testing.assert_array_equal(np.asarray(ratio[:, :3]), ab[:, 15:])


@pytest.fixture
def lanes_on_cpu(monkeypatch):
  """ekf_lanes.cov_tick replaced by the XLA reference for the batch (the kernel itself needs a GPU): what is tested
  is the routing around it. Returns the list of P shapes it was called with."""
  calls = []

  def fake(spec, resets, P, A, B, H, innov, enable, due, stage="full", interpret=None):
    calls.append(P.shape)
    cfg = fake.cfg
    noise, gate = ekf_lib._noise_and_gates(cfg)
    stale = () if spec.used[0] else ("gps",)
    return jax.vmap(lambda *x: ekf_lib._cov_tick(cfg, *x[:3], spec.dt, *x[3:5], jnp.asarray(noise) ** 2,
                                                 jnp.asarray(gate), *x[5:], stale, unrolled=True))(
        P, A, B, H, innov, enable, due)

  fake.cfg = _cfg("drone")
  monkeypatch.setattr(ekf_lanes, "cov_tick", fake)
  return calls


def test_env_routes_the_batch_through_the_lanes_kernel(lanes_on_cpu):
  """A drone env with fused_ekf="lanes" (the kernel stood in for on the CPU) keeps P [15, 15], hands the kernel the
  whole vmapped batch, and steps as the XLA env does: 6 steps of 3 vehicles."""
  import envs
  ref_env, env = envs.make("drone"), envs.make("drone")
  env._fused_ekf = env._fused_shadow = "lanes"
  keys = jax.random.split(jax.random.PRNGKey(3), 3)

  def rollout(e):
    s0 = jax.vmap(e.reset)(keys)
    step = lambda s, _: (jax.vmap(e.step)(s, jnp.zeros((3, 3))),) * 2
    return jax.lax.scan(step, s0, None, length=6)[1]

  ref, out = jax.jit(lambda: rollout(ref_env))(), jax.jit(lambda: rollout(env))()
  assert lanes_on_cpu and all(shape == (3, 15, 15) for shape in lanes_on_cpu)
  assert out.info["sim"]["ekf"].P.shape == (6, 3, 15, 15)
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), rtol=1e-4, atol=1e-4)
  np.testing.assert_allclose(np.asarray(out.info["sim"]["ekf"].P), np.asarray(ref.info["sim"]["ekf"].P),
                             rtol=1e-4, atol=1e-8)


def test_fused_ekf_names_a_kernel():
  from envs.base import ekf_kernel_kind
  assert [ekf_kernel_kind(v) for v in (False, None, "", True, "triton", "lanes")] == ["", "", "", "triton",
                                                                                       "triton", "lanes"]
  with pytest.raises(ValueError, match="fused_ekf must be false, true or one of triton, lanes; got 'cuda'"):
    ekf_kernel_kind("cuda")


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
