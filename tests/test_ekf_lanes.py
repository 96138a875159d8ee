"""bench/ekf_lanes.py (the per-lane covariance tick, an experiment): its body equals ekf._cov_tick, and its Mosaic GPU
kernel lowers for CUDA (compiled and timed only on a GPU: BENCHMARKS.md, session 34)."""

import os
import sys

import jax
import numpy as np
import pytest

from specguard_jax import ekf as ekf_lib
from test_ekf_kernel import DT, _batch, _check, _xla

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))
import ekf_lanes as lanes  # noqa: E402


@pytest.mark.parametrize("vehicle", ["drone", "rover"])
@pytest.mark.parametrize("stale", [(), ("gps",)])
def test_lane_body_equals_xla_tick(vehicle, stale):
  cfg = ekf_lib.EKFConfig.drone() if vehicle == "drone" else ekf_lib.EKFConfig.rover()
  args = _batch(cfg, 64, seed=5)
  spec = ekf_lib._cov_spec(cfg, DT, stale)
  # eager: ~10^4 small ops, quicker op by op on the CPU than one XLA compile of the straight-line code
  out = lanes.cov_tick_lanes_xla(spec, lanes.resets_of(cfg), *args)
  _check(_xla(cfg, stale)(*args), out)


def test_lane_body_catches_a_changed_tick():
  """The comparison above can fail: a lane body given another tick length differs from the reference."""
  cfg = ekf_lib.EKFConfig.drone()
  args = _batch(cfg, 64, seed=5)
  out = lanes.cov_tick_lanes_xla(ekf_lib._cov_spec(cfg, 2 * DT, ()), lanes.resets_of(cfg), *args)
  with pytest.raises(AssertionError):
    _check(_xla(cfg, ())(*args), out)


def test_mosaic_kernel_lowers_for_cuda():
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  cfg = ekf_lib.EKFConfig.rover()
  args = _batch(cfg, 256, seed=0)
  spec = ekf_lib._cov_spec(cfg, DT, ())
  fn = jax.jit(lambda *x: lanes.cov_tick_lanes_mgpu(spec, lanes.resets_of(cfg), *x))
  text = fn.trace(*args).lower(lowering_platforms=("cuda",)).as_text()
  assert "mosaic_gpu" in text


def test_mosaic_kernel_blocks_in_mosaic_interpreter():
  """The kernel's plumbing (pack, padding to whole blocks, each program's TMA copies at its own offset, unpack) in
  Mosaic GPU's interpreter on the CPU, with the copy stage (each output row = the same input row): 300 vehicles, 3
  programs. The full body's arithmetic is checked above; interpreted it takes ~1 min per program."""
  pytest.importorskip("jax.experimental.pallas.mosaic_gpu")
  params = pytest.importorskip("jax._src.pallas.mosaic_gpu.interpret.params")
  cfg = ekf_lib.EKFConfig.drone()
  P, A, B, H, innov, enable, due = _batch(cfg, 300, seed=1)
  spec = ekf_lib._cov_spec(cfg, DT, ("gps",))
  P_out, dx, _, _ = lanes.cov_tick_lanes_mgpu(spec, lanes.resets_of(cfg), P, A, B, H, innov, enable, due,
                                              stage="copy", interpret=params.InterpretGPUParams())
  np.testing.assert_array_equal(np.asarray(P_out), np.asarray(P))
  np.testing.assert_array_equal(np.asarray(dx), np.concatenate([np.asarray(A).reshape(300, 9),
                                                                np.asarray(B).reshape(300, 9)[:, :6]], axis=1))
