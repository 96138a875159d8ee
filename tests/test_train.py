"""Trainer on the CPU: PPO pieces (GAE, loss, NaN guard), no recompiles between calls, a tiny phase-1 run with an
interrupted + resumed twin that ends bit-identical, the CLI's one-line errors, and a tiny train -> export smoke
(phase 1 + adversarial phase 2 + ONNX parity) asserting real outcomes."""

import dataclasses
import functools
import json
import os
import re
import shutil
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from specguard_jax.cli import train as train_cli
from specguard_jax import evaluation, export
from specguard_jax.ppo import attacker, config, iteration, losses, networks, runner

TINY_PPO = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-3)


def tiny(env=None, **kw):
  """A tiny TrainConfig: kw TrainConfig fields, env: fields of its EnvConfig (TrainConfig.env)."""
  base = dict(num_envs=8, unroll_length=8, iters_per_call=2, phase1_steps=256, phase2_steps=0, hidden=(32, 32),
              sg=TINY_PPO, aa=TINY_PPO, checkpoint_every_s=0.0, seed=3)
  base.update(kw)
  # the oracle detector in phase 2 (the default 'mixed' also runs the residual one: a longer compile; its env is
  # tested in test_env_detection)
  return config.TrainConfig(**base).with_env(**{"worlds": ("suburban_residential",), "detector": "oracle",
                                                **(env or {})}).validate()


def test_convergence_rule_is_relative_to_the_returns():
  """runner.converged (Algorithm 2's stop): both agents' mean returns move less than eps of their size per iteration
  between the last two windows; a drifting or too short history does not stop."""
  flat = [[500.0 + 0.1 * (i % 2), -500.0] for i in range(40)]
  assert runner.converged(flat, 20, 1e-3)
  assert not runner.converged(flat[:39], 20, 1e-3)             # fewer than two windows
  assert not runner.converged(flat, 20, 0.0)                   # off
  rising = [[500.0 + 2.0 * i, -500.0] for i in range(40)]      # +2 / iteration = 4e-3 of 500
  assert not runner.converged(rising, 20, 1e-3) and runner.converged(rising, 20, 5e-3)
  small = [[0.01 * i, 0.0] for i in range(40)]                  # near zero: measured against 1
  assert runner.converged(small, 20, 1e-3) is False and runner.converged(small, 20, 2e-2)


def test_gae_bootstraps_truncation_not_termination():
  r = jnp.array([[1.0], [1.0], [1.0]])
  v = jnp.array([[0.5], [0.5], [0.5]])
  nv = jnp.array([[0.5], [10.0], [0.5]])
  done = jnp.array([[0.0], [1.0], [0.0]])
  for term, expect_boot in ((0.0, True), (1.0, False)):
    adv, target = losses.gae(r, v, nv, done * term, done, 0.9, 1.0)
    delta1 = 1.0 + (0.9 * 10.0 if expect_boot else 0.0) - 0.5
    np.testing.assert_allclose(adv[1, 0], delta1, rtol=1e-6)          # cut at the episode end
    np.testing.assert_allclose(adv[2, 0], 1.0 + 0.9 * 0.5 - 0.5, rtol=1e-6)
    np.testing.assert_allclose(target, adv + v, rtol=1e-6)


@pytest.mark.parametrize("max_trunc", [1, 2])
def test_bootstrap_values_from_the_next_steps_obs(max_trunc):
  """iteration.bootstrap_values: V(next_obs) taken from V(obs[t+1]) where the env went on, from the gathered own
  next_obs where it was truncated (up to max_trunc times per env in steps 0..T-2) and at the last step; GAE's inputs
  equal the direct 2T-row computation wherever they are used (terminated rows are multiplied by 0)."""
  T, G, B, n = 9, 2, 5, 3
  rng = np.random.default_rng(0)
  obs = rng.normal(size=(T, G, B, n)).astype(np.float32)
  next_obs = np.concatenate([obs[1:], rng.normal(size=(1, G, B, n)).astype(np.float32)])
  done = np.zeros((T, G, B), np.float32)
  term = np.zeros((T, G, B), np.float32)
  # env (0, 0): truncated at 1 (and at 5 when two fit); (0, 1): terminated at 2; (1, 2): truncated at 7, the last
  # step before T-1; (1, 3): truncated at T-1 (bootstrapped from next_obs[T-1]); (1, 4): terminated at 0, truncated
  # at 3
  done[1, 0, 0] = 1
  if max_trunc == 2:
    done[5, 0, 0] = 1
  done[2, 0, 1] = term[2, 0, 1] = 1
  done[7, 1, 2] = 1
  done[T - 1, 1, 3] = 1
  done[0, 1, 4] = term[0, 1, 4] = 1
  done[3, 1, 4] = 1
  finished = done > 0
  next_obs[:-1][finished[:-1]] = rng.normal(size=(int(finished[:-1].sum()), n))   # a finished env's own last obs
  value_fn = lambda x: jnp.sum(jnp.sin(3.0 * x), axis=-1) + 0.1 * jnp.sum(x, axis=-1)  # noqa: E731
  v, nv = iteration.bootstrap_values(value_fn, jnp.asarray(obs), jnp.asarray(next_obs), jnp.asarray(done),
                                     jnp.asarray(term), max_trunc, 4)
  np.testing.assert_allclose(v, value_fn(obs), rtol=1e-6, atol=1e-6)
  used = term == 0
  np.testing.assert_allclose(np.asarray(nv)[used], np.asarray(value_fn(next_obs))[used], rtol=1e-6, atol=1e-6)
  assert np.all(np.isfinite(nv))
  # one truncation fewer than the env had: the second one is (knowingly) taken from the next step's obs
  if max_trunc == 2:
    _, nv1 = iteration.bootstrap_values(value_fn, jnp.asarray(obs), jnp.asarray(next_obs), jnp.asarray(done),
                                        jnp.asarray(term), 1, 4)
    assert not np.isclose(float(nv1[5, 0, 0]), float(value_fn(next_obs[5, 0, 0])))


def test_nan_gradients_never_reach_params():
  cfg = tiny()
  sg, _ = iteration.make_agents(cfg)
  st = sg.init(jax.random.PRNGKey(0), 24)
  batch = {"obs": jnp.ones((4, 8, 24)), "action": jnp.zeros((4, 8, 3)), "logp": jnp.zeros((4, 8)),
           "value": jnp.zeros((4, 8)), "adv": jnp.full((4, 8), jnp.nan), "target": jnp.zeros((4, 8)),
           "mask": jnp.ones((4, 8))}
  new, aux = jax.jit(lambda s, b, k: losses.update(sg, s, b, k))(st, batch, jax.random.PRNGKey(1))
  assert int(aux["nan_skips"]) == cfg.sg.update_epochs * cfg.sg.num_minibatches
  for a, b in zip(jax.tree.leaves(new.params), jax.tree.leaves(st.params)):
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("groups", [1, 2])
def test_chunked_minibatch_gradients_equal_the_whole_minibatchs(groups):
  """losses.update with each minibatch's gradient summed over 4 chunks (what PPOConfig.max_rows_per_pass asks for
  at large env counts) gives the same params, Adam state and loss statistics as one pass, with masked rows and
  advantage normalisation over the whole minibatch, and with env groups."""
  ppo = config.PPOConfig(num_minibatches=2, update_epochs=2, lr=1e-2)
  cfg = tiny(sg=ppo)
  sg, _ = iteration.make_agents(cfg)
  st = losses.with_hparams(sg.init(jax.random.PRNGKey(0), 24), ppo)
  ks = jax.random.split(jax.random.PRNGKey(1), 7)
  T, B = 4, 16
  batch = {"obs": jax.random.normal(ks[0], (T, B, 24)), "action": jax.random.normal(ks[1], (T, B, 3)),
           "logp": jax.random.normal(ks[2], (T, B)), "value": jax.random.normal(ks[3], (T, B)),
           "adv": 3.0 + jax.random.normal(ks[4], (T, B)), "target": jax.random.normal(ks[5], (T, B)),
           "mask": (jax.random.uniform(ks[6], (T, B)) > 0.3).astype(jnp.float32)}
  run = lambda c: jax.jit(lambda s, b, k: losses.update(sg, s, b, k, groups=groups, chunks=c))(  # noqa: E731
      st, batch, jax.random.PRNGKey(2))
  (one, aux1), (four, aux4) = run(1), run(4)
  for a, b in zip(jax.tree.leaves((one.params, one.opt_state)), jax.tree.leaves((four.params, four.opt_state))):
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-6)
  for k in ("loss", "pg_loss", "v_loss", "entropy", "approx_kl"):
    np.testing.assert_allclose(aux1[k], aux4[k], rtol=1e-5, atol=1e-6)
  moved = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(one.params), jax.tree.leaves(st.params)))
  assert moved > 1e-3
  with pytest.raises(ValueError, match="chunks"):
    run(3)


def test_chunks_per_minibatch_caps_the_rows_of_one_pass_per_device():
  ppo = config.PPOConfig(max_rows_per_pass=1 << 20)
  rows = lambda envs: envs * 32 // ppo.num_minibatches  # noqa: E731   default unroll and minibatches, one group
  assert losses.chunks_per_minibatch(ppo, rows(262_144), 1) == 1
  assert losses.chunks_per_minibatch(ppo, rows(524_288), 1) == 2
  assert losses.chunks_per_minibatch(ppo, rows(1_048_576), 1) == 4
  assert losses.chunks_per_minibatch(ppo, rows(131_072), 4) == 2           # 4 groups (sweep members) on a device
  assert losses.chunks_per_minibatch(config.PPOConfig(max_rows_per_pass=7), 12, 1) == 2   # fewest divisors that fit
  assert losses.chunks_per_minibatch(config.PPOConfig(max_rows_per_pass=1), 12, 1) == 12
  with pytest.raises(ValueError, match="max_rows_per_pass"):
    tiny(sg=config.PPOConfig(max_rows_per_pass=0))


def test_update_on_raveled_params_equals_per_array_adam():
  """losses.update runs Adam on the raveled params (one [P] vector); one epoch of one minibatch must equal optax's
  clip + Adam applied array by array to the gradient of the same loss (a minibatch is a permutation of the batch,
  and the loss is a mean over it)."""
  ppo = config.PPOConfig(num_minibatches=1, update_epochs=1, lr=1e-2, max_grad_norm=0.05)
  cfg = tiny(sg=ppo)
  sg, _ = iteration.make_agents(cfg)
  st = losses.with_hparams(sg.init(jax.random.PRNGKey(0), 24), ppo)
  ks = jax.random.split(jax.random.PRNGKey(1), 6)
  batch = {"obs": jax.random.normal(ks[0], (4, 8, 24)), "action": jax.random.normal(ks[1], (4, 8, 3)),
           "logp": jax.random.normal(ks[2], (4, 8)), "value": jax.random.normal(ks[3], (4, 8)),
           "adv": jax.random.normal(ks[4], (4, 8)), "target": jax.random.normal(ks[5], (4, 8)),
           "mask": jnp.ones((4, 8))}
  new, aux = jax.jit(lambda s, b, k: losses.update(sg, s, b, k))(st, batch, jax.random.PRNGKey(2))
  assert int(aux["nan_skips"]) == 0
  import optax
  from brax.training.acme import running_statistics
  flat = jax.tree.map(lambda a: a.reshape((32,) + a.shape[2:]), batch)
  norm = running_statistics.update(st.normalizer, flat["obs"])
  g = jax.grad(lambda p: losses.ppo_loss(sg, p, norm, flat)[0])(st.params)
  tx = optax.chain(optax.clip_by_global_norm(ppo.max_grad_norm), optax.adam(ppo.lr, eps=1e-5))
  upd, _ = tx.update(g, tx.init(st.params), st.params)
  ref = optax.apply_updates(st.params, upd)
  assert jax.tree.structure(ref) == jax.tree.structure(new.params)
  for a, b in zip(jax.tree.leaves(new.params), jax.tree.leaves(ref)):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
  moved = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(st.params)))
  assert moved > 1e-3                         # the step did change the params
  assert new.opt_state.inner_state[1][0].mu.ndim == 1     # Adam's moments are one raveled vector


def _one_sum_per_statistic_ppo_loss(agent, params, normalizer, batch, hp):
  """The PPO loss as first written (one reduction per statistic)."""
  from brax.training.acme import running_statistics
  p = agent.ppo
  x = jnp.clip(running_statistics.normalize(batch["obs"], normalizer), -agent.obs_clip, agent.obs_clip)
  logp, ent = agent.policy.log_prob_entropy(params["policy"], x, batch["action"])
  v = agent.value.apply({"params": params["value"]}, x)[..., 0]
  mask, adv = batch["mask"], batch["adv"]
  n = jnp.maximum(jnp.sum(mask), 1.0)
  if p.normalize_advantage:
    mu = jnp.sum(adv * mask) / n
    adv = (adv - mu) / (jnp.sqrt(jnp.sum(mask * (adv - mu) ** 2) / n) + 1e-8)
  ratio = jnp.exp(logp - batch["logp"])
  surr = jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - hp["clip_eps"], 1.0 + hp["clip_eps"]) * adv)
  pg_loss = -jnp.sum(surr * mask) / n
  v_err = (v - batch["target"]) ** 2
  if p.value_clip_eps > 0:
    v_clip = batch["value"] + jnp.clip(v - batch["value"], -p.value_clip_eps, p.value_clip_eps)
    v_err = jnp.maximum(v_err, (v_clip - batch["target"]) ** 2)
  v_loss = 0.5 * jnp.mean(v_err)
  entropy = jnp.sum(ent * mask) / n
  loss = pg_loss + hp["vf_coef"] * v_loss - hp["ent_coef"] * entropy
  approx_kl = jnp.sum(((ratio - 1.0) - (logp - batch["logp"])) * mask) / n
  return loss, {"pg_loss": pg_loss, "v_loss": v_loss, "entropy": entropy, "approx_kl": approx_kl}


@pytest.mark.parametrize("normalize,value_clip", [(True, 0.0), (True, 0.2), (False, 0.0)])
def test_ppo_loss_equals_the_one_sum_per_statistic_form(normalize, value_clip):
  """losses.ppo_loss takes its minibatch sums as stacked reductions; loss, statistics and gradient equal the
  one-reduction-per-statistic form (masked rows included)."""
  ppo = config.PPOConfig(normalize_advantage=normalize, value_clip_eps=value_clip)
  sg, _ = iteration.make_agents(tiny(sg=ppo))
  st = sg.init(jax.random.PRNGKey(0), 24)
  ks = jax.random.split(jax.random.PRNGKey(3), 7)
  n = 512
  batch = {"obs": jax.random.normal(ks[0], (n, 24)), "action": jax.random.normal(ks[1], (n, 3)),
           "logp": -3.0 + jax.random.normal(ks[2], (n,)), "value": jax.random.normal(ks[3], (n,)),
           "adv": 3.0 + jax.random.normal(ks[4], (n,)), "target": jax.random.normal(ks[5], (n,)),
           "mask": (jax.random.uniform(ks[6], (n,)) < 0.8).astype(jnp.float32)}
  hp = {"clip_eps": ppo.clip_eps, "ent_coef": ppo.ent_coef, "vf_coef": ppo.vf_coef}
  (loss, aux), g = jax.jit(jax.value_and_grad(lambda p: losses.ppo_loss(sg, p, st.normalizer, batch, hp),
                                              has_aux=True))(st.params)
  ref_fn = lambda p: _one_sum_per_statistic_ppo_loss(sg, p, st.normalizer, batch, hp)  # noqa: E731
  (ref, ref_aux), g_ref = jax.jit(jax.value_and_grad(ref_fn, has_aux=True))(st.params)
  np.testing.assert_allclose(loss, ref, rtol=1e-5, atol=1e-6)
  for k in ref_aux:
    np.testing.assert_allclose(aux[k], ref_aux[k], rtol=1e-5, atol=1e-6, err_msg=k)
  for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
  from jax.flatten_util import ravel_pytree
  assert float(jnp.max(jnp.abs(ravel_pytree(g)[0]))) > 1e-3


@pytest.mark.parametrize("phase", [1, 2])
def test_carry_types_are_stable_so_calls_never_recompile(phase):
  """The carry a call returns has exactly the input's shapes/dtypes/weak types (else each call would recompile).
  Both trace with the progress pay, phase 2 with the reward's other optional terms too (TrainConfig.action_cost,
  violation_penalty, stall_penalty)."""
  extra = {"action_cost": 0.05, "violation_penalty": 1.0, "stall_penalty": 1.0} if phase == 2 else {}
  cfg = tiny(phase2_steps=256, progress_reward=0.2, **extra)
  ph = iteration.make_phase(cfg, phase)
  k = jax.random.PRNGKey(0)
  c = jax.eval_shape(lambda: ph.init(k, ph.sg.init(k, ph.cfg.n_obs), ph.aa.init(k, attacker.N_OBS)))
  out = jax.eval_shape(lambda c: ph.run(c)[0], c)
  a, b = jax.tree.leaves(c), jax.tree.leaves(out)
  assert jax.tree.structure(c) == jax.tree.structure(out)
  bad = [(x, y) for x, y in zip(a, b) if (x.shape, x.dtype, x.weak_type) != (y.shape, y.dtype, y.weak_type)]
  assert not bad, bad[:3]


def test_trainer_envs_keep_the_ekf_records_only_for_the_residual_detector():
  """The trainer's envs skip the NaN fallback, and the EKF records unless the training detector reads them."""
  for detector, phase, want in (("oracle", 1, False), ("oracle", 2, False), ("residual", 2, True)):
    env = iteration.make_env(tiny(env=dict(detector=detector)), phase)
    env = getattr(env, "env", env)   # phase 2: the AttackerEnv's wrapped env
    assert (env.config.nan_fallback, env.config.ekf_records) == (False, want), (detector, phase)


@functools.lru_cache(maxsize=4)
def _lowered_phase_text(cfg, phase):
  """The lowered phase program's text with its debug locations (kept: the default config's serves both tests)."""
  ph = iteration.make_phase(cfg, phase)
  k = jax.random.PRNGKey(0)
  c = jax.eval_shape(lambda: ph.init(k, ph.sg.init(k, ph.cfg.n_obs), ph.aa.init(k, attacker.N_OBS)))
  return ph.run.lower(c).as_text(debug_info=True)


def _dot_precisions(cfg, phase, precision=True):
  """[(bf16?, names of the scopes it was traced in)] of every dot_general in the lowered phase program. bf16: the
  dot's precision config rounds its inputs to bf16 (precision=True), or its result is a bf16 tensor (False)."""
  txt = _lowered_phase_text(cfg, phase)
  locs = dict(re.findall(r"^(#loc\d+) = (.*)$", txt, re.M))

  def names(ref, depth=0):   # a location's own names and those of the locations it refers to
    d = locs.get(ref, "")
    inner = re.findall(r"#loc\d+", d) if depth < 8 else []
    return re.findall(r'loc\("([^"]*)"', d) + [n for r in inner for n in names(r, depth + 1)]
  out = []
  for line in txt.splitlines():
    if "dot_general" in line:
      ref = re.search(r"loc\((#loc\d+)\)\s*$", line)
      bf16 = "lhs_precision_type = bf16" in line if precision else bool(re.search(r"->\s*tensor<[^>]*bf16>", line))
      out.append((bf16, " ".join(names(ref.group(1))) if ref else ""))
  return out


def test_bf16_matmuls_only_in_the_agents_networks():
  """--matmul-precision bf16 rounds the inputs of every matmul of both agents' networks (acting, values,
  PPO update) to bfloat16, and of nothing else: the env's physics, EKF and reconstruction stay f32."""
  default = _dot_precisions(tiny(phase2_steps=256), 2)
  bf16 = _dot_precisions(tiny(phase2_steps=256, matmul_precision="bf16"), 2)
  assert len(default) == len(bf16) and not any(b for b, _ in default)
  nets = sum("MLP" in n for _, n in default)
  assert nets >= 30                                                  # SG + AA: acting, values, gradients
  assert sum(b for b, _ in bf16) == nets
  assert all("MLP" in n for b, n in bf16 if b) and not any("MLP" in n for b, n in bf16 if not b)
  assert any("physics" in n for b, n in bf16 if not b) and any("ekf" in n for b, n in bf16 if not b)
  with pytest.raises(ValueError, match="unknown matmul_precision 'fp8'"):
    tiny(matmul_precision="fp8")
  assert train_cli.build_config(train_cli.parse_args(["--matmul-precision", "bf16"])).matmul_precision == "bf16"


def test_unroll_ticks_reaches_the_trainers_envs():
  """train.py --unroll-ticks: TrainConfig.env.unroll_ticks, on in both phases' envs (EnvConfig.unroll_ticks); off
  by default."""
  assert not train_cli.build_config(train_cli.parse_args([])).env.unroll_ticks
  cfg = train_cli.build_config(train_cli.parse_args(["--unroll-ticks"]))
  assert cfg.env.unroll_ticks
  assert iteration.make_env(cfg, 1).config.unroll_ticks
  assert iteration.make_env(cfg, 2).env.config.unroll_ticks
  assert not iteration.make_env(cfg.with_env(unroll_ticks=False), 2).env.config.unroll_ticks


def test_bf16_network_dtype_only_in_the_hidden_layers():
  """network_dtype='bfloat16' computes the hidden layers of both agents' networks in bf16 (acting, after-rollout
  values, PPO update), never their output layers (logits, means, values stay f32) and nothing of the env."""
  default = _dot_precisions(tiny(phase2_steps=256), 2, precision=False)
  bf16 = _dot_precisions(tiny(phase2_steps=256, network_dtype="bfloat16"), 2, precision=False)
  assert len(default) == len(bf16) and not any(b for b, _ in default)
  low = [n for b, n in bf16 if b]
  assert len(low) >= 20 and all("MLP" in n for n in low)              # SG + AA hidden layers, forward and backward
  assert not any("dense_2" in n for n in low)            # hidden=(32, 32) and (128, 128): dense_2 is the output layer
  assert any("dense_2" in n for b, n in bf16 if not b)
  assert any("physics" in n for b, n in bf16 if not b) and any("ekf" in n for b, n in bf16 if not b)
  with pytest.raises(ValueError, match="unknown network_dtype 'fp8'"):
    tiny(network_dtype="fp8")
  assert train_cli.build_config(train_cli.parse_args(["--network-dtype", "float32"])).network_dtype == "float32"
  assert tuple(networks.DTYPES) == config.NETWORK_DTYPES
  assert runner.default_sizes("gpu")["network_dtype"] == "bfloat16"
  assert "network_dtype" not in runner.default_sizes("cpu")


def test_bad_config_and_flags_are_one_line_errors(tmp_path, capsys):
  with pytest.raises(ValueError, match="unknown variant"):
    tiny(variant="xx")
  with pytest.raises(ValueError, match="divisible"):
    tiny(num_envs=5, unroll_length=3)
  with pytest.raises(ValueError, match="unknown config key"):
    config.from_dict({"bogus": 1})
  assert config.from_dict({"fused_mlp": False}) == config.TrainConfig()   # an older run dir's config.json
  with pytest.raises(ValueError, match="'fused_mlp' = True is no longer supported"):
    config.from_dict({"fused_mlp": True})
  # values of the wrong type name their key (a string for a bool reached the env's lax.scan as a TypeError)
  for d, msg in (({"unroll_ticks": "yes"}, "'env.unroll_ticks' must be bool, got 'yes'"),
                 ({"env": {"unroll_ticks": "yes"}}, "'env.unroll_ticks' must be bool, got 'yes'"),
                 ({"env": {"clearance": "far"}}, "'env.clearance' must be float, got 'far'"),
                 ({"env": {"bogus": 1}}, "unknown env key"), ({"env": 3}, "'env' must be an object"),
                 ({"env": {"mission": {"a": 1}}}, "'env.mission' is an object a config file cannot set"),
                 ({"detector": "oracle", "env": {"detector": "residual"}}, "given both at the top level and in env"),
                 ({"num_envs": 2.5}, "'num_envs' must be int"), ({"seed": True}, "'seed' must be int"),
                 ({"vehicle": 3}, "'vehicle' must be str"), ({"sg": {"lr": "fast"}}, "'sg.lr' must be float"),
                 ({"aa": 1}, "'aa' must be an object"), ({"fused_ekf": 1}, "'fused_ekf' must be false, true")):
    with pytest.raises(ValueError, match=msg):
      config.from_dict(d)
  cfg = config.from_dict({"phase1_steps": 1e8, "sg": {"lr": 1}, "fused_ekf": "lanes", "worlds": ["urban_park"]})
  assert cfg.phase1_steps == 100_000_000 and isinstance(cfg.phase1_steps, int) and cfg.sg.lr == 1.0
  assert cfg.env.ekf_kernel == "lanes" and cfg.env.worlds == ("urban_park",)   # an older run's fused_ekf
  assert config.from_dict(config.TrainConfig().to_dict()) == config.TrainConfig()   # a run dir's config.json
  if jax.default_backend() != "gpu":
    with pytest.raises(ValueError, match="ekf_kernel='lanes' needs a GPU"):
      tiny(env=dict(ekf_kernel="lanes"))
  bad = tmp_path / "c.json"
  bad.write_text("{not json")
  assert train_cli.main(["--config", str(bad), "--out", str(tmp_path / "r")]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "cannot read config file" in err[0]
  assert train_cli.main(["--resume", str(tmp_path / "nothing")]) == 2
  assert "not a run directory" in capsys.readouterr().err


W4 = ("suburban_residential", "urban_city_streets", "urban_park", "open_mountain")
# A config.json as train.py wrote it before the env settings moved into TrainConfig.env (flat keys), non-default
OLD_FLAT_CONFIG = {
    "vehicle": "drone", "variant": "pc", "worlds": ["urban_park"], "reward": "binary", "action": "gaussian",
    "hidden": [256, 256, 256], "activation": "tanh", "speeds": [4.0, 4.0, 2.0], "residual": False,
    "init_log_std": -1.0, "num_envs": 256, "unroll_length": 32, "phase1_steps": 2000000, "phase2_steps": 2000000,
    "iters_per_call": 4, "seed": 0, "reconstruction": False, "detector": "residual", "eval_detector": "oracle",
    "detector_delay": 1.0, "attack_sensors": ["gps", "gyro", "accel", "mag", "baro", "flow"],
    "attack_max_duration_s": 40.0, "attack_alpha": 1.0, "attack_beta": 0.0, "attack_gamma": 0.0,
    "alternate_iters": 10, "converge_eps": 0.0, "converge_window": 20, "completion_bonus": -1.0, "obs_clip": 10.0,
    "sg": {"lr": 0.0003, "lr_schedule": "constant", "lr_end_frac": 0.1, "gamma": 0.99, "gae_lambda": 0.95,
           "clip_eps": 0.2, "value_clip_eps": 0.0, "vf_coef": 0.5, "ent_coef": 0.003, "max_grad_norm": 0.5,
           "num_minibatches": 8, "update_epochs": 4, "normalize_advantage": True, "max_rows_per_pass": 1048576},
    "aa": {"lr": 0.0003, "lr_schedule": "constant", "lr_end_frac": 0.1, "gamma": 0.99, "gae_lambda": 0.95,
           "clip_eps": 0.2, "value_clip_eps": 0.0, "vf_coef": 0.5, "ent_coef": 0.01, "max_grad_norm": 0.5,
           "num_minibatches": 8, "update_epochs": 4, "normalize_advantage": True, "max_rows_per_pass": 1048576},
    "eval_missions": 0, "checkpoint_every_s": 120.0, "max_nan_skips": 100, "fused_ekf": False, "unroll_ticks": True,
    "num_devices": 0, "env_groups": 0, "matmul_precision": "default", "network_dtype": "float32"}


def test_phase_and_eval_env_configs_are_the_old_trainers():
  """config.env_config builds, for the default run and two others, exactly the EnvConfigs the trainer built when
  TrainConfig mirrored the env fields (written out here): phase 1, phase 2 (training detector) and the held-out
  evaluation's (eval_detector, EnvConfig's defaults for the speed options)."""
  from envs import base
  from specguard_jax import controllers

  def EnvConfig(**kw):   # every run config here has the trainer's observation layout (TRAIN_ENV)
    return base.EnvConfig(**{"obs_layout": "recovery", "override_phases": "all", **kw})

  expected = {
      "default": (config.TrainConfig(), (
          EnvConfig(worlds=W4, override_frame="body", override_residual=True, control_mode="override",
                    nan_fallback=False, ekf_records=False, ekf_kernel="auto"),
          EnvConfig(worlds=W4, override_frame="body", override_residual=True, control_mode="reactive",
                    detector="mixed", detector_delay=0.5, reconstruction=True, nan_fallback=False,
                    ekf_records=True, ekf_kernel="auto"),
          EnvConfig(worlds=W4, override_frame="body", override_residual=True, control_mode="reactive",
                    detector="residual", detector_delay=0.5, reconstruction=True))),
      "pc, residual, old flat config.json": (config.from_dict(OLD_FLAT_CONFIG), (
          EnvConfig(worlds=("urban_park",), reward="binary", override_frame="body", override_residual=False,
                    unroll_ticks=True, ekf_kernel="xla", control_mode="override", nan_fallback=False,
                    ekf_records=False),
          EnvConfig(worlds=("urban_park",), reward="binary", override_frame="body", override_residual=False,
                    unroll_ticks=True, ekf_kernel="xla", control_mode="override", detector="residual",
                    detector_delay=1.0, reconstruction=False, nan_fallback=False, ekf_records=True),
          EnvConfig(worlds=("urban_park",), reward="binary", override_frame="body", override_residual=False,
                    control_mode="override", detector="oracle", detector_delay=1.0, reconstruction=False))),
      "ftc-like, lanes kernel": (config.TrainConfig().with_env(reward="survival", reconstruction=False,
                                                               ekf_kernel="lanes"), (
          EnvConfig(worlds=W4, reward="survival", override_frame="body", override_residual=True, ekf_kernel="lanes",
                    control_mode="override", nan_fallback=False, ekf_records=False),
          EnvConfig(worlds=W4, reward="survival", override_frame="body", override_residual=True, ekf_kernel="lanes",
                    control_mode="reactive", detector="mixed", detector_delay=0.5, reconstruction=False,
                    nan_fallback=False, ekf_records=True),
          EnvConfig(worlds=W4, reward="survival", override_frame="body", override_residual=True,
                    control_mode="reactive", detector="residual", detector_delay=0.5, reconstruction=False))),
  }
  for name, (cfg, want) in expected.items():
    got = tuple(config.env_config(cfg, phase) for phase in (1, 2, "eval"))
    assert got == want, name
  assert controllers.run_overrides(config.TrainConfig()) == (
      ("control_mode", "reactive"), ("override_frame", "body"), ("override_residual", True),
      ("override_attitude", False), ("detector", "residual"), ("detector_delay", 0.5), ("reconstruction", True),
      ("override_phases", "all"), ("recovery_rule", "none"))
  # A policy trained over the rule-based fallback (a residual on its setpoint) is flown over it; phase 1 (no alarm,
  # no reconstruction) has no rule.
  over_rule = config.TrainConfig().with_env(recovery_rule="fallback").validate()
  assert config.env_config(over_rule, 1).recovery_rule == "none"
  assert config.env_config(over_rule, 2).recovery_rule == "fallback"
  assert dict(controllers.run_overrides(over_rule))["recovery_rule"] == "fallback"
  assert dict(controllers.run_overrides(over_rule, reconstruction=False))["recovery_rule"] == "none"   # the ablation
  cfg = tiny(phase2_steps=256)   # the envs the trainer and the held-out evaluation build carry these configs
  assert iteration.make_env(cfg, 1).config == config.env_config(cfg, 1)
  assert iteration.make_env(cfg, 2).env.config == config.env_config(cfg, 2)
  assert iteration.eval_env(cfg).config == config.env_config(cfg, "eval")


def test_old_flat_config_json_loads_into_env_and_resumes(tmp_path):
  """A run directory's config.json from before TrainConfig.env (flat keys) loads with those keys in env, for a resume
  (runner.load_run_config) and for evaluation (controllers.load_run_config); the new nested form round-trips."""
  from specguard_jax import controllers
  cfg = config.from_dict(OLD_FLAT_CONFIG)
  assert (cfg.variant, cfg.eval_detector) == ("pc", "oracle")
  assert cfg.env == dataclasses.replace(config.TRAIN_ENV, worlds=("urban_park",), reward="binary",
                                        override_residual=False, reconstruction=False, detector="residual",
                                        detector_delay=1.0, unroll_ticks=True, ekf_kernel="xla")
  (tmp_path / "config.json").write_text(json.dumps(OLD_FLAT_CONFIG))
  # a run written before observation layouts and override phases existed: the 24-input layout, cruise and loiter
  old = cfg.with_env(obs_layout="paper24", override_phases="cruise_loiter")
  assert runner.load_run_config(str(tmp_path)) == old and controllers.load_run_config(str(tmp_path)) == old
  d = json.loads(json.dumps(cfg.to_dict()))
  assert "worlds" not in d and d["env"]["worlds"] == ["urban_park"] and d["env"]["mission"] is None
  assert config.from_dict(d) == cfg


def test_flags_and_set_reach_the_config_through_from_dict(capsys):
  """train.py's flags each set their config key (nested ones in env); --set KEY=VALUE sets any field, nested ones
  dotted, values as JSON else strings; an unknown key or a wrong type is a one-line error (exit 2)."""
  a = train_cli.parse_args(["--world", "urban_park,open_mountain", "--detector", "residual", "--no-reconstruction",
                            "--reward", "binary", "--seed", "5", "--steps", "1001", "--envs", "64",
                            "--set", "env.clearance=6", "sg.lr=1e-4", "env.detector_delay=1", "activation=relu"])
  cfg = train_cli.build_config(a)
  assert cfg.env.worlds == ("urban_park", "open_mountain") and cfg.env.detector == "residual"
  assert not cfg.env.reconstruction and cfg.env.reward == "binary" and cfg.env.clearance == 6.0
  assert cfg.env.detector_delay == 1.0 and isinstance(cfg.env.detector_delay, float)
  assert (cfg.seed, cfg.num_envs, cfg.phase1_steps, cfg.phase2_steps) == (5, 64, 500, 501)
  assert cfg.sg.lr == 1e-4 and cfg.activation == "relu"
  cfg = train_cli.build_config(train_cli.parse_args(["--detector", "oracle", "--set", "env.ekf_records=false"]))
  assert not config.env_config(cfg, 2).ekf_records and config.env_config(cfg, "eval").ekf_records
  for argv, msg in ((["--set", "env.bogus=1"], "unknown env key(s) bogus"),
                    (["--set", "seed=abc"], "config key 'seed' must be int, got 'abc'"),
                    (["--set", "env.clearance=[1]"], "config key 'env.clearance' must be float"),
                    (["--set", "clearance"], "bad --set item 'clearance'"),
                    (["--set", "env.control_mode=override"], "env.control_mode is set per phase from variant"),
                    (["--detector", "residual", "--set", "env.ekf_records=false"], "needs ekf_records=True"),
                    (["--set", "env.ekf_records=false"], "detector='mixed' reads the EKF's test ratios")):
    assert train_cli.main(argv) == 2, argv
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("train.py: error: ") and msg in err[0], (argv, err)


def test_sweep_keys_reach_nested_and_old_flat_fields():
  """--sweep env.clearance=6,9 sweeps a nested env field; an old flat key (detector=...) still sweeps env's."""
  base = tiny()
  members = train_cli._sweep_members(base, ["env.clearance=6,9", "detector=oracle,residual"])
  assert [p for p, _ in members] == [{"env.clearance": c, "detector": d} for c in (6, 9)
                                     for d in ("oracle", "residual")]
  assert [(m.env.clearance, m.env.detector) for _, m in members] == [(6.0, "oracle"), (6.0, "residual"),
                                                                      (9.0, "oracle"), (9.0, "residual")]
  with pytest.raises(ValueError, match="config key 'env.clearance' must be float"):
    train_cli._sweep_members(base, ["env.clearance=far"])


def test_deterministic_gpu_flag_reaches_xla_before_the_backend_starts(tmp_path):
  """--deterministic-gpu puts XLA's deterministic-ops flag into XLA_FLAGS before anything of train.main starts JAX's
  backend (a fresh process: XLA then parses it, and would abort on a flag it does not know); an in-process caller
  whose backend already runs, or whose XLA_FLAGS turn the option off, gets a one-line error instead of a no-op."""
  import subprocess
  import sys
  code = ("import os, sys, jax, train\n"
          f"rc = train.main(['--deterministic-gpu', '--config', {str(tmp_path / 'missing.json')!r}])\n"
          "print(rc, os.environ['XLA_FLAGS'].split(), jax.numpy.ones(3).sum())\n")
  env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_cpu_enable_fast_math=false")
  out = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(os.path.dirname(__file__)), env=env,
                       capture_output=True, text=True, timeout=300)
  assert out.returncode == 0, out.stderr[-2000:]
  assert out.stdout.strip().splitlines()[-1] == ("2 ['--xla_cpu_enable_fast_math=false', "
                                                 f"'{train_cli.DETERMINISTIC_XLA_FLAG}'] 3.0"), out.stdout
  assert "cannot read config file" in out.stderr   # the request came first and did not refuse
  jax.devices()
  environ = {}
  with pytest.raises(ValueError, match="before JAX starts its backend"):   # this process's backend runs already
    train_cli.request_deterministic_gpu_ops(environ)
  assert environ == {}
  environ = {"XLA_FLAGS": train_cli.DETERMINISTIC_XLA_FLAG}
  train_cli.request_deterministic_gpu_ops(environ)                 # already there: nothing to do, nothing to refuse
  assert environ == {"XLA_FLAGS": train_cli.DETERMINISTIC_XLA_FLAG}
  with pytest.raises(ValueError, match="conflicts with XLA_FLAGS"):
    train_cli.request_deterministic_gpu_ops({"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"})


TWO_PHASE = dict(phase1_steps=2 * 128, phase2_steps=2 * 128, iters_per_call=2)


_COMPILES = {"on": False, "secs": [], "log": None}   # XLA compiles over 5 s while recording (the resumed run below)
# 5 s: a training phase compiles in 20-90 s on the CPU; the resumed run's own small jits (restore, eval helpers) take up
# to ~0.5 s on an idle 2-core machine and can exceed 1 s under the suite's two workers.


def _on_duration(event, secs, fun_name="", **_):
  if "backend_compile" not in event:
    return
  if _COMPILES["on"] and secs > 5.0:
    _COMPILES["secs"].append(secs)
  if _COMPILES["log"] is not None:   # every compile, by function and thread (the compile-ahead run below)
    _COMPILES["log"].append((fun_name, threading.current_thread().name))


jax.monitoring.register_event_duration_secs_listener(_on_duration)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """One uninterrupted two-phase run (with held-out eval + export) and a twin stopped inside phase 2 and resumed;
  both reuse the same compiled phases (make_phase is cached per config)."""
  root = tmp_path_factory.mktemp("train")
  cfg = tiny(eval_missions=1, alternate_iters=2, **TWO_PHASE)
  _COMPILES["log"] = []
  try:   # phase 2 and the held-out evaluation compile on background threads while phase 1 compiles and trains
    full = runner.train(cfg, str(root / "full"), progress=False, compile_ahead=True)
  finally:
    ahead_compiles, _COMPILES["log"] = _COMPILES["log"], None
  # The interrupted twin skips the held-out evaluation (host-side, after training: program_config leaves it out, so
  # both twins run the same compiled phases); its resumes read eval_missions=0 from its config.json.
  twin = dataclasses.replace(cfg, eval_missions=0)
  part = runner.train(twin, str(root / "part"), progress=False, export=False, stop_after_calls=3)
  shutil.copytree(root / "part", root / "cut")   # the same stop, for the phase-boundary resume below
  _COMPILES["on"] = True
  try:
    resumed = runner.train(cfg, str(root / "part"), resume=True, progress=False)
  finally:
    _COMPILES["on"] = False
  return dict(cfg=cfg, root=root, full=full, part=part, resumed=resumed, resumed_compiles=list(_COMPILES["secs"]),
              ahead_compiles=ahead_compiles)


def _final_sg(cfg, run_dir):
  mgr = runner._checkpointer(str(run_dir))
  ph = iteration.make_phase(cfg, 2)
  k = jax.random.PRNGKey(0)
  abstract = jax.eval_shape(lambda: ph.init(k, ph.sg.init(k, ph.cfg.n_obs), ph.aa.init(k, attacker.N_OBS)))
  carry = runner._restore_carry(mgr, mgr.latest_step(), abstract)
  mgr.close()
  return carry


def test_interrupted_run_resumes_bit_identical(runs):
  assert runs["part"]["interrupted"] and runs["part"]["calls"] == 3
  # The restored carry has the fresh one's types and shardings (zero-size leaves, which Orbax does not store,
  # included), so the resumed run reuses the compiled phase instead of compiling it again.
  assert runs["resumed_compiles"] == [], runs["resumed_compiles"]
  assert runs["resumed"]["env_steps"] == runs["full"]["env_steps"] == 4 * 2 * 64
  full = _final_sg(runs["cfg"], runs["root"] / "full")
  part = _final_sg(runs["cfg"], runs["root"] / "part")
  for name in ("sg", "aa", "rng"):
    for a, b in zip(jax.tree.leaves(getattr(full, name)), jax.tree.leaves(getattr(part, name))):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  lines = [json.loads(x) for x in open(runs["root"] / "part" / "metrics.jsonl")]
  assert [(r["phase"], r["iteration"]) for r in lines] == [(1, 1), (1, 2), (1, 3), (1, 4), (2, 1), (2, 2), (2, 3),
                                                            (2, 4)]
  f1 = export.load_jax_policy(str(runs["root"] / "full"))
  f2 = export.load_jax_policy(str(runs["root"] / "part"))
  x = np.random.default_rng(0).normal(size=(5, runs["cfg"].n_obs)).astype(np.float32)
  np.testing.assert_array_equal(np.asarray(f1(x)["setpoint"]), np.asarray(f2(x)["setpoint"]))


def test_compile_ahead_compiles_phase_2_and_the_evaluation_once_off_the_main_thread(runs):
  """The full run (compile_ahead=True) compiled phase 2's init and run and the held-out rollout on the compile-ahead
  thread, and its own calls of them found them compiled (no program compiled twice); the resumed twin, compiled the
  ordinary way, ends bit-identical to it (test_interrupted_run_resumes_bit_identical)."""
  log = runs["ahead_compiles"]
  ahead = lambda name: sorted(t == "specguard-compile-ahead" for f, t in log if f == name)  # noqa: E731
  assert ahead("jit(run)") == [False, True], log      # phase 1's on the caller's thread, phase 2's ahead
  assert ahead("jit(init)") == [False, True], log
  assert ahead("jit(_rollout)") == [True], log
  env = iteration.eval_env(runs["cfg"])   # the precompiled rollout served the held-out evaluation once, then went
  assert not any(dict(ck[:-1])["env"] is env for ck in evaluation._COMPILED)


def test_attitude_interface_trains_and_exports(tmp_path):
  """env.override_attitude (train.py --attitude): SpecGuard's policy has 6 outputs (velocity, then the acceleration
  residual scaled by accels), the attack agent's action follows them in phase 2, and the run saves the 6 scales and
  exports an ONNX graph with parity. (Phase 2 alone, without the reconstruction: a smaller program, the same wiring.)"""
  cfg = tiny(env=dict(override_attitude=True, reconstruction=False), campaign_share=0.0, phase1_steps=0,
             phase2_steps=128, alternate_iters=1, accels=(2.0, 2.0, 1.0))
  assert cfg.action_scales == (4.0, 4.0, 2.0, 2.0, 2.0, 1.0) and iteration.sg_policy(cfg).n == 6
  s = runner.train(cfg, str(tmp_path / "run"), progress=False)
  assert s["env_steps"] == 128
  policy, params, _, scales, _ = export.load_policy(str(tmp_path / "run"))
  assert policy.n == 6 and scales.tolist() == list(cfg.action_scales)
  assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(params))
  assert os.path.isfile(tmp_path / "run" / "policy.onnx")
  with pytest.raises(ValueError, match="drone only"):
    dataclasses.replace(cfg, vehicle="rover").validate()
  with pytest.raises(ValueError, match="needs action gaussian"):
    dataclasses.replace(cfg, action="discrete").validate()


def test_sweep_compiles_phase_2_ahead_once(tmp_path):
  """A vmapped two-phase sweep with compile_ahead: phase 2's (member-batched) init and run compile once, on the
  compile-ahead thread, and both members train. (Phase 2 without the reconstruction and the scripted campaigns: a
  smaller program to compile, the same compile schedule.)"""
  cfg = tiny(env=dict(reconstruction=False), campaign_share=0.0, alternate_iters=2, **TWO_PHASE)
  _COMPILES["log"] = []
  try:
    sw = runner.train_sweep([cfg, dataclasses.replace(cfg, seed=4)], ["a", "b"], str(tmp_path), progress=False,
                            export=False, compile_ahead=True)
  finally:
    log, _COMPILES["log"] = _COMPILES["log"], None
  big = [t == "specguard-compile-ahead" for f, t in log if f == "jit(<lambda>)"]   # the sweep's init_fn / run_fn
  assert sorted(big) == [False, False, True, True], log
  assert sw[0]["env_steps"] == sw[1]["env_steps"] == 4 * 2 * 64
  a, b = (jax.tree.leaves(m["sg_state"].params) for m in sw)
  assert all(np.all(np.isfinite(x)) for x in a + b)
  assert any(not np.array_equal(x, y) for x, y in zip(a, b))   # two seeds, two policies
  # export=False skips only the ONNX: each member's policy is saved for evaluate.py
  for m in ("a", "b"):
    assert os.path.isfile(tmp_path / m / "policy.msgpack") and not os.path.exists(tmp_path / m / "policy.onnx")


EXIT_MID_COMPILE = """
import sys, threading, time, jax, jax.numpy as jnp
from specguard_jax.ppo import ahead
lowered = threading.Event()   # set when the compile leaves tracing/lowering for XLA
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **kw: lowered.set() if event.endswith("jaxpr_to_mlir_module_duration") else None)
def f(x):
  for i in range(1500):   # a few seconds of XLA:CPU compile (default flags: minutes)
    x = jnp.tanh(x @ x.T) + i
  return x
a = ahead.CompileAhead()
a.submit("big", lambda: jax.jit(f).lower(jax.ShapeDtypeStruct((32, 32), jnp.float32)).compile())
lowered.wait(300)
time.sleep(0.2)
print("pending", a.pending(), flush=True)
sys.exit(3)
"""


def test_a_process_exiting_during_a_compile_ahead_exits_cleanly():
  """A run stopped early (e.g. SIGTERM after its checkpoint) may exit while a later phase still compiles ahead: the
  process ends with its own exit status once that compile is done (a daemon compile thread made it abort: 134)."""
  import subprocess
  import sys
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  r = subprocess.run([sys.executable, "-c", EXIT_MID_COMPILE], capture_output=True, text=True, timeout=600,
                     env=dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", "")))
  assert "pending ['big']" in r.stdout, (r.stdout, r.stderr[-2000:])
  assert r.returncode == 3, (r.returncode, r.stderr[-2000:])


def test_resume_from_the_phase_1_closing_checkpoint(runs):
  """Killed after phase 1's closing checkpoint and before phase 2's first save (here: the phase-2 save removed), the
  resumed run starts phase 2 from that checkpoint's agents and ends bit-identical to the uninterrupted run."""
  cut = runs["root"] / "cut"
  steps = sorted(int(d.name) for d in (cut / "checkpoints").iterdir() if d.name.isdigit())
  shutil.rmtree(cut / "checkpoints" / str(steps[-1]))               # the phase-2 save: gone
  mgr = runner._checkpointer(str(cut))
  assert runner._restore_host(mgr)[1]["carry_phase"] == 1            # the newest left closes phase 1
  mgr.close()
  s = runner.train(runs["cfg"], str(cut), resume=True, progress=False, export=False)
  assert s["env_steps"] == runs["full"]["env_steps"]
  full, cutc = _final_sg(runs["cfg"], runs["root"] / "full"), _final_sg(runs["cfg"], cut)
  for name in ("sg", "aa", "rng"):
    for a, b in zip(jax.tree.leaves(getattr(full, name)), jax.tree.leaves(getattr(cutc, name))):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_tiny_train_evaluate_export_smoke(runs):
  run = runs["root"] / "full"
  s = runs["full"]
  for f in ("config.json", "metrics.jsonl", "policy.onnx", "policy.msgpack", "summary.json"):
    assert (run / f).exists(), f
  assert any(n.startswith("events") for n in os.listdir(run / "tb"))
  lines = [json.loads(x) for x in open(run / "metrics.jsonl")]
  assert {r["phase"] for r in lines} == {1, 2}
  assert all(np.isfinite(r["sg_loss"]) for r in lines)
  assert any(r["aa_loss"] != 0 for r in lines if r["phase"] == 2)   # the attack agent trained in its turns
  assert any(r["sg_loss"] != 0 for r in lines if r["phase"] == 2)   # and SpecGuard in its turns
  assert s["export"]["max_abs_diff"] <= 1e-5 and s["export"]["opset"] <= 17
  h = s["heldout"]
  assert h["attack_free"]["missions"] == 1 and h["gps/overt"]["attacked"] == 1.0
  for k, v in h.items():
    if k[0] != "_":
      assert 0.0 <= v["svr"] <= 1.0 and v["unfinished"] == 0.0, (k, v)
  fn = export.load_jax_policy(str(run))
  assert runs["cfg"].n_obs == 44    # the trainer's default layout, recorded with the policy
  assert export.load_obs_layout(str(run))["name"] == "recovery"
  out = fn(np.zeros((2, 44), np.float32))
  assert np.all(np.isfinite(np.asarray(out["setpoint"])))


def test_corrupt_checkpoint_is_a_one_line_error(tmp_path, capsys):
  run = tmp_path / "run"
  (run / "checkpoints" / "1" / "host").mkdir(parents=True)
  (run / "config.json").write_text(json.dumps(tiny().to_dict()))
  (run / "checkpoints" / "1" / "host" / "metadata").write_text("garbage")
  (run / "checkpoints" / "1" / "_CHECKPOINT_METADATA").write_text("{}")
  assert train_cli.main(["--resume", str(run), "--no-progress"]) == 2
  err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
  assert len(err) == 1 and "cannot restore checkpoint" in err[0], err
  assert (run / "checkpoints" / "1" / "host" / "metadata").read_text() == "garbage"   # nothing deleted
