"""Auto-reset that fits our per-episode randomised envs (Brax's other training wrappers work as they are).

Brax's AutoResetWrapper restores a cached first state (every episode would replay the same mission, world and domain
sample) and ignores `State.info`, where our episode state lives. Generating a fresh mission + world for every env on
every step (to select it where done) would cost a full reset per env per step. `AutoReset` instead keeps a pool of
pre-generated initial states and refreshes `refresh` of them per step (round robin): finished episodes take the next
pool entries, so each new episode gets a new mission/world/domain sample as long as fewer than `refresh` episodes
end per step on average (otherwise some pool entries are reused before being regenerated: their episodes start from
the same mission but diverge through their own rng). Defaults: pool = max(8, B/8), refresh = max(1, B/128).

`refresh_in_step=False` leaves the pool alone in `step`; the caller then regenerates it in bulk with `refresh_pool`
(the trainer does, once per rollout of `steps` env steps: the same number of fresh entries, `refresh` per step, capped
at the pool size). A step then costs no reset at all: the per-step refresh (a vmapped reset of B/128 envs plus one
pool write per state leaf) is most of AutoReset's extra GPU kernels per env step (`bench/env_profile.py`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import State, Wrapper

from envs.base import tree_where
from specguard_jax import rewards as rewards_lib

_POOL_KEYS = ("reset_pool", "pool_cursor", "pool_refresh", "reset_key", "last_episode", "final_obs",
              "final_spec_robustness")


class AutoReset(Wrapper):
  """Batched auto-reset from a refreshed pool of initial states; wrap a VmapWrapper-ed env (leading batch axis B).

  After a step, a finished env carries the fresh episode's obs/info but the finished step's reward, done and
  metrics; `info['truncation']` is the finished step's, `info['last_episode']` the finished episode's flags,
  `info['final_obs']` the observation the step produced before any reset (for bootstrapping truncated episodes) and
  `info['final_spec_robustness']` the finished episode's per-spec robustness.
  """

  def __init__(self, env, pool_size: int | None = None, refresh: int | None = None, refresh_in_step: bool = True,
               reset_chunk: int = 65_536):
    """reset_chunk: most envs one vmapped reset generates at once; `reset` makes the envs and the pool in equal
    chunks of at most this many, one after another (lax.map), so its working memory stops growing with the batch
    (a drone reset's temporaries are ~84 KB per env: 1,048,576 envs and their pool in one go need ~82 GiB, more
    than a GPU's memory)."""
    super().__init__(env)
    if reset_chunk < 1:
      raise ValueError(f"reset_chunk must be >= 1, got {reset_chunk}")
    self._pool_size = pool_size
    self._refresh = refresh
    self._refresh_in_step = refresh_in_step
    self._reset_chunk = reset_chunk

  def _sizes(self, batch):
    pool = self._pool_size or max(8, batch // 8)
    return pool, min(pool, self._refresh or max(1, batch // 128))

  def reset(self, rng: jax.Array) -> State:
    batch = rng.shape[0]
    pool_n, _ = self._sizes(batch)
    k_pool, k_next = jax.random.split(jax.random.fold_in(rng[0], 0x5eed))
    # the envs and the pool in one vmapped reset (each env's state depends on its key only): one copy of the reset
    # program for XLA to compile, not one per batch size
    both = self._reset_chunked(jnp.concatenate([rng, jax.random.split(k_pool, pool_n)]))
    state, pool = jax.tree.map(lambda x: x[:batch], both), jax.tree.map(lambda x: x[batch:], both)
    info = dict(state.info, reset_pool=pool, pool_cursor=jnp.zeros((), jnp.int32),
                pool_refresh=jnp.zeros((), jnp.int32), reset_key=k_next, last_episode=state.info["episode"],
                final_obs=state.obs, final_spec_robustness=state.info["spec_robustness"])
    return state.replace(info=info)

  def _reset_chunked(self, keys: jax.Array) -> State:
    """self.env.reset(keys) for keys [N, ...], in ceil(N / reset_chunk) equal chunks (the last padded with repeated
    keys, their states dropped) when N > reset_chunk; each env's state depends on its key only."""
    n = keys.shape[0]
    if n <= self._reset_chunk:
      return self.env.reset(keys)
    chunks = -(-n // self._reset_chunk)
    per = -(-n // chunks)
    padded = jnp.concatenate([keys, keys[:chunks * per - n]])
    out = jax.lax.map(self.env.reset, padded.reshape((chunks, per) + keys.shape[1:]))
    return jax.tree.map(lambda x: x.reshape((chunks * per,) + x.shape[2:])[:n], out)

  def step(self, state: State, action: jax.Array) -> State:
    info = state.info
    pool, cursor, ref_ptr = info["reset_pool"], info["pool_cursor"], info["pool_refresh"]
    pool_n = pool.done.shape[0]
    batch = state.done.shape[0]
    _, refresh = self._sizes(batch)
    inner = {k: v for k, v in info.items() if k not in _POOL_KEYS}
    out = self.env.step(state.replace(info=inner), action)
    with jax.named_scope("autoreset"):
      merged, taken = self._take_fresh(out, pool, cursor)
      # What the finished step leaves for the caller's bookkeeping goes out through a barrier: a caller that reduces
      # it over the batch (the trainer's episode statistics) would otherwise get its reductions fused with the
      # selects above, which read the same values, into one slow reduction-rooted kernel (about half of the
      # auto-reset's GPU time).
      last, final_obs, final_rob = jax.lax.optimization_barrier(
          (out.info["episode"], out.obs, out.info["spec_robustness"]))
    new_info = dict(merged.info, truncation=out.info["truncation"], reset_pool=pool, final_obs=final_obs,
                    final_spec_robustness=final_rob,
                    pool_cursor=((cursor + taken) % pool_n).astype(jnp.int32), pool_refresh=ref_ptr,
                    reset_key=info["reset_key"], last_episode=last)
    merged = merged.replace(info=new_info)
    if self._refresh_in_step:
      merged = self._regenerate(merged, refresh)
    return merged

  def _take_fresh(self, out: State, pool: State, cursor):
    """(out with its finished envs replaced by consecutive pool entries from `cursor`, keeping the finished step's
    reward, done and metrics; [] int32 number of entries taken).

    The selects read `done` and the pool index through an optimization barrier and the count comes from the prefix
    sum's last entry: otherwise XLA fused the selects of every state leaf with reductions over `done` into
    reduction-rooted kernels that ran several times slower than memory-bound on a GPU."""
    done = out.done > 0
    rank = jnp.cumsum(done.astype(jnp.int32)) - 1
    sel, idx = jax.lax.optimization_barrier((done, (cursor + rank) % pool.done.shape[0]))
    fresh = jax.tree.map(lambda x: x[idx], pool)
    merged = tree_where(sel, fresh.replace(reward=out.reward, done=out.done, metrics=out.metrics), out)
    return merged, rank[-1] + 1

  def refresh_pool(self, state: State, steps: int) -> State:
    """Regenerates the pool entries `steps` env steps of in-step refreshing would have (min(pool, refresh x steps),
    round robin, new missions/worlds); for a wrapper built with refresh_in_step=False, called between rollouts."""
    pool_n = state.info["reset_pool"].done.shape[0]
    _, refresh = self._sizes(state.done.shape[0])
    return self._regenerate(state, min(pool_n, refresh * steps))

  def _regenerate(self, state: State, n: int) -> State:
    """Replaces n (static) consecutive pool entries from the refresh pointer (round robin) with fresh resets."""
    info = state.info
    pool, ref_ptr = info["reset_pool"], info["pool_refresh"]
    pool_n = pool.done.shape[0]
    key, sub = jax.random.split(info["reset_key"])
    keys = jax.random.split(sub, n)
    if n == pool_n:
      # The whole pool (the trainer's bulk refresh with its default sizes): entry j goes to slot (ref_ptr + j) % n,
      # so reset the keys in slot order and take the result as the pool. The same states as the scatter below
      # without its one scatter kernel per state leaf (over a third of the drone's pool-refresh kernels).
      pool = self._reset_chunked(keys[(jnp.arange(n) - ref_ptr) % n])
    else:
      new = self._reset_chunked(keys)
      slots = (ref_ptr + jnp.arange(n)) % pool_n
      pool = jax.tree.map(lambda p, x: p.at[slots].set(x), pool, new)
    return state.replace(info=dict(info, reset_pool=pool, reset_key=key,
                                   pool_refresh=((ref_ptr + n) % pool_n).astype(jnp.int32)))


def violation_onsets(spec_eval, weights, info_before: dict, info_after: dict, done) -> jax.Array:
  """Weighted count [...] of the specs whose violation became certain in one AutoReset step (rewards.violation_onset
  on specs.SpecEvaluator.settled): info_before / info_after the batch's infos before and after the step ('spec_monitor',
  'spec_robustness'), done [...], weights [n_specs]. An episode that ended in the step is judged on its whole-episode
  robustness ('final_spec_robustness': its monitor has been replaced by the next episode's), which also settles what
  was still open at its end. A violation already in an episode's first sample (the reset's) is not counted: no
  action caused it."""
  before = spec_eval.settled(info_before["spec_monitor"], info_before["spec_robustness"])
  after = spec_eval.settled(info_after["spec_monitor"], info_after["spec_robustness"])
  after = jnp.where(jnp.asarray(done)[..., None] > 0, info_after["final_spec_robustness"], after)
  return rewards_lib.violation_onset(before, after, weights)
