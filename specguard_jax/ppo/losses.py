"""PPO pieces kept apart from acting: agent state, GAE, the clipped loss and the minibatch-epoch update.

Shapes: T = unroll length, B = envs. All functions are pure and jittable.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from specguard_jax import third_party  # noqa: F401 - before brax: mujoco.mjx without its Warp notices
from brax.training.acme import running_statistics, specs
from flax import struct
from jax.flatten_util import ravel_pytree

from specguard_jax.ppo import networks
from specguard_jax.ppo.config import PPOConfig


@struct.dataclass
class AgentState:
  """One learner: policy + value params, their Adam state, the observation normaliser and update count."""
  params: Any          # {'policy': ..., 'value': ...}
  opt_state: Any       # the optimizer's state over the raveled params (flat [P] moment vectors, see `update`)
  normalizer: running_statistics.RunningStatisticsState
  updates: jnp.ndarray


@struct.dataclass
class Agent:
  """Static description of a learner (not a pytree of arrays): its policy, value net, optimiser and PPO config."""
  policy: networks.Policy = struct.field(pytree_node=False)
  value: Any = struct.field(pytree_node=False)
  optimizer: Any = struct.field(pytree_node=False)
  ppo: PPOConfig = struct.field(pytree_node=False)
  obs_clip: float = struct.field(pytree_node=False, default=10.0)

  def init(self, key, n_obs: int) -> AgentState:
    k1, k2 = jax.random.split(key)
    params = {"policy": self.policy.init(k1, n_obs),
              "value": self.value.init(k2, jnp.zeros((1, n_obs)))["params"]}
    norm = running_statistics.init_state(specs.Array((n_obs,), jnp.float32))
    return AgentState(params=params, opt_state=self.optimizer.init(ravel_pytree(params)[0]), normalizer=norm,
                      updates=jnp.zeros((), jnp.int32))

  def normalize(self, state: AgentState, obs):
    return jnp.clip(running_statistics.normalize(obs, state.normalizer), -self.obs_clip, self.obs_clip)

  def act(self, state: AgentState, obs, key):
    """(action, log_prob, value) for raw observations obs [.., n_obs]."""
    x = self.normalize(state, obs)
    a, logp = self.policy.sample(state.params["policy"], x, key)
    return a, logp, self.value_of(state, obs, normalized=x)

  def sample(self, state: AgentState, obs, key):
    """(action, log_prob) for raw observations obs [.., n_obs], without the value."""
    return self.policy.sample(state.params["policy"], self.normalize(state, obs), key)

  def value_of(self, state: AgentState, obs, normalized=None):
    x = self.normalize(state, obs) if normalized is None else normalized
    return self.value.apply({"params": state.params["value"]}, x)[..., 0]


HPARAMS = ("lr", "ent_coef", "clip_eps", "vf_coef")
"""PPO hyperparameters kept as data in the optimizer state (optax.inject_hyperparams), so a sweep over them is one
vmapped program (train.py --sweep): opt_state.hyperparams[name] is a float32 scalar per agent."""


def _adam(lr, frac, ent_coef, clip_eps, vf_coef, max_grad_norm):
  del ent_coef, clip_eps, vf_coef   # carried for ppo_loss, not used by the optimizer
  return optax.chain(optax.clip_by_global_norm(max_grad_norm), optax.adam(lr * frac, eps=1e-5))


def make_agent(policy: networks.Policy, value_hidden, activation, ppo: PPOConfig, total_updates: int,
               obs_clip: float = 10.0) -> Agent:
  """Agent with Adam (global-norm gradient clipping, constant or linearly decaying step size); lr, ent_coef,
  clip_eps and vf_coef are data in the optimizer state (see HPARAMS). The value network computes in the policy's
  dtype."""
  frac = (optax.linear_schedule(1.0, ppo.lr_end_frac, max(1, total_updates)) if ppo.lr_schedule == "linear"
          else 1.0)
  opt = optax.inject_hyperparams(_adam, static_args=("max_grad_norm",))(
      lr=ppo.lr, frac=frac, ent_coef=ppo.ent_coef, clip_eps=ppo.clip_eps, vf_coef=ppo.vf_coef,
      max_grad_norm=ppo.max_grad_norm)
  return Agent(policy=policy, value=networks.value_module(value_hidden, activation, policy.dtype), optimizer=opt,
               ppo=ppo, obs_clip=obs_clip)


def with_hparams(state: AgentState, ppo: PPOConfig) -> AgentState:
  """The agent state with its data hyperparameters (HPARAMS) set from `ppo` (float32 scalars, or any leading
  member axis the state has)."""
  hp = dict(state.opt_state.hyperparams)
  for k in HPARAMS:
    hp[k] = jnp.full(hp[k].shape, getattr(ppo, k), hp[k].dtype)
  return state.replace(opt_state=state.opt_state._replace(hyperparams=hp))


def gae(rewards, values, next_values, terminated, done, gamma: float, lam: float):
  """Generalised advantage estimation over [T, B].

  next_values[t] = V of the observation step t produced (before any auto-reset), so a truncated episode is
  bootstrapped from its own last state; terminated[t] zeroes the bootstrap (termination is not bootstrapped);
  done[t] cuts the GAE recursion at episode ends. Returns (advantages, value targets), both [T, B].
  """
  delta = rewards + gamma * next_values * (1.0 - terminated) - values

  def body(carry, xs):
    d, dn = xs
    adv = d + gamma * lam * (1.0 - dn) * carry
    return adv, adv

  _, adv = jax.lax.scan(body, jnp.zeros_like(values[0]), (delta, done), reverse=True)
  return adv, adv + values


def _sums(*terms):
  """[k] sums of k same-shaped terms, one stacked reduction."""
  return jnp.sum(jnp.stack([t.reshape(-1) for t in terms]), axis=1)


def minibatch_norms(ppo: PPOConfig, batch) -> dict:
  """What ppo_loss divides by, from a whole minibatch (mask, adv [..]): n (its unmasked rows, >= 1), size (all its
  rows), and with advantage normalisation the advantages' masked mean mu and standard deviation sd. Passing a whole
  minibatch's norms to ppo_loss on each of its chunks makes the chunks' losses (and gradients) sum to the whole's."""
  mask, adv = batch["mask"], batch["adv"]
  count, s_adv = _sums(mask, adv * mask)   # s_adv is dead code (dropped) without advantage normalisation
  norms = {"n": jnp.maximum(count, 1.0), "size": mask.size}
  if ppo.normalize_advantage:
    norms["mu"] = s_adv / norms["n"]
    norms["sd"] = jnp.sqrt(jnp.sum(mask * (adv - norms["mu"]) ** 2) / norms["n"]) + 1e-8   # exact however far mu is
  return norms


def ppo_loss(agent: Agent, params, normalizer, batch, hp=None, norms=None):
  """Clipped PPO loss on a minibatch dict (obs, action, logp, value, adv, target, mask [..]). hp: {clip_eps,
  ent_coef, vf_coef} as data (default: the agent's PPOConfig). norms: minibatch_norms of the whole minibatch when
  `batch` is one chunk of it (default: of `batch`). Returns (loss, aux).

  The minibatch sums are taken as stacked reductions (mask count with the advantage sum; the surrogate, entropy,
  value-error and KL terms together) rather than one per statistic: on a GPU each sum over a 65,536-row minibatch is
  a launch-bound kernel or two of its own, 32 minibatch steps per training iteration
  (tests/test_train.py::test_ppo_loss_equals_the_one_sum_per_statistic_form).
  """
  p = agent.ppo
  hp = hp or {"clip_eps": p.clip_eps, "ent_coef": p.ent_coef, "vf_coef": p.vf_coef}
  x = jnp.clip(running_statistics.normalize(batch["obs"], normalizer), -agent.obs_clip, agent.obs_clip)
  logp, ent = agent.policy.log_prob_entropy(params["policy"], x, batch["action"])
  v = agent.value.apply({"params": params["value"]}, x)[..., 0]
  mask = batch["mask"]
  adv = batch["adv"]
  norms = norms or minibatch_norms(p, batch)
  n = norms["n"]
  if p.normalize_advantage:
    adv = (adv - norms["mu"]) / norms["sd"]
  ratio = jnp.exp(logp - batch["logp"])
  surr = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - hp["clip_eps"], 1.0 + hp["clip_eps"]) * adv)
  v_err = (v - batch["target"]) ** 2
  if p.value_clip_eps > 0:
    v_clip = batch["value"] + jnp.clip(v - batch["value"], -p.value_clip_eps, p.value_clip_eps)
    v_err = jnp.maximum(v_err, (v_clip - batch["target"]) ** 2)
  kl = jax.lax.stop_gradient((ratio - 1.0) - (logp - batch["logp"]))   # a diagnostic, not differentiated
  s_surr, s_ent, s_verr, s_kl = _sums(surr * mask, ent * mask, v_err, kl * mask)
  pg_loss = -s_surr / n
  v_loss = 0.5 * s_verr / norms["size"]
  entropy = s_ent / n
  loss = pg_loss + hp["vf_coef"] * v_loss - hp["ent_coef"] * entropy
  return loss, {"pg_loss": pg_loss, "v_loss": v_loss, "entropy": entropy, "approx_kl": s_kl / n}


_LOSS_STATS = ("pg_loss", "v_loss", "entropy", "approx_kl")   # ppo_loss's aux, in this order


def chunks_per_minibatch(ppo: PPOConfig, rows_per_group: int, groups_per_device: int) -> int:
  """Chunks each minibatch's gradient is taken in: the fewest that divide a group's `rows_per_group` minibatch rows
  and leave at most ppo.max_rows_per_pass rows per device in one pass (groups_per_device groups, or vmapped sweep
  members' groups, share a device)."""
  need = -(-rows_per_group * groups_per_device // ppo.max_rows_per_pass)
  return next(c for c in range(max(1, need), rows_per_group + 1) if rows_per_group % c == 0)


def update(agent: Agent, state: AgentState, batch, key, groups: int = 1, constrain=None, chunks: int = 1):
  """Normaliser update on the batch's observations, then epochs x minibatches of Adam on the PPO loss.

  batch: dict of [T, B, ...] arrays (see ppo_loss). groups: G env groups (B = G x B/G, the groups axis is the one
  sharded over devices, ppo/distributed.py): each epoch shuffles inside each group and every minibatch takes the
  same number of samples from each group, so the shuffle never crosses devices; G = 1 is a plain global shuffle.
  constrain: optional fn applied to [G, ...] arrays (a sharding constraint). chunks: each minibatch's gradient is
  the sum of this many chunks' (chunks_per_minibatch; each chunk takes the same rows of every group), so the
  networks' activations are those of one chunk. A non-finite gradient step is skipped (params unchanged) and counted
  in aux['nan_skips'], so NaNs never reach the parameters.
  """
  p = agent.ppo
  constrain = constrain or (lambda t: t)
  T, B = batch["mask"].shape[:2]
  # [T, B, ...] -> [G, T * B/G, ...] (time-major inside a group)
  flat = jax.tree.map(lambda a: jnp.swapaxes(a.reshape((T, groups, B // groups) + a.shape[2:]), 0, 1).reshape(
      (groups, T * (B // groups)) + a.shape[2:]), batch)
  flat = constrain(flat)
  n = T * (B // groups)
  normalizer = running_statistics.update(state.normalizer, flat["obs"])
  hp = {k: state.opt_state.hyperparams[k] for k in ("clip_eps", "ent_coef", "vf_coef")}
  # The minibatch steps work on the raveled params (one [P] vector): the gradient arrives as one vector and the
  # clipping norm, Adam, the finiteness check and the skip-select are a handful of kernels per step instead of a few
  # per parameter array.
  theta0, unravel = ravel_pytree(state.params)
  loss_of_flat = lambda theta, mb, norms=None: ppo_loss(agent, unravel(theta), normalizer, mb, hp, norms)  # noqa: E731
  grad_fn = jax.value_and_grad(loss_of_flat, has_aux=True)
  if (n // p.num_minibatches) % chunks:
    raise ValueError(f"chunks ({chunks}) must divide a group's minibatch rows ({n // p.num_minibatches})")

  def minibatch_grad(theta, mb):
    """((loss, aux), gradient) of one minibatch [G, n / M, ...], summed over its chunks."""
    if chunks == 1:
      return grad_fn(theta, mb)
    norms = minibatch_norms(p, mb)
    # [G, n / M, ...] -> [C, G, n / (M C), ...]
    parts = jax.tree.map(lambda a: jnp.swapaxes(a.reshape((a.shape[0], chunks, -1) + a.shape[2:]), 0, 1), mb)

    def chunk(total, part):
      out = grad_fn(theta, constrain(part), norms)
      return jax.tree.map(jnp.add, total, out), None

    zero = jax.tree.map(jnp.zeros_like, jax.eval_shape(grad_fn, theta, mb))
    return jax.lax.scan(chunk, zero, parts)[0]

  def minibatch(carry, idx):
    theta, opt_state, skips, totals = carry
    # minibatch m: rows idx [G, n / M] of every group, gathered here so that only one minibatch of the shuffled
    # batch is ever materialised (a whole shuffled copy holds the attacker's observations alone at 5.8 KB per env in
    # phase 2)
    mb = jax.tree.map(lambda a: jax.vmap(lambda x, i: x[i])(a, idx), flat)
    (loss, aux), g = minibatch_grad(theta, constrain(mb))
    upd, new_opt = agent.optimizer.update(g, opt_state, theta)
    ok = jnp.isfinite(loss) & jnp.all(jnp.isfinite(g))
    theta = jnp.where(ok, theta + upd, theta)
    opt_state = jax.tree.map(lambda a, b: jnp.where(ok, a, b), new_opt, opt_state)
    # the loss statistics as running totals in the carry (one small kernel per step, not a stacked output per name)
    totals = totals + jnp.stack([loss] + [aux[k] for k in _LOSS_STATS])
    return (theta, opt_state, skips + (~ok).astype(jnp.int32), totals), None

  def epoch(carry, k):
    keys = jax.random.split(k, groups) if groups > 1 else k[None]
    perm = constrain(jax.vmap(lambda kg: jax.random.permutation(kg, n))(keys))     # [G, n]
    # [G, n] -> [M, G, n / M]: minibatch m takes the same slice of every group's permutation
    return jax.lax.scan(minibatch, carry, jnp.swapaxes(perm.reshape(groups, p.num_minibatches, -1), 0, 1))

  init = (theta0, state.opt_state, jnp.zeros((), jnp.int32), jnp.zeros(1 + len(_LOSS_STATS), jnp.float32))
  (theta, opt_state, skips, totals), _ = jax.lax.scan(epoch, init, jax.random.split(key, p.update_epochs))
  params = unravel(theta)
  means = totals / (p.update_epochs * p.num_minibatches)   # the loss statistics' means over all minibatch steps
  aux = {name: means[i] for i, name in enumerate(("loss",) + _LOSS_STATS)}
  aux["nan_skips"] = skips
  return AgentState(params=params, opt_state=opt_state, normalizer=normalizer, updates=state.updates + 1), aux
