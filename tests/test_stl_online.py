"""Online monitor: after every step its value equals the offline robustness of the trace so far at time 0."""

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from specguard_jax import stl

SIGS = ("x", "y")


def run_monitor(mon, sig):
  """Scan the monitor over [B, T] traces; returns [T, B] running robustness."""
  b, t = next(iter(sig.values())).shape
  state = mon.init((b,))
  xs = {k: jnp.asarray(v).T for k, v in sig.items()}

  def step(s, x_t):
    return mon.update(s, x_t)

  _, out = jax.jit(lambda s, xs: jax.lax.scan(step, s, xs))(state, xs)
  return np.asarray(out)


def check(text, t=24, n=4, seed=0):
  rng = np.random.default_rng(seed)
  sig = {k: np.round(rng.uniform(-3, 3, (n, t)), 3).astype(np.float32) for k in SIGS}
  mon = stl.OnlineMonitor.create(text, dt=0.5)
  online = run_monitor(mon, sig)  # [T, B]
  # offline robustness of every prefix at time 0, in one call: lengths [T, 1] against traces [1, B, T]
  prefix = np.asarray(stl.robustness(text, {k: v[None] for k, v in sig.items()}, dt=0.5,
                                     length=np.arange(1, t + 1)[:, None]))[..., 0]
  np.testing.assert_allclose(online, prefix, rtol=0, atol=1e-5)
  final = np.asarray(stl.robustness(text, sig, dt=0.5))[:, 0]
  np.testing.assert_array_equal(stl.episode_robustness(text, sig, dt=0.5), final)
  np.testing.assert_array_equal(
      stl.episode_robustness(text, {k: v[None] for k, v in sig.items()}, dt=0.5, length=np.arange(1, t + 1)[:, None]),
      prefix)
  np.testing.assert_allclose(online[-1], final, rtol=0, atol=1e-5)  # final verdict == whole-trace offline
  mid = np.asarray(stl.robustness(text, {k: v[:, :7] for k, v in sig.items()}, dt=0.5))[:, 0]
  np.testing.assert_allclose(online[6], mid, rtol=0, atol=1e-5)


@pytest.mark.parametrize("text", [
    "always(x > -2)",
    "eventually(y > 2.5)",
    "always((x > 0.5) -> eventually[0,4](y < 0))",
    "always(x > 0 -> always[1,3](y > -2.5)) and eventually[2,6](x < 1)",
    "(x > -2) until (y > 2)",
    "(x > -2 or always[0,2](y > 0)) until eventually[1,3](y > 2.5)",
    "always[0,30](x > -2.9)",  # bounded formula longer than the trace
    "x > 0 until[2,5] y > 1",
    "not eventually(always[0,2](x > 1)) or (y > 0)",
    "always((x > 1) -> eventually[0s, 1.5s](y > 0 or x < 0))",  # seconds, dt = 0.5
])
def test_online_equals_offline_prefixes(text):
  check(text)


_pred = st.sampled_from(["x > 0.5", "x <= -1", "y >= 1.5", "y < 0", "(x - y) > 0"])


@st.composite
def bounded(draw, depth=2):
  if depth == 0 or draw(st.integers(0, 2)) == 0:
    return draw(_pred)
  k = draw(st.sampled_from(["not", "and", "or", "implies", "G", "F", "U"]))
  a = draw(st.integers(0, 3))
  iv = f"[{a},{a + draw(st.integers(0, 4))}]"
  sub = lambda: draw(bounded(depth - 1))
  return {"not": lambda: f"(not {sub()})", "and": lambda: f"({sub()} and {sub()})",
          "or": lambda: f"({sub()} or {sub()})", "implies": lambda: f"({sub()} -> {sub()})",
          "G": lambda: f"(always{iv}({sub()}))", "F": lambda: f"(eventually{iv}({sub()}))",
          "U": lambda: f"({sub()} until{iv} {sub()})"}[k]()


@st.composite
def monitorable(draw, depth=2):
  if depth == 0 or draw(st.integers(0, 2)) == 0:
    k = draw(st.sampled_from(["G", "F", "U", "B"]))
    return {"G": lambda: f"(always({draw(bounded())}))", "F": lambda: f"(eventually({draw(bounded())}))",
            "U": lambda: f"({draw(bounded())} until {draw(bounded())})", "B": lambda: draw(bounded())}[k]()
  k = draw(st.sampled_from(["not", "and", "or", "implies"]))
  sub = lambda: draw(monitorable(depth - 1))
  return {"not": lambda: f"(not {sub()})", "and": lambda: f"({sub()} and {sub()})",
          "or": lambda: f"({sub()} or {sub()})", "implies": lambda: f"({sub()} -> {sub()})"}[k]()


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=monitorable(), seed=st.integers(0, 2**31 - 1))
def test_online_random_fragment(text, seed):
  check(text, t=18, n=3, seed=seed)


@pytest.mark.parametrize("text", ["always(eventually(x > 0))", "eventually[0,5](always(x > 0))",
                                  "(always(x > 0)) until (y > 0)"])
def test_unsupported_online_is_rejected(text):
  with pytest.raises(stl.UnsupportedOnlineError, match="online monitor"):
    stl.OnlineMonitor.create(text)


def test_functional_api_and_state_size():
  s = stl.monitor_init("always((x > 0) -> eventually[0,3](y > 0))", batch_shape=(5,))
  assert s.window["x"].shape == (5, 4) and s.prefix == {}
  s, v = stl.monitor_update("always((x > 0) -> eventually[0,3](y > 0))", s, {"x": jnp.ones(5), "y": -jnp.ones(5)})
  assert v.shape == (5,)
  np.testing.assert_array_equal(v, -1.0)  # trace so far [x=1, y=-1]: eventually window truncated -> -1


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=bounded(depth=3), t=st.sampled_from([1, 2, 5, 8, 13]), seed=st.integers(0, 2**31 - 1))
def test_columns_equal_the_array_form(text, t, seed):
  """The monitor's per-position form (stl/columns.py) gives offline.evaluate's values exactly (min / max and the
  same affine arithmetic per position), windows longer than the buffer included."""
  from specguard_jax.stl import columns, offline
  rng = np.random.default_rng(seed)
  sig = {k: jnp.asarray(np.round(rng.uniform(-3, 3, (3, t)), 3).astype(np.float32)) for k in SIGS}
  f = stl.OnlineMonitor.create(text).formula
  want = np.asarray(offline.evaluate(f, sig))
  got = np.stack([np.broadcast_to(np.asarray(c), (3,)) for c in columns.evaluate_columns(f, sig)], -1)
  np.testing.assert_array_equal(got, np.broadcast_to(want, got.shape), err_msg=text)


@pytest.mark.parametrize("t", [1, 4, 7, 31])
def test_window_columns_equal_window_reduce(t):
  from specguard_jax.stl import columns, windows
  x = jnp.asarray(np.random.default_rng(t).normal(size=(2, t)).astype(np.float32))
  for a in range(0, t + 2):
    for b in range(a, t + 3):
      for op in (jnp.minimum, jnp.maximum):
        want = np.asarray(windows.window_reduce(x, a, b, op))
        got = np.stack([np.asarray(c) for c in columns.window_columns(columns.split_columns(x), a, b, op)], -1)
        np.testing.assert_array_equal(got, want, err_msg=f"[{a},{b}] {op.__name__}")


@pytest.mark.parametrize("text,h", [("always((x > 0.5) -> eventually[0,4](y < 0))", 4), ("always(x > -2)", 0),
                                    ("always(always[1,3](y > -2.5) or x > 1)", 3)])
def test_settled_is_the_minimum_over_closed_positions(text, h):
  """OnlineMonitor.settled after step t of always(psi) (psi of horizon h) = min over positions j <= t - h of psi's
  robustness at j on the whole trace (+inf before any closes): it never rises, and ends >= the final verdict.
  Other formulas: the so-far value."""
  rng = np.random.default_rng(3)
  t_len, n = 24, 4
  sig = {k: np.round(rng.uniform(-3, 3, (n, t_len)), 3).astype(np.float32) for k in SIGS}
  mon = stl.OnlineMonitor.create(text)
  psi = np.asarray(stl.robustness(mon.formula.arg, sig))            # [B, T] psi at every position, whole trace
  state = mon.init((n,))
  settled = []
  for t in range(t_len):
    state, so_far = mon.update(state, {k: jnp.asarray(v[:, t]) for k, v in sig.items()})
    settled.append(np.asarray(mon.settled(state, so_far)))
    closed = psi[:, : max(t - h + 1, 0)]
    expect = closed.min(axis=1) if closed.shape[1] else np.full(n, np.inf)
    np.testing.assert_allclose(settled[-1], expect, rtol=0, atol=1e-5)
  settled = np.stack(settled)
  assert np.all(settled[1:] <= settled[:-1]) and np.all(settled[-1] >= np.asarray(so_far) - 1e-6)
  other = stl.OnlineMonitor.create("eventually(x > 2.9)")
  s, v = other.update(other.init((n,)), {"x": jnp.zeros(n)})
  assert np.array_equal(np.asarray(other.settled(s, v)), np.asarray(v))
