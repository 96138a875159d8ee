"""Denoising-autoencoder baseline (UnRocker-style sensor denoising), Flax + optax, and its in-tick estimator
(`DAEEstimator`: while the alarm is up the autopilot flies on the DAE's estimate; specguard_jax.baselines.unrocker
trains and registers it).

Maps the attacked input vector x'_t [15] (recon.INPUT_NAMES, from the attacked EKF) to the clean one, trained on
(attacked, true) pairs. Per-feature standardisation, MLP encoder -> bottleneck -> decoder, residual output
(x_hat = x + dec(enc(x)) in standardised units); angles are not unwrapped (the DAE sees raw Euler angles).
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from specguard_jax import math3d
from specguard_jax.estimation import recon
from specguard_jax.estimation import tree_file
from specguard_jax.estimation.estimator import Estimator


@dataclasses.dataclass(frozen=True)
class DAEConfig:
  """hidden: encoder widths (decoder mirrors them); bottleneck: code size; steps, batch, lr: Adam training."""
  hidden: tuple = (128, 64)
  bottleneck: int = 16
  steps: int = 2000
  batch: int = 512
  lr: float = 1e-3


class DAENet(nn.Module):
  hidden: tuple
  bottleneck: int
  n_out: int

  @nn.compact
  def __call__(self, x):
    h = x
    for w in self.hidden:
      h = nn.gelu(nn.Dense(w)(h))
    h = nn.Dense(self.bottleneck)(h)
    for w in reversed(self.hidden):
      h = nn.gelu(nn.Dense(w)(h))
    return x + nn.Dense(self.n_out)(h)


@struct.dataclass
class DAEParams:
  """net: Flax params.  mean, std: [n] input standardisation (also used for the output)."""
  net: dict
  mean: jnp.ndarray
  std: jnp.ndarray


def dae_apply(cfg: DAEConfig, p: DAEParams, x):
  """Denoise x [..., n] -> [..., n]."""
  net = DAENet(cfg.hidden, cfg.bottleneck, x.shape[-1])
  z = (x - p.mean) / p.std
  return net.apply(p.net, z) * p.std + p.mean


@functools.partial(jax.jit, static_argnames=("cfg",))
def train_dae(cfg: DAEConfig, x_noisy, x_clean, key) -> tuple[DAEParams, jax.Array]:
  """Fit on pairs x_noisy, x_clean [N, n]. Returns (params, final training loss (standardised MSE))."""
  mean = jnp.mean(x_clean, 0)
  std = jnp.std(x_clean, 0) + 1e-3
  net = DAENet(cfg.hidden, cfg.bottleneck, x_clean.shape[-1])
  k_init, k_batch = jax.random.split(key)
  params = net.init(k_init, jnp.zeros((1, x_clean.shape[-1])))
  opt = optax.adam(cfg.lr)
  zn, zc = (x_noisy - mean) / std, (x_clean - mean) / std

  def loss_fn(params, idx):
    return jnp.mean((net.apply(params, zn[idx]) - zc[idx]) ** 2)

  def body(carry, k):
    params, st = carry
    idx = jax.random.randint(k, (cfg.batch,), 0, zn.shape[0])
    loss, g = jax.value_and_grad(loss_fn)(params, idx)
    upd, st = opt.update(g, st, params)
    return (optax.apply_updates(params, upd), st), loss

  (params, _), losses = jax.lax.scan(body, (params, opt.init(params)), jax.random.split(k_batch, cfg.steps))
  return DAEParams(net=params, mean=mean, std=std), losses[-50:].mean()


@dataclasses.dataclass(eq=False)
class DAEEstimator(Estimator):
  cfg: DAEConfig
  params: DAEParams

  @classmethod
  def create(cls, env, model_path: str = ""):
    del env
    if not model_path:
      raise ValueError("recovery_estimator='dae' needs recovery_model= a DAE file (specguard_jax.baselines.unrocker)")
    cfg, params = load_dae(model_path)
    return cls(cfg, params)

  def init(self, ekf, readings):
    return jnp.zeros(())

  def post_ekf(self, sim, est, readings):
    alarm = jnp.asarray(sim["det"].alarm) > 0
    x_hat = dae_apply(self.cfg, self.params, recon.input_vector(est, readings))
    den = est.replace(pos=x_hat[0:3], vel=x_hat[3:6], quat=math3d.euler_to_quat(x_hat[9:12]))
    return sim, jax.tree.map(lambda a, b: jnp.where(alarm, a, b), den, est)


def _template(cfg: DAEConfig):
  net = DAENet(cfg.hidden, cfg.bottleneck, recon.N_INPUT)
  p = net.init(jax.random.PRNGKey(0), jnp.zeros((1, recon.N_INPUT)))
  return DAEParams(net=p, mean=jnp.zeros(recon.N_INPUT), std=jnp.ones(recon.N_INPUT))


def load_dae(path: str):
  """(DAEConfig, DAEParams) from a file written by specguard_jax.baselines.unrocker.build; one-line ValueError if
  corrupt."""
  _, meta = tree_file.load_tree(path)
  try:
    cfg = DAEConfig(hidden=tuple(meta["hidden"]), bottleneck=int(meta["bottleneck"]))
  except (KeyError, TypeError, ValueError) as e:
    raise ValueError(f"corrupt baseline cache {path}: bad DAE config ({e})") from None
  tree, _ = tree_file.load_tree(path, _template(cfg))
  return cfg, jax.tree.map(jnp.asarray, tree)
