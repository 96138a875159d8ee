"""STL engine: parser errors, window kernels, and property tests against rtamt (the oracle) on random formulas."""

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from specguard_jax import stl
from specguard_jax.stl import windows

rtamt = pytest.importorskip("rtamt")

SIGS = ("x", "y", "z")
LENGTHS = (2, 3, 6, 13, 40)  # rtamt 0.4.10 crashes on 1-sample traces


def rtamt_eval(text, sig):
  spec = rtamt.StlDiscreteTimeSpecification()
  for k in sig:
    spec.declare_var(k, "float")
  spec.spec = text
  spec.parse()
  n = len(next(iter(sig.values())))
  ds = {"time": list(range(n))}
  ds.update({k: [float(v) for v in vals] for k, vals in sig.items()})
  return np.array([r[1] for r in spec.evaluate(ds)], dtype=np.float64)


def assert_close(ours, ref, atol=1e-5):
  ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
  assert ours.shape == ref.shape
  inf_ok = np.array_equal(np.isposinf(ours), np.isposinf(ref)) and np.array_equal(np.isneginf(ours), np.isneginf(ref))
  fin = np.isfinite(ref)
  assert inf_ok, f"infinities differ:\n{ours}\n{ref}"
  assert np.all(np.abs(ours[fin] - ref[fin]) <= atol), f"max diff {np.max(np.abs(ours[fin] - ref[fin]))}"


# ---------------------------------------------------------------- random formulas (rtamt-compatible text)
_num = st.sampled_from([-2.0, -1.0, -0.5, 0.0, 0.25, 1.0, 1.5, 3.0])


@st.composite
def predicates(draw):
  cmp = draw(st.sampled_from([">", ">=", "<", "<="]))
  c = draw(_num)
  if draw(st.booleans()):
    return f"{draw(st.sampled_from(SIGS))} {cmp} {c}"
  a, b = draw(st.lists(st.sampled_from(SIGS), min_size=2, max_size=2, unique=True))
  ca, cb = draw(_num.filter(bool)), draw(_num.filter(bool))
  return f"(({ca}*{a}) + ({cb}*{b})) {cmp} {c}"


@st.composite
def intervals(draw, allow_none=True):
  if allow_none and draw(st.integers(0, 3)) == 0:
    return ""
  lo = draw(st.integers(0, 6))
  hi = lo + draw(st.integers(0, 8))
  return f"[{lo},{hi}]"


@st.composite
def formulas(draw, depth=3):
  if depth == 0 or draw(st.integers(0, 4)) == 0:
    return draw(predicates())
  kind = draw(st.sampled_from(["not", "and", "or", "implies", "always", "eventually", "until"]))
  sub = lambda: draw(formulas(depth=depth - 1))
  if kind == "not":
    return f"(not {sub()})"
  if kind in ("and", "or"):
    return f"({sub()} {kind} {sub()})"
  if kind == "implies":
    return f"({sub()} -> {sub()})"
  if kind in ("always", "eventually"):
    return f"({kind}{draw(intervals())}({sub()}))"
  return f"({sub()} until{draw(intervals())} {sub()})"


def random_traces(seed, n_traces, t):
  rng = np.random.default_rng(seed)
  return {s: np.round(rng.uniform(-4, 4, size=(n_traces, t)), 3).astype(np.float32) for s in SIGS}


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=formulas(), t=st.sampled_from(LENGTHS), seed=st.integers(0, 2**31 - 1))
def test_matches_rtamt_on_random_formulas(text, t, seed):
  """Max abs difference to rtamt <= 1e-5 at every index, for 3 traces per formula (batched in one call)."""
  sig = random_traces(seed, 3, t)
  ours = np.asarray(stl.robustness(text, {k: jnp.asarray(v) for k, v in sig.items()}))
  np.testing.assert_array_equal(stl.episode_robustness(text, sig), ours[:, 0])
  for b in range(3):
    ref = rtamt_eval(text, {k: v[b].astype(np.float64) for k, v in sig.items()})
    assert_close(ours[b], ref)


@pytest.mark.parametrize("text", [
    "always[0,10](x > 1) and eventually[20,40](y < 0.5)",
    "x > 0 until[3,9] y > 1",
    "x > 0 until y > 1 until z < 0",
    "always((x > 0.5) -> eventually[0,5](y <= 0))",
    "not eventually[2,4](always[1,3]((x - y) >= 0.25))",
    "always[0,60](x > -3)",
    "eventually(z > 3.5)",
    "(x > 0) -> ((y > 0) -> (z < 1))",
])
def test_matches_rtamt_fixed(text):
  sig = random_traces(7, 2, 50)
  ours = np.asarray(stl.robustness(text, sig))
  for b in range(2):
    assert_close(ours[b], rtamt_eval(text, {k: v[b] for k, v in sig.items()}))


def test_rtamt_semantic_facts():
  """Facts checked empirically on rtamt 0.4.10 that the engine reproduces."""
  x = np.array([1.0, 3.0, -2.0, 5.0, 0.0], np.float32)
  for text in ["x > 1", "x >= 1"]:
    np.testing.assert_allclose(stl.robustness(text, {"x": x}), x - 1)  # strict and non-strict alike
  for text in ["x < 1", "x <= 1"]:
    np.testing.assert_allclose(stl.robustness(text, {"x": x}), 1 - x)
  # truncated windows: empty -> +inf for always, -inf for eventually / until
  np.testing.assert_array_equal(stl.robustness("always[1,2](x > 0)", {"x": x}), [-2, -2, 0, 0, np.inf])
  np.testing.assert_array_equal(stl.robustness("eventually[1,3](x > 0)", {"x": x}), [5, 5, 5, 0, -np.inf])
  # implies is max(-a, b); until is left-associative
  y = np.array([0.0, -1.0, 2.0, 1.0, 4.0], np.float32)
  np.testing.assert_array_equal(stl.robustness("(x > 0) -> (y > 0)", {"x": x, "y": y}), [0, -1, 2, 1, 4])
  np.testing.assert_array_equal(stl.robustness("x>0 until y > 0 until x < 2", {"x": x, "y": y}), [1, 2, 4, 2, 2])


# ---------------------------------------------------------------- kernels
def _naive_window(x, a, b, op, fill):
  t = x.shape[-1]
  out = np.full_like(x, fill)
  for i in range(t):
    seg = x[..., i + a:min(i + b + 1, t)]
    if seg.shape[-1]:
      out[..., i] = op(seg, axis=-1)
  return out


@pytest.mark.parametrize("method", ["doubling", "vhgw"])
@pytest.mark.parametrize("a,b", [(0, 0), (0, 1), (0, 6), (2, 9), (3, 40), (0, 63), (10, 200)])
def test_window_reduce_methods(method, a, b):
  x = np.random.default_rng(a * 100 + b).normal(size=(3, 97)).astype(np.float32)
  for op, nop, fill in ((jnp.minimum, np.min, np.inf), (jnp.maximum, np.max, -np.inf)):
    got = np.asarray(windows.window_reduce(jnp.asarray(x), a, b, op, method=method))
    np.testing.assert_array_equal(got, _naive_window(x, a, b, nop, fill))


def test_batched_jit_vmap_grad():
  text = "always((x > 0.5) -> eventually[0,4](y < 1)) and (x > -3 until[1,6] y > 2)"
  f = stl.parse(text)
  sig = random_traces(3, 4, 30)
  full = stl.robustness(f, sig)
  jitted = jax.jit(lambda s: stl.robustness(f, s))(sig)
  vm = jax.vmap(lambda s: stl.robustness(f, s))(sig)
  np.testing.assert_array_equal(full, jitted)
  np.testing.assert_array_equal(full, vm)
  # leading batch axes broadcast: a [2, 1, T] signal against a [1, 4, T] one
  b = stl.robustness("x > y", {"x": np.zeros((2, 1, 5)), "y": np.ones((1, 4, 5))})
  assert b.shape == (2, 4, 5)
  g = jax.grad(lambda xs: stl.robustness("always[0,3](x > 0)", {"x": xs})[0])(jnp.array([3.0, 1.0, 2.0, 5.0, -9.0]))
  np.testing.assert_array_equal(g, [0, 1, 0, 0, 0])


def test_seconds_intervals_and_length():
  x = np.arange(10, dtype=np.float32) - 5
  a = stl.robustness("eventually[0.2s, 0.5s](x > 0)", {"x": x}, dt=0.1)
  np.testing.assert_array_equal(a, stl.robustness("eventually[2,5](x > 0)", {"x": x}))
  np.testing.assert_array_equal(stl.robustness("always[0,2s](x>0)", {"x": x}, dt=1.0),
                                stl.robustness("always[0,2](x>0)", {"x": x}))
  with pytest.raises(stl.IntervalError, match="dt"):
    stl.robustness("always[0s,1s](x > 0)", {"x": x})
  with pytest.raises(stl.IntervalError, match="multiple"):
    stl.robustness("always[0s,0.25s](x > 0)", {"x": x}, dt=0.1)
  # ragged episodes: length=6 equals evaluating the first 6 samples
  xs = np.stack([x, x[::-1]])
  r = stl.robustness("always(x > -2) and eventually[1,3](x < 0)", {"x": xs}, length=np.array([6, 10]))
  np.testing.assert_array_equal(r[0, :6], stl.robustness("always(x > -2) and eventually[1,3](x < 0)", {"x": x[:6]}))


@pytest.mark.parametrize("text,err,msg", [
    ("always[5,2](x > 1)", stl.IntervalError, "inverted"),
    ("always[](x > 1)", stl.STLSyntaxError, "empty interval"),
    ("always[-1,2](x > 1)", stl.IntervalError, "negative"),
    ("always[0,1.5](x > 1)", stl.IntervalError, "integers"),
    ("always(x > 1", stl.STLSyntaxError, "position 6"),
    ("x > 1 y", stl.STLSyntaxError, "position 6"),
    ("x * y > 1", stl.STLSyntaxError, "affine"),
    ("x > 1 and", stl.STLSyntaxError, "ended early"),
    ("x $ 1", stl.STLSyntaxError, "unexpected character"),
    ("", stl.STLSyntaxError, "empty formula"),
    ("3 > 1", stl.STLSyntaxError, "signal"),
    ("always[0,inf](x > 1)", stl.STLSyntaxError, "unbounded"),
])
def test_parse_errors_are_one_line(text, err, msg):
  with pytest.raises(err, match=msg) as e:
    stl.parse(text)
  assert isinstance(e.value, ValueError) and "\n" not in str(e.value)


def test_unknown_signals_and_params():
  with pytest.raises(stl.UnknownSignalError, match="'altitud'"):
    stl.parse("always(altitud > 10)", signals=["altitude"])
  f = stl.parse("always[0, T_S s](altitude > MIN_ALT + 1)", params={"MIN_ALT": 9.0, "T_S": 2.0})
  assert f == stl.parse("always[0s, 2s](altitude > 10)")
  with pytest.raises(stl.UnknownSignalError, match="'y'"):
    stl.robustness("x > 0 and y > 0", {"x": np.zeros(3)})


def test_str_roundtrip():
  for text in ["always[0,10](alt > 10) and eventually[20,40](dist_wp1 < 5)", "x > 0 until[1,2] (y <= 1 -> z > 0)",
               "not (x > 1 or G[0s,3s](y < 2))"]:
    f = stl.parse(text)
    assert stl.parse(str(f)) == f
