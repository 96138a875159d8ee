"""Wrappers that fit our per-episode randomised envs (the rest of Brax's training wrappers work as they are)."""

from __future__ import annotations

import jax
from brax.envs.base import State, Wrapper

from envs.base import tree_where


class AutoReset(Wrapper):
  """Resets finished episodes with a NEW mission, world and domain sample (Brax's AutoResetWrapper replays a cached
  first state). Works on a single or a batched (VmapWrapper-ed) env.

  The returned state of a finished episode carries the fresh episode's obs/info, but the finished step's reward,
  done and metrics; `info['truncation']` is the finished step's, and `info['last_episode']` holds the finished
  episode's flags (collision, crash, stall, complete, ...), valid where done.
  """

  def reset(self, rng: jax.Array) -> State:
    state = self.env.reset(rng)
    keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(rng) if rng.ndim > 1 else jax.random.fold_in(rng, 1)
    info = dict(state.info, reset_key=keys, last_episode=state.info["episode"])
    return state.replace(info=info)

  def step(self, state: State, action: jax.Array) -> State:
    reset_key = state.info["reset_key"]
    split = (jax.vmap(jax.random.split) if reset_key.ndim > 1 else jax.random.split)(reset_key)
    next_key, sub = split[..., 0, :], split[..., 1, :]
    inner = dict(state.info)
    inner.pop("reset_key")
    inner.pop("last_episode")
    out = self.env.step(state.replace(info=inner), action)
    fresh = self.env.reset(sub)
    done = out.done > 0
    merged = tree_where(done, fresh.replace(reward=out.reward, done=out.done, metrics=out.metrics), out)
    info = dict(merged.info, truncation=out.info["truncation"], reset_key=next_key, last_episode=out.info["episode"])
    return merged.replace(info=info)
