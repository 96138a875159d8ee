"""Per-step SpecGuard reward from a spec table: shaped (sigmoid families) and binary baseline.

`RewardFn.create(table)` compiles the table's reward fields once; `reward(signals_t, table)` is the one-call form.
Per spec i at one step: if the spec's phase guard is inactive the reward is 1 (vacuously satisfied), else the
family's value of its condition(s) f against threshold a. Total = sum_i w_i rho_i, with w_i = critical_weight for
critical specs (S1, S2, S12) and 1 otherwise; `normalize=True` divides by sum_i w_i (paper Algorithm 1's
normalize()), so a fully satisfied step scores ~1. Specs of family "none" (monitored only) get 0 and weight 0.
Binary baseline: 1 when satisfied and 0 when violated, per spec per step: the truth (robustness >= 0) of the body
of `always(body)` at this step when the body is non-temporal (S1-S6, S8, S9, S11, S12), else (S7, S10, whose body
has a grace window) of `guard -> condition` from the reward fields.
Capped compliance (`capped=True`): 1 wherever the binary reward is 1; where the step violates the spec, the
compliance sigmoid of the margin rescaled to reach 1 at the threshold, 2 sigma(k margin) in (0, 1) (a gradient back
to safety). Every compliant step then earns exactly the maximum, so no compliant trajectory earns less than another
(no pay for clearance beyond the threshold, none for rushing to a waypoint while the spec still holds) and the
completion bonus of 1 / (1 - gamma) per unit reward (ppo.config.TrainConfig.completion_bonus) is time-neutral for a
compliant flight. Why it exists: docs/DESIGN.md "Reward".

Default k constants (the paper leaves k unspecified; chosen so the reward moves from 0.5 at the threshold to ~0.98
about one "natural scale" inside the safe side): S1 1/m (obstacle, a = 5 m), S2 0.5/m (path, 10 m), S3/S4 0.5/m
(altitude), S5 0.25/m (waypoint distance: long-range pull), S6 0.5/m, S7/S8 1 s/m (speeds), S9 8 s/m (0.5 m/s
landing), S10 2 s/m (climb), S11 0.5/m (loiter), S12 0.5/m (fence). They live in the spec table (Spec.k).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional, Tuple

import jax.numpy as jnp

from specguard_jax import stl
from specguard_jax.rewards import families
from specguard_jax.specs.table import SpecTable, _parse
from specguard_jax.stl.offline import evaluate, predicate_value


@dataclasses.dataclass(frozen=True)
class _Term:
  family: str
  k: float
  exprs: Tuple[stl.Predicate, ...]
  threshold: float
  guard: Optional[stl.Formula]
  critical: bool
  body: Optional[stl.Formula]  # non-temporal body of `always(body)`, used by the binary baseline


@dataclasses.dataclass(frozen=True)
class RewardFn:
  """Compiled per-step reward of a spec table (hashable)."""

  names: Tuple[str, ...]
  terms: Tuple[_Term, ...]

  @staticmethod
  def create(table: SpecTable) -> "RewardFn":
    p = table.params
    terms = []
    for s in table.specs:
      exprs = tuple(_parse(s, p, f"({e}) > 0", "reward signal") for e in s.reward_signals)
      guard = _parse(s, p, s.reward_guard, "reward guard") if s.reward_guard else None
      thr = table.threshold(s) if s.family != "none" else 0.0
      f = table.formula(s.name)
      body = None
      if isinstance(f, stl.Always) and f.interval is None and not stl.is_temporal(f.arg):
        body = f.arg
      terms.append(_Term(s.family, float(s.k), exprs, thr, guard, s.critical, body))
    return RewardFn(table.names, tuple(terms))

  def weights(self, critical_weight: float = 1.0) -> jnp.ndarray:
    return jnp.array([0.0 if t.family == "none" else (critical_weight if t.critical else 1.0) for t in self.terms],
                     jnp.float32)

  def step_conditions(self) -> Tuple[bool, ...]:
    """Per spec: whether it has a pass/fail condition at each step (per_spec(binary=True)): an always() over a
    non-temporal body, or a reward family's margin. A spec with neither (a temporal body, no family) has none."""
    return tuple(t.body is not None or t.family != "none" for t in self.terms)

  def per_spec(self, signals_t: Mapping[str, jnp.ndarray], binary: bool = False, capped: bool = False) -> jnp.ndarray:
    """Per-spec reward [..., n] for one step (signals_t: {name: [...]}); binary / capped: see the module docstring."""
    sig = {n: jnp.asarray(v, jnp.float32) for n, v in signals_t.items()}
    shape = jnp.broadcast_shapes(*[v.shape for v in sig.values()])
    out = []
    for t in self.terms:
      if binary and t.body is not None:
        out.append(jnp.broadcast_to((evaluate(t.body, sig) >= 0).astype(jnp.float32), shape))
        continue
      if t.family == "none":
        out.append(jnp.zeros(shape, jnp.float32))
        continue
      fs = tuple(predicate_value(e, sig) for e in t.exprs)
      if binary:
        r = (families.margin(t.family, fs, t.threshold) >= 0).astype(jnp.float32)
      elif capped:
        margin = families.margin(t.family, fs, t.threshold)
        holds = evaluate(t.body, sig) >= 0 if t.body is not None else margin >= 0
        r = jnp.where(holds, 1.0, jnp.minimum(2.0 * families.sigmoid(t.k * margin), 1.0))
      else:
        r = families.shaped(t.family, fs, t.threshold, t.k)
      if t.guard is not None:
        r = jnp.where(evaluate(t.guard, sig) > 0, r, 1.0)
      out.append(jnp.broadcast_to(r, shape))
    return jnp.stack(out, axis=-1)

  def __call__(self, signals_t: Mapping[str, jnp.ndarray], normalize: bool = False, critical_weight: float = 1.0,
               binary: bool = False, capped: bool = False) -> Tuple[jnp.ndarray, jnp.ndarray]:
    """(total [...], per_spec [..., n]) for one step; see the module docstring."""
    per = self.per_spec(signals_t, binary, capped)
    w = self.weights(critical_weight)
    total = jnp.sum(per * w, axis=-1)
    if normalize:
      total = total / jnp.maximum(jnp.sum(w), 1e-12)
    return total, per


def reward(signals_t: Mapping[str, jnp.ndarray], table: SpecTable, normalize: bool = False,
           critical_weight: float = 1.0) -> Tuple[jnp.ndarray, jnp.ndarray]:
  """Shaped SpecGuard reward for one step: (total [...], per_spec [..., n_specs])."""
  return RewardFn.create(table)(signals_t, normalize, critical_weight)


def binary_reward(signals_t: Mapping[str, jnp.ndarray], table: SpecTable, normalize: bool = False,
                  critical_weight: float = 1.0) -> Tuple[jnp.ndarray, jnp.ndarray]:
  """Binary baseline (1 satisfied, 0 violated per spec per step): (total [...], per_spec [..., n_specs])."""
  return RewardFn.create(table)(signals_t, normalize, critical_weight, binary=True)


def violation_onset(settled_before, settled_after, weights) -> jnp.ndarray:
  """Weighted count [...] of the specs whose violation became certain in one step, sum_i w_i [after_i < 0 <=
  before_i] (settled robustness [..., n] before and after the step: specs.SpecEvaluator.settled; weights [n],
  RewardFn.weights). For a spec `always(psi)` with psi bounded (every spec of the built-in tables) the settled value
  never rises within an episode, so it counts at most once, on the step the mission became a violation of it in
  the SVR sense; another formula's settled value is its so-far robustness, which can rise again, so it may count
  more than once. A NaN counts as no onset (the step that produced it ends the episode as a failure anyway)."""
  before, after = jnp.asarray(settled_before), jnp.asarray(settled_after)
  onset = (after < 0) & (before >= 0)
  return jnp.sum(jnp.where(onset, jnp.asarray(weights, jnp.float32), 0.0), axis=-1)


def survival_reward(failed) -> jnp.ndarray:
  """Survival reward of the FTC baseline (specguard_jax.baselines.ftc; no spec terms): 1.0 per step the vehicle
  flies on, 0.0 on the step it crashes, collides or its physics fails (`failed` [...] bool; the episode ends there)."""
  return 1.0 - jnp.asarray(failed, jnp.float32)
