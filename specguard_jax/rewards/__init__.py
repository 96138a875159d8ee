"""SpecGuard rewards: sigmoid families (paper appendix, made continuous) and the per-step reward of a spec table.

  keep_above(f, a, k), keep_below(f, a, k), two_sided(f, a, k), s6(f, a, k), fence_hv(h, v, m, k), fence(f, m, k)
  reward(signals_t, table, normalize=False, critical_weight=1.0) -> (total [...], per_spec [..., n])
  binary_reward(signals_t, table, ...) -> same shapes, 0/1 per spec ; RewardFn.create(table) compiled form.
"""

from specguard_jax.rewards.families import (fence, fence_hv, keep_above, keep_below, paper_equation, s6, shaped,
                                            two_sided)
from specguard_jax.rewards.reward import RewardFn, binary_reward, reward, survival_reward, violation_onset
