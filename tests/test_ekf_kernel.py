"""The fused covariance kernel (specguard_jax/ekf_kernel.py) against the XLA form of the same tick.

On the CPU the kernel runs through Pallas' interpreter (the same kernel body, so the same arithmetic and control);
on a GPU (JAX_PLATFORMS=cuda) the compiled Triton kernel is checked too.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from specguard_jax import ekf_kernel

DT = 0.02


def _batch(cfg, n, seed):
  """n random vehicles' inputs to one tick's covariance work: SPD P, transition blocks, H on its support,
  innovations (some far outside their gates), fresh flags, timeout resets due."""
  rng = np.random.default_rng(seed)
  L = rng.normal(size=(n, 15, 15)).astype(np.float32) * 0.3
  P = np.einsum("bij,bkj->bik", L, L) + np.eye(15, dtype=np.float32) * 0.01
  A = rng.normal(size=(n, 3, 3)).astype(np.float32) * 0.02
  B = rng.normal(size=(n, 3, 3)).astype(np.float32) * 0.02
  H = np.zeros((n, 13, 15), np.float32)
  for i, support in enumerate(ekf_lib._H_SUPPORT):
    for c in support:
      H[:, i, c] = rng.normal(size=n)
  scale = np.r_[np.ones(7), 0.05, np.full(5, 0.1)].astype(np.float32)
  innov = (rng.normal(size=(n, 13)) * scale * 3).astype(np.float32)
  enable = rng.random((n, 13)) < 0.8
  due = rng.random((n, 3)) < 0.5
  return [jnp.asarray(x) for x in (P, A, B, H, innov, enable, due)]


def _xla(cfg, stale):
  noise, gate = ekf_lib._noise_and_gates(cfg)
  return jax.jit(jax.vmap(lambda P, A, B, H, innov, en, due: ekf_lib._cov_tick(
      cfg, P, A, B, DT, H, innov, jnp.asarray(noise) ** 2, jnp.asarray(gate), en, due, stale, unrolled=True)))


def _fused(cfg, stale, interpret):
  return jax.jit(jax.vmap(lambda P, A, B, H, innov, en, due: ekf_lib._cov_tick_fused(
      cfg, P, A, B, DT, H, innov, en, due, stale, interpret=interpret)))


def _check(ref, out):
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


@pytest.mark.parametrize("vehicle,stale", [("drone", ()), ("rover", ("gps",))])
def test_kernel_equals_the_xla_tick_interpreted(vehicle, stale):
  cfg = ekf_lib.EKFConfig.drone() if vehicle == "drone" else ekf_lib.EKFConfig.rover()
  args = _batch(cfg, 37, seed=len(stale) + (vehicle == "rover"))     # 37: not a multiple of the block (padding)
  ref = _xla(cfg, stale)(*args)
  _check(ref, _fused(cfg, stale, interpret=True)(*args))
  resets = np.asarray(jax.vmap(ekf_lib._resets)(ref[3], args[6]))
  assert resets.any() and not resets.all()    # timeout resets are exercised (the GPS ones only when GPS is fresh)


def test_padded_layout_of_P_goes_through_the_kernel_unchanged():
  """P kept as [16, 16] with a zero last row and column (ekf_init(p_layout="padded")): the kernel takes and returns
  that layout, equal to the [15, 15] result with the padding still exactly zero; the XLA tick accepts it too."""
  cfg = ekf_lib.EKFConfig.drone()
  P, A, B, H, innov, en, due = _batch(cfg, 21, seed=5)
  P16 = jnp.pad(P, ((0, 0), (0, 1), (0, 1)))
  ref = _fused(cfg, (), interpret=True)(P, A, B, H, innov, en, due)
  out = _fused(cfg, (), interpret=True)(P16, A, B, H, innov, en, due)
  assert out[0].shape == (21, 16, 16)
  np.testing.assert_array_equal(np.asarray(out[0][:, :15, :15]), np.asarray(ref[0]))
  assert not np.any(np.asarray(out[0][:, 15, :])) and not np.any(np.asarray(out[0][:, :, 15]))
  for x, y in zip(out[1:], ref[1:]):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  xla16 = _xla(cfg, ())(P16, A, B, H, innov, en, due)
  np.testing.assert_array_equal(np.asarray(xla16[0][:, :15, :15]),
                                np.asarray(_xla(cfg, ())(P, A, B, H, innov, en, due)[0]))
  assert not np.any(np.asarray(xla16[0][:, 15, :]))


def test_kernel_keeps_nonfinite_out_and_matches_under_nested_vmap():
  cfg = ekf_lib.EKFConfig.drone()
  P, A, B, H, innov, en, due = _batch(cfg, 24, seed=3)
  P = P.at[0, 4, 4].set(jnp.nan).at[1, 2, 7].set(jnp.inf).at[1, 7, 2].set(jnp.inf)
  innov = innov.at[2, 7].set(jnp.inf)
  out = _fused(cfg, (), interpret=True)(P, A, B, H, innov, en, due)
  _check(_xla(cfg, ())(P, A, B, H, innov, en, due), out)
  assert all(bool(jnp.all(jnp.isfinite(x))) for x in out[:3])
  # a sweep vmaps the env a second time: the kernel call is batched by Pallas' own rule
  args2 = [x.reshape((2, 12) + x.shape[1:]) for x in (P, A, B, H, innov, en, due)]
  nested = jax.jit(jax.vmap(jax.vmap(lambda *a: ekf_lib._cov_tick_fused(cfg, *a[:3], DT, *a[3:], (), interpret=True))))
  for x, y in zip(nested(*args2), out):
    np.testing.assert_array_equal(np.asarray(x).reshape(np.asarray(y).shape), np.asarray(y))


def test_ekf_step_with_the_kernel_follows_the_xla_step():
  """Whole EKF ticks (interpreted kernel) against the XLA ticks over 300 ticks of hover readings, three vehicles:
  undisturbed, a 50 m GPS jump that is rejected then reset to after the timeout, a 1 m jump that is fused."""
  from test_ekf import _hover_readings
  cfg = ekf_lib.EKFConfig.drone(reset_timeout=2.0)
  n = 300
  rd = [_hover_readings(n), _hover_readings(n, gps_jump_at=50), _hover_readings(n, gps_jump_at=50)]
  rd[2] = rd[2].replace(gps_pos=rd[2].gps_pos.at[50:, 0].add(1.0 - 50.0))
  readings = jax.tree.map(lambda *x: jnp.stack(x), *rd)

  def run(fused, p_layout="square"):
    def one(r):
      s0 = ekf_lib.ekf_init(cfg, jax.tree.map(lambda x: x[0], r), p_layout=p_layout)
      step = lambda s, x: (ekf_lib.ekf_step(cfg, s, x, DT, fused=fused),) * 2
      return jax.lax.scan(step, s0, jax.tree.map(lambda x: x[1:], r))[1]
    return jax.jit(jax.vmap(one))(readings)

  ref, out = run(False), run("interpret", p_layout="padded")    # the env's layout with the kernel: P padded to [16, 16]
  assert out.P.shape[-2:] == (16, 16) and not np.any(np.asarray(out.P[..., 15, :]))
  out = out.replace(P=ekf_lib.as_square(out.P))
  assert float(ref.n_resets[1, -1]) >= 1 and float(ref.n_resets[2, -1]) == 0   # the scenarios do what they say
  np.testing.assert_array_equal(np.asarray(out.accepted), np.asarray(ref.accepted))
  np.testing.assert_array_equal(np.asarray(out.n_resets), np.asarray(ref.n_resets))
  for name in ("pos", "vel", "quat", "gyro_bias", "accel_bias"):
    np.testing.assert_allclose(np.asarray(getattr(out, name)), np.asarray(getattr(ref, name)), atol=2e-4,
                               err_msg=name)
  np.testing.assert_allclose(np.asarray(out.P), np.asarray(ref.P), rtol=1e-3, atol=1e-7)


@pytest.mark.skipif(jax.default_backend() != "gpu", reason="the compiled Triton kernel needs a GPU")
@pytest.mark.parametrize("vehicle", ["drone", "rover"])
def test_compiled_kernel_equals_the_xla_tick(vehicle):
  cfg = ekf_lib.EKFConfig.drone() if vehicle == "drone" else ekf_lib.EKFConfig.rover()
  for stale in [(), ("gps",)]:
    args = _batch(cfg, 4099, seed=11)
    _check(_xla(cfg, stale)(*args), _fused(cfg, stale, interpret=False)(*args))


def test_shadow_filter_with_the_kernel_follows_the_xla_shadow():
  """The reconstruction's shadow EKF (recon_tick(fused=...), vmapped over three vehicles blaming the gyro, the
  accelerometer and the GPS, alarm up) with the kernel (interpreted on the CPU, compiled on a GPU) against the XLA
  form, 25 ticks."""
  from test_recon_handback import DT as RDT, _readings
  from specguard_jax.estimation import model_file, recon
  from specguard_jax.types import SENSOR_NAMES
  cfg = recon.ReconConfig(n_controls=4, ekf=ekf_lib.EKFConfig.drone())
  params = model_file.load_params(model_file.default_path("drone"), 4)
  controls = jnp.full((4,), 1.5 * 9.81 / 4)
  masks = jnp.stack([jnp.zeros(len(SENSOR_NAMES)).at[SENSOR_NAMES.index(s)].set(1.0) for s in ("gyro", "accel", "gps")])

  def run(fused):
    # the env keeps P padded with the kernel
    e0 = ekf_lib.ekf_init(cfg.ekf, _readings(0), p_layout="padded" if fused else "square")
    tick = jax.jit(jax.vmap(lambda st, rd, m: recon.recon_tick(cfg, params, st, e0, rd, controls, m, True, RDT,
                                                                fused=fused)[:2], in_axes=(0, None, 0)))
    st = jax.vmap(lambda _: recon.recon_init(cfg, e0))(jnp.arange(3))
    assert ("pallas_call" in str(jax.make_jaxpr(tick)(st, _readings(1), masks))) == bool(fused)
    xs = []
    for k in range(1, 26):
      st, x = tick(st, _readings(k), masks)
      xs.append(x)
    return st, jnp.stack(xs)

  (ref, x_ref), (out, x_out) = run(False), run(True if jax.default_backend() == "gpu" else "interpret")
  np.testing.assert_allclose(np.asarray(x_out), np.asarray(x_ref), rtol=1e-4, atol=1e-5)
  for name in ("pos", "vel", "quat", "gyro_bias", "accel_bias"):
    np.testing.assert_allclose(np.asarray(getattr(out.shadow, name)), np.asarray(getattr(ref.shadow, name)),
                               atol=1e-5, err_msg=name)
  assert out.shadow.P.shape[-1] == 16 and not np.any(np.asarray(out.shadow.P[:, 15]))
  np.testing.assert_allclose(np.asarray(ekf_lib.as_square(out.shadow.P)), np.asarray(ref.shadow.P), rtol=1e-3,
                             atol=1e-7)
  np.testing.assert_array_equal(np.asarray(out.shadow.accepted), np.asarray(ref.shadow.accepted))


def _rollouts(ref_env, env, steps: int):
  """Both envs' (reset states, stacked step states) over `steps` zero-action steps of the same 3 vehicles, jitted."""
  keys = jax.random.split(jax.random.PRNGKey(3), 3)

  def rollout(e):
    s0 = jax.vmap(e.reset)(keys)
    step = lambda s, _: (jax.vmap(e.step)(s, jnp.zeros((3, 3))),) * 2
    return s0, jax.lax.scan(step, s0, None, length=steps)[1]

  return jax.jit(lambda: rollout(ref_env))(), jax.jit(lambda: rollout(env))()


def test_phase2_env_with_the_kernel_follows_the_xla_env():
  """The whole phase-2 env (autopilot EKF and the reconstruction's shadow on the kernel, interpreted on the CPU; P in
  the padded layout from reset on) against the XLA env: 8 closed-loop steps (40 ticks) of 3 vehicles."""
  import envs
  kw = dict(control_mode="reactive", detector="residual", reconstruction=True)
  ref_env, env = envs.make("drone", **kw), envs.make("drone", **kw)
  env._fused_ekf = env._fused_shadow = "interpret"
  (s0_ref, ref), (s0, out) = _rollouts(ref_env, env, 8)
  sim = s0.info["sim"]
  assert sim["ekf"].P.shape == (3, 16, 16) and sim["recon"].shadow.P.shape == (3, 16, 16)
  assert s0_ref.info["sim"]["ekf"].P.shape == (3, 15, 15)
  np.testing.assert_allclose(np.asarray(out.obs), np.asarray(ref.obs), rtol=1e-3, atol=1e-3)
  np.testing.assert_allclose(np.asarray(out.reward), np.asarray(ref.reward), rtol=1e-3, atol=1e-4)
  e, e_ref = out.info["sim"]["ekf"], ref.info["sim"]["ekf"]
  assert not np.any(np.asarray(e.P[..., 15, :]))
  np.testing.assert_allclose(np.asarray(ekf_lib.as_square(e.P)), np.asarray(e_ref.P), rtol=1e-2, atol=1e-6)
