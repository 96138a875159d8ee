"""Sigmoid reward families of SpecGuard (paper Eq. 1 and appendix "Reward Functions for Mission Specifications").

Every family is a logistic of k times the spec's margin (its predicate robustness, > 0 satisfied): paper Eq. 1,
rho(S) = 1 / (1 + e^-S), with S = k * margin. All functions are elementwise over any shape, jittable, differentiable.
Units: f and a in the condition's unit (m, m/s, s), k in 1/unit.

Deviations from the printed appendix equations (`paper_equation` below reproduces them literally):
  1. Continuity. The printed forms are piecewise with a jump at the threshold a (S1: 0 -> 1, S2/S4/S5/S8/S10:
     0.5 -> 0, S3/S7/S9/S11: 0 -> 0.5, S6: 0.5 -> 1). We keep the printed sigmoid branch exactly and replace the
     constant branch by the sigmoid's own continuation, which tends to that constant a few 1/k away from a. So the
     reward is continuous and monotone in the margin, and a slight violation still has a gradient back to safety.
  2. S1 (two_sided): 2 sigma(k(f-a)) - 1 on both sides: the printed violated branch (-1, 0), then 0 at a rising to 1.
  3. S6 equals keep_above once made continuous (its printed form is keep_above with the branches' roles swapped);
     `s6` is kept as a named alias.
  4. S9 (descent speed <= MPC_LAND_SPEED) and S11 (stay within the loiter radius; STL `< 8`) are printed keep-above
     but mean keep-below; S10 (STL: climb rate >= MPC_TKO_SPEED) is printed keep-below but means keep-above. We use
     the meaning (the spec tables pick the family).
  5. S12 drone: the printed product repeats one factor 1/(1+e^{k(f-1)}) twice and decreases as the margin grows.
     `fence_hv` is its repaired form, sigma(k(h-m)) * sigma(k(v-m)) (an AND of horizontal and vertical margins: right
     for staying inside a cylinder); the spec tables use `fence`, sigma(k(f-m)) on the 3D fence_margin, for both
     vehicles, because our keep-out prisms are cleared by being beside OR above them (specs.table, S12).
  6. Outside a spec's phase guard the reward is the family's maximum (1), i.e. vacuous satisfaction (`reward.py`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

sigmoid = jax.nn.sigmoid


def keep_above(f, a, k):
  """Reward for `f > a` (S3 altitude, S6, S7 speed, S10 climb): sigma(k (f - a)) in (0, 1), 0.5 at f = a."""
  return sigmoid(k * (f - a))


def keep_below(f, a, k):
  """Reward for `f < a` (S2, S4, S5, S8, S9, S11): 1 / (1 + e^{k (f - a)}) in (0, 1), 0.5 at f = a."""
  return sigmoid(k * (a - f))


def two_sided(f, a, k):
  """S1 reward for `f > a`: 2 / (1 + e^{-k (f - a)}) - 1 in (-1, 1); negative when violated, 0 at f = a."""
  return 2.0 * sigmoid(k * (f - a)) - 1.0


def s6(f, a, k):
  """S6 reward (continuous form of the printed S6 equation; equals keep_above)."""
  return keep_above(f, a, k)


def fence_hv(h, v, m, k):
  """Drone S12: product of horizontal and vertical margin factors sigma(k (h - m)) sigma(k (v - m)) in (0, 1)."""
  return sigmoid(k * (h - m)) * sigmoid(k * (v - m))


def fence(f, m, k):
  """Rover S12: sigma(k (f - m)) on the fence margin f (m)."""
  return sigmoid(k * (f - m))


def margin(family: str, fs, a):
  """Instantaneous margin (> 0 satisfied) of a family's condition: fs is the tuple of condition values."""
  if family == "keep_below":
    return a - fs[0]
  if family == "fence_hv":
    return jnp.minimum(fs[0] - a, fs[1] - a)
  return fs[0] - a


def shaped(family: str, fs, a, k):
  """Dispatch: reward of `family` for condition values `fs` (tuple), threshold `a`, constant `k`."""
  if family == "fence_hv":
    return fence_hv(fs[0], fs[1], a, k)
  fn = {"keep_above": keep_above, "keep_below": keep_below, "two_sided": two_sided, "s6": s6, "fence": fence}[family]
  return fn(fs[0], a, k)


def paper_equation(spec_id: str, f, a, k, v=None):
  """The appendix's printed piecewise equation for spec `spec_id` ("S1".."S12", "S12_rover"), literally (NaN where
  the printed cases do not define a value, e.g. f <= 0 for S1/S2/S5/S6, f == a, or mixed h/v cases for S12)."""
  f = jnp.asarray(f, jnp.float32)
  nan = jnp.full_like(f, jnp.nan)
  above, below = f > a, f < a
  pos = f > 0
  if spec_id == "S1":
    return jnp.where(above, 1.0, jnp.where(pos & below, 2 * sigmoid(k * (f - a)) - 1, nan))
  if spec_id in ("S2", "S5"):
    return jnp.where(above, 0.0, jnp.where(pos & below, sigmoid(-k * (f - a)), nan))
  if spec_id in ("S4", "S8", "S10"):
    return jnp.where(above, 0.0, jnp.where(below, sigmoid(-k * (f - a)), nan))
  if spec_id in ("S3", "S7", "S9", "S11"):
    return jnp.where(below, 0.0, jnp.where(above, sigmoid(k * (f - a)), nan))
  if spec_id == "S6":
    return jnp.where(above, 1.0, jnp.where(pos & below, sigmoid(k * (f - a)), nan))
  if spec_id == "S12":  # f = h here, v the vertical margin; printed product repeats one factor of f
    both_in, both_out = (f > 1) & (v > 1), (f < 1) & (v < 1)
    return jnp.where(both_out, 0.0, jnp.where(both_in, sigmoid(-k * (f - 1)) ** 2, nan))
  if spec_id == "S12_rover":
    return jnp.where(f < 1, 0.0, jnp.where(f > 1, sigmoid(-k * (f - 1)), nan))
  raise ValueError(f"unknown spec id {spec_id!r}")
