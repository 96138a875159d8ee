"""Reward families (bounded, monotone, continuous, paper-equation sample points) and the per-step table reward."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax import rewards, specs
from specguard_jax.rewards import families as fam
from specguard_jax.signals import SIGNAL_NAMES

A, K = 5.0, 1.0
GRID = np.linspace(-100, 100, 20001, dtype=np.float32)  # condition values f, threshold A
SINGLE = {"keep_above": (fam.keep_above, 1), "keep_below": (fam.keep_below, -1), "two_sided": (fam.two_sided, 1),
          "s6": (fam.s6, 1), "fence": (fam.fence, 1)}


@pytest.mark.parametrize("name", sorted(SINGLE))
def test_bounded_monotone_continuous(name):
  fn, direction = SINGLE[name]
  r = np.asarray(fn(GRID, A, K))
  lo = -1.0 if name == "two_sided" else 0.0
  assert np.all(r >= lo) and np.all(r <= 1.0) and np.all(np.isfinite(r))
  d = np.diff(r) * direction
  assert np.all(d >= 0)  # monotone non-decreasing in the margin
  mid = np.abs(GRID - A) < 10
  assert np.all(d[mid[:-1]] > 0)  # strictly increasing near the threshold
  eps = 1e-3
  jump = abs(float(fn(A + eps, A, K)) - float(fn(A - eps, A, K)))
  assert jump < 2 * K * eps  # continuous (Lipschitz k/2 for sigma, k for two_sided)
  assert float(fn(A, A, K)) == (0.0 if name == "two_sided" else 0.5)


def test_fence_hv_bounded_monotone_in_each_margin():
  h = GRID[::50]
  for v in (-3.0, 1.0, 4.0):
    r = np.asarray(fam.fence_hv(h, v, 1.0, 0.5))
    assert np.all((r >= 0) & (r <= 1)) and np.all(np.diff(r) >= 0)
  assert np.asarray(fam.fence_hv(20.0, 20.0, 1.0, 0.5)) > 0.99
  assert np.asarray(fam.fence_hv(20.0, -5.0, 1.0, 0.5)) < 0.05  # one bad margin is enough to lose the reward


# sample points on the side where each printed equation has its sigmoid branch (there we match it exactly)
@pytest.mark.parametrize("spec_id,fn,points", [
    ("S1", fam.two_sided, [0.5, 2.0, 4.0, 4.9]),
    ("S2", fam.keep_below, [0.5, 2.0, 4.9]), ("S5", fam.keep_below, [1.0, 3.0]),
    ("S4", fam.keep_below, [-2.0, 1.0, 4.5]), ("S8", fam.keep_below, [0.0, 4.0]),
    ("S3", fam.keep_above, [5.1, 7.0, 30.0]), ("S7", fam.keep_above, [6.0, 9.0]),
    ("S6", fam.s6, [0.5, 3.0, 4.9]),
])
def test_matches_paper_equations_at_sample_points(spec_id, fn, points):
  f = np.array(points, np.float32)
  np.testing.assert_allclose(fn(f, A, K), fam.paper_equation(spec_id, f, A, K), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("spec_id,fn", [("S1", fam.two_sided), ("S2", fam.keep_below), ("S3", fam.keep_above),
                                        ("S6", fam.s6), ("S8", fam.keep_below)])
def test_constant_branch_is_approached(spec_id, fn):
  """Away from the threshold our continuous forms tend to the printed constant branch."""
  f = np.array([A - 8.0 / K, A + 8.0 / K], np.float32)
  f = f[np.isfinite(np.asarray(fam.paper_equation(spec_id, f, A, K)))]
  np.testing.assert_allclose(fn(f, A, K), fam.paper_equation(spec_id, f, A, K), atol=2e-3)


def test_deviations_from_printed_equations():
  # S9 (land speed <= a) rewards slow descent, S10 (climb >= a) fast climb, S11 (stay within radius) small deviation
  d = specs.drone_specs()
  assert (d["S9"].family, d["S10"].family, d["S11"].family) == ("keep_below", "keep_above", "keep_below")
  # printed S12 (drone) is one repeated factor decreasing in the margin; ours increases in both margins
  assert fam.paper_equation("S12", 10.0, 1.0, 0.5, v=10.0) < fam.paper_equation("S12", 2.0, 1.0, 0.5, v=10.0)
  assert fam.fence_hv(10.0, 10.0, 1.0, 0.5) > fam.fence_hv(2.0, 10.0, 1.0, 0.5)
  assert fam.fence(10.0, 1.0, 0.5) > fam.fence(2.0, 1.0, 0.5)


def _signals(n=()):
  s = {k: jnp.full(n, 1.0) for k in SIGNAL_NAMES}
  s.update(obstacle_distance=jnp.full(n, 20.0), altitude=jnp.full(n, 15.0), speed_xy=jnp.full(n, 8.0),
           in_takeoff=jnp.zeros(n), in_landing=jnp.zeros(n), in_loiter=jnp.zeros(n), in_cruise=jnp.ones(n),
           dist_wp=jnp.full(n, 3.0), wp_slack=jnp.full(n, 5.0), fence_margin=jnp.full(n, 5.0),
           fence_h=jnp.full(n, 20.0), fence_v=jnp.full(n, 5.0), path_deviation=jnp.full(n, 1.0))
  return s


def test_table_reward_shapes_guards_weights():
  d = specs.drone_specs()
  total, per = rewards.reward(_signals((4, 3)), d)
  assert total.shape == (4, 3) and per.shape == (4, 3, 12)
  per = np.asarray(per)[0, 0]
  names = d.names
  for guarded in ("S9", "S10", "S11"):  # phase off -> vacuously satisfied -> family maximum
    assert per[names.index(guarded)] == 1.0
  np.testing.assert_allclose(per[names.index("S1")], fam.two_sided(20.0, 5.0, 1.0), rtol=1e-6)
  np.testing.assert_allclose(per[names.index("S12")], fam.fence(5.0, 1.0, 0.5), rtol=1e-6)
  t1, p1 = rewards.reward(_signals(), d, normalize=True, critical_weight=3.0)
  w = np.array([3.0 if c else 1.0 for c in d.critical])
  np.testing.assert_allclose(t1, (np.asarray(p1) * w).sum() / w.sum(), rtol=1e-6)
  assert float(t1) <= 1.0
  # jit with the table static, and gradients flow to the signals
  f = jax.jit(lambda s: rewards.RewardFn.create(d)(s, normalize=True)[0])
  np.testing.assert_allclose(f(_signals()), rewards.reward(_signals(), d, normalize=True)[0], rtol=1e-6)
  g = jax.grad(lambda x: rewards.reward({**_signals(), "obstacle_distance": x}, d)[0])(4.0)
  assert g > 0


def test_binary_baseline():
  d = specs.drone_specs()
  s = _signals()
  total, per = rewards.binary_reward(s, d)
  assert set(np.unique(np.asarray(per))) <= {0.0, 1.0} and float(total) == 12.0
  s_bad = {**s, "obstacle_distance": jnp.array(3.0), "wp_slack": jnp.array(-1.0), "dist_wp": jnp.array(9.0)}
  _, per = rewards.binary_reward(s_bad, d)
  bad = {n for n, v in zip(d.names, np.asarray(per)) if v == 0}
  assert bad == {"S1", "S5", "S6"}
  s_land = {**s, "in_cruise": jnp.array(0.0), "in_landing": jnp.array(1.0), "descent_speed": jnp.array(0.9)}
  _, per = rewards.binary_reward(s_land, d)
  assert {n for n, v in zip(d.names, np.asarray(per)) if v == 0} == {"S9"}


def test_step_conditions_name_the_specs_judged_at_each_step():
  """Every built-in spec has a step condition; an added spec with a temporal body and no reward family has none
  (evaluation counts it as seen: never a blind violation)."""
  d = specs.drone_specs()
  assert rewards.RewardFn.create(d).step_conditions() == (True,) * 12
  t = specs.add_spec(d, "S13", "always(eventually[0s, 5s](altitude > 1))")
  assert rewards.RewardFn.create(t).step_conditions() == (True,) * 12 + (False,)
  t = specs.add_spec(d, "S13", "always(altitude > 1 and speed_xy < 20)")   # no family, a non-temporal body
  assert rewards.RewardFn.create(t).step_conditions()[-1]


def test_capped_reward_is_one_while_a_spec_holds_and_the_sigmoid_where_it_does_not():
  """Capped compliance: every spec that holds pays exactly 1 (so a compliant step totals the maximum and no compliant
  flight earns less than another), a violated one 2 sigma(k margin) < 1, continuous at the threshold."""
  d = specs.drone_specs()
  fn = rewards.RewardFn.create(d)
  s = _signals()
  total, per = fn(s, normalize=True, capped=True)
  assert float(total) == 1.0 and np.all(np.asarray(per)[np.asarray(fn.weights()) > 0] == 1.0)
  shaped_total, _ = fn(s, normalize=True)
  assert float(shaped_total) < 1.0   # the paper's sigmoids pay less than 1 for the same compliant step
  # obstacle at 3 m (CP_DIST 5 m, k 1/m): S1 and S6 violated, S5 too (no waypoint slack, 9 m from the waypoint)
  s_bad = {**s, "obstacle_distance": jnp.array(3.0), "wp_slack": jnp.array(-1.0), "dist_wp": jnp.array(9.0)}
  _, per = fn(s_bad, capped=True)
  per = dict(zip(d.names, np.asarray(per)))
  _, binary = fn(s_bad, binary=True)
  assert {n for n, v in per.items() if v < 1.0} == {n for n, v in zip(d.names, np.asarray(binary)) if v == 0}
  np.testing.assert_allclose(per["S1"], 2 * fam.sigmoid(1.0 * (3.0 - 5.0)), rtol=1e-6)
  np.testing.assert_allclose(per["S6"], 2 * fam.sigmoid(0.5 * (3.0 - 5.0)), rtol=1e-6)
  np.testing.assert_allclose(per["S5"], 2 * fam.sigmoid(0.25 * (d.params["NAV_ACC_RAD"] - 9.0)), rtol=1e-6)
  # landing at 0.9 m/s against MPC_LAND_SPEED 0.5: only S9, and just past the threshold it is ~1 (continuous)
  land = {**s, "in_cruise": jnp.array(0.0), "in_landing": jnp.array(1.0)}
  for v, expect in ((0.9, 2 * fam.sigmoid(8.0 * (0.5 - 0.9))), (0.5001, 1.0), (0.3, 1.0)):
    _, per = fn({**land, "descent_speed": jnp.array(v)}, capped=True)
    np.testing.assert_allclose(np.asarray(per)[d.names.index("S9")], expect, rtol=1e-3)


def test_residual_cost_scales_with_the_residual_where_it_is_in_effect():
  """TrainConfig.action_cost: 0 without a residual or where it is not in effect, `cost` at full scale on every axis,
  quadratic in between, per axis relative to the axis' speed scale."""
  from specguard_jax.ppo.networks import residual_cost
  speeds = (4.0, 4.0, 2.0)
  sp = jnp.array([[0.0, 0.0, 0.0], [4.0, -4.0, 2.0], [2.0, 0.0, 0.0], [0.0, 0.0, -1.0], [4.0, -4.0, 2.0]])
  active = jnp.array([1.0, 1.0, 1.0, 1.0, 0.0])
  np.testing.assert_allclose(residual_cost(sp, speeds, active, 0.05), [0.0, 0.05, 0.05 / 12, 0.05 / 12, 0.0],
                             rtol=1e-6)
  # speeds z = 0 (no vertical authority, --set speeds=[4,4,0]): that axis costs nothing, never 0 / 0 = NaN
  flat = residual_cost(jnp.array([[0.0, 0.0, 0.0], [4.0, -4.0, 0.0]]), (4.0, 4.0, 0.0), jnp.ones(2), 0.05)
  np.testing.assert_allclose(flat, [0.0, 0.05 * 2 / 3], rtol=1e-6)
  # an attitude residual (6 outputs): the velocity part costs what it did, the acceleration part as much again
  six = residual_cost(jnp.array([[4.0, -4.0, 2.0, 0.0, 0.0, 0.0], [4.0, -4.0, 2.0, 3.0, -3.0, 3.0]]),
                      speeds + (3.0, 3.0, 3.0), jnp.ones(2), 0.05)
  np.testing.assert_allclose(six, [0.05, 0.1], rtol=1e-6)


def test_s12_pays_beside_a_keep_out_prism_taller_than_the_vehicle():
  """15 m beside a keep-out prism whose top is 5 m above the drone: the spec holds (3D margin 15 m), so its shaped
  reward must be ~1 (the two-factor (h, v) product paid ~0 there: v = -5 m), and it falls as the margin closes."""
  d = specs.drone_specs()
  i = d.names.index("S12")
  beside = {**_signals(), "fence_margin": jnp.array(15.0), "fence_h": jnp.array(15.0), "fence_v": jnp.array(-5.0)}
  near = {**beside, "fence_margin": jnp.array(2.0), "fence_h": jnp.array(2.0)}
  r_far, r_near = (float(np.asarray(rewards.reward(s, d)[1])[i]) for s in (beside, near))
  assert r_far > 0.99 and r_near < r_far


def _onsets(trace, ev, w):
  """violation_onset per transition of a trace flown through the online monitor (settled robustness), and the
  final so-far robustness (= the whole-episode verdict)."""
  update = jax.jit(lambda m, s: (lambda m2, r: (m2, r, ev.settled(m2, r)))(*ev.monitor_update(m, s)[:2]))
  monitor, rob, before = update(ev.monitor_init(), trace[0])
  counts = []
  for s in trace[1:]:
    monitor, rob, after = update(monitor, s)
    counts.append(float(rewards.violation_onset(before, after, w)))
    before = after
  return np.asarray(counts), np.asarray(rob)


def test_violation_onset_counts_each_violated_spec_once_when_it_becomes_certain():
  """TrainConfig.violation_penalty's count, fed by the env's online STL monitor: S1 (critical) and S6 (obstacle
  within 5 m) from step 4 on, S9 (landing faster than 0.5 m/s) at step 7 only: each counts once, weighted, on its
  step. S7 (cruise at >= 5 m/s or within 10 m of the waypoint, with a 3 s grace): a 2 s slow stretch is no
  violation and counts nothing, though the so-far robustness dips below 0 during it; a 4 s one counts once, when the
  grace has run out. Over each episode the counts add up to the weighted count of specs violated at its end."""
  d = specs.drone_specs()
  ev = specs.compile_specs(d, 0.1)
  w = np.asarray(rewards.RewardFn.create(d).weights(critical_weight=3.0))
  i1, i6, i7, i9 = (d.names.index(k) for k in ("S1", "S6", "S7", "S9"))
  assert (w[i1], w[i6], w[i7], w[i9]) == (3.0, 1.0, 1.0, 1.0)
  trace = []
  for t in range(12):
    s = _signals()
    if t >= 4:
      s["obstacle_distance"] = jnp.array(2.0)
    if t >= 6:
      s.update(in_cruise=jnp.array(0.0), in_landing=jnp.array(1.0), descent_speed=jnp.array(0.3))
    if t == 7:
      s["descent_speed"] = jnp.array(1.5)
    trace.append(s)
  counts, final = _onsets(trace, ev, w)
  expect = np.zeros(11)
  expect[3] = w[i1] + w[i6]                  # trace step 4 is transition 3
  expect[6] = w[i9]
  np.testing.assert_allclose(counts, expect)
  assert np.isclose(counts.sum(), np.sum(w * (final < 0)))
  for slow_steps, violated in ((20, False), (40, True)):
    trace = [{**_signals(), "dist_wp": jnp.array(50.0),
              **({"speed_xy": jnp.array(1.0)} if 10 <= t < 10 + slow_steps else {})} for t in range(80)]
    counts, final = _onsets(trace, ev, w)
    assert (final[i7] < 0) == violated and counts.sum() == float(violated), slow_steps
    if violated:   # certain once the 3 s (30 steps) after the first slow step have passed
      assert int(np.flatnonzero(counts)[0]) + 1 == 10 + 30
  # NaN robustness (a failed physics step) counts as no onset
  assert float(rewards.violation_onset(jnp.zeros(12), jnp.full(12, jnp.nan), w)) == 0.0


def test_violation_onsets_of_an_auto_reset_step_judge_ended_episodes_on_their_final_verdict():
  """envs.wrappers.violation_onsets over a batch of 3 envs in one step: env 0 flies on into an obstacle (S1 and S6
  become certain), env 1 ended in the step and its final verdict violates S9 while the next episode's monitor (in
  the after-info) is clean, env 2 ended with S1 already charged before (nothing new)."""
  from envs.wrappers import violation_onsets
  d = specs.drone_specs()
  ev = specs.compile_specs(d, 0.1)
  w = np.asarray(rewards.RewardFn.create(d).weights(critical_weight=3.0))
  i1, i6, i9 = (d.names.index(k) for k in ("S1", "S6", "S9"))
  clean = _signals((3,))
  hit = {**clean, "obstacle_distance": jnp.array([20.0, 20.0, 2.0])}   # env 2 already violated S1 / S6
  m0, r0, _ = ev.monitor_update(ev.monitor_init((3,)), clean)
  m1, r1, _ = ev.monitor_update(m0, hit)
  before = {"spec_monitor": m1, "spec_robustness": r1}
  m2, r2, _ = ev.monitor_update(m1, {**hit, "obstacle_distance": jnp.array([2.0, 20.0, 2.0])})
  reset_m, reset_r, _ = ev.monitor_update(ev.monitor_init((3,)), clean)   # envs 1 and 2: the next episode's start
  pick = lambda a, b: jnp.where(jnp.array([True, False, False])[(...,) + (None,) * (a.ndim - 1)], a, b)  # noqa: E731
  final = np.asarray(r2).copy()
  final[1, i9] = -0.4                          # env 1's last window settled as a landing too fast
  after = {"spec_monitor": jax.tree.map(pick, m2, reset_m), "spec_robustness": pick(r2, reset_r),
           "final_spec_robustness": jnp.asarray(final)}
  got = np.asarray(violation_onsets(ev, w, before, after, jnp.array([0.0, 1.0, 1.0])))
  np.testing.assert_allclose(got, [w[i1] + w[i6], w[i9], 0.0])
