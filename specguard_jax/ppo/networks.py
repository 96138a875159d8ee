"""Policy and value networks (Flax linen) and their action distributions.

SpecGuard's policy (paper App. "SpecGuard Training", after Swift): 4 fully connected layers over the env's observation
(envs.observation: the paper's 24 inputs, or 24 + the recovery context, the trainer's default). Default
`hidden=(256, 256, 256)` + the output layer = 4 Dense layers, tanh activations.

Action heads (`Policy.kind`):
  'discrete'  the paper's 6 actions U = {+x, -x, +y, -y, +z, -z} (categorical over 6 logits); action k becomes the
              velocity setpoint DIRECTIONS[k] * speeds in the vehicle's yaw frame (App. "Generating actuator
              commands": body-frame moves rotated by the heading, forwarded to the autopilot as override commands).
  'gaussian'  a continuous velocity setpoint: diagonal Gaussian over an unbounded vector a [n]; the env receives
              tanh(a) * speeds (the squashing belongs to the action adapter, so log-probabilities are the plain
              Gaussian's). Also used by the attack agent.
Everything is a pure function of (params, obs); params are plain dicts {'net': ..., 'log_std': ...}.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


@jax.custom_jvp
def tanh_stored(x):
  """tanh whose output is materialised and whose derivative, (1 + y)(1 - y), reads that output.

  Flax's `nn.tanh` leaves XLA free to store the pre-activation (z + b) instead and to recompute tanh wherever y is read:
  in the next layer's GEMM (a tanh in f32 on every operand load of XLA's Triton GEMM fusion) and in the backward's
  derivative. On a GPU those GEMMs run at about half the speed of the same shape without the activation in it
  (docs/PERFORMANCE.md). The optimization barrier makes the bias-add
  kernel write y = tanh(z + b) and every reader load it. Same values as nn.tanh (y rounded to the layer's dtype either
  way)."""
  return jax.lax.optimization_barrier(jnp.tanh(x))


@tanh_stored.defjvp
def _tanh_stored_jvp(primals, tangents):
  (x,), (dx,) = primals, tangents
  y = tanh_stored(x)
  return y, (dx + dx * y) * (1 - y)   # jax's own tanh rule, dx (1 + y)(1 - y): the same rounding


ACTIVATIONS = {"tanh": tanh_stored, "relu": nn.relu, "elu": nn.elu, "swish": nn.swish}
DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)
"""[6, 3] unit moves of the paper's discrete actions {+x, -x, +y, -y, +z, -z} (yaw frame)."""
ACTION_KINDS = ("discrete", "gaussian")
DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}
"""Compute dtypes of the networks' hidden layers (`MLP.dtype`): 'float32' (Flax's default) or 'bfloat16' (matmuls, bias
adds and activations in bf16; parameters and the output layer stay f32)."""


class MLP(nn.Module):
  """Dense layers of `sizes` (the last one linear, orthogonal init scaled by `final_scale`). dtype: a key of DTYPES,
  the hidden layers' compute dtype; the parameters are float32 either way, and the last (output) layer computes in
  float32, so logits, means and values keep f32 resolution."""
  sizes: Sequence[int]
  activation: str = "tanh"
  final_scale: float = 1.0
  dtype: str = "float32"

  @nn.compact
  def __call__(self, x):
    act = ACTIVATIONS[self.activation]
    for i, n in enumerate(self.sizes):
      last = i == len(self.sizes) - 1
      x = nn.Dense(n, kernel_init=nn.initializers.orthogonal(self.final_scale if last else np.sqrt(2.0)),
                   dtype=None if last else DTYPES[self.dtype], param_dtype=jnp.float32, name=f"dense_{i}")(x)
      if not last:
        x = act(x)
    return x


@dataclasses.dataclass(frozen=True)
class Policy:
  """A stochastic policy obs [.., n_obs] -> action. kind: 'discrete' (n logits) or 'gaussian' (n dims)."""
  kind: str
  n: int
  hidden: tuple = (256, 256, 256)
  activation: str = "tanh"
  init_log_std: float = -0.5
  dtype: str = "float32"   # the hidden layers' compute dtype (DTYPES); parameters and output layer stay float32

  def __post_init__(self):
    if self.kind not in ACTION_KINDS:
      raise ValueError(f"unknown action head {self.kind!r}; choose one of {ACTION_KINDS}")
    if self.activation not in ACTIVATIONS:
      raise ValueError(f"unknown activation {self.activation!r}; choose one of {', '.join(ACTIVATIONS)}")
    if self.dtype not in DTYPES:
      raise ValueError(f"unknown network dtype {self.dtype!r}; choose one of {', '.join(DTYPES)}")

  def module(self) -> MLP:
    return MLP(tuple(self.hidden) + (self.n,), self.activation, 0.01, self.dtype)

  def init(self, key, n_obs: int) -> dict:
    p = {"net": self.module().init(key, jnp.zeros((1, n_obs)))["params"]}
    if self.kind == "gaussian":
      p["log_std"] = jnp.full((self.n,), self.init_log_std, jnp.float32)
    return p

  def forward(self, params, obs):
    """Logits [.., n] (discrete) or Gaussian mean [.., n]."""
    return self.module().apply({"params": params["net"]}, obs)

  def sample(self, params, obs, key):
    """(action, log_prob): action int32 [..] (discrete) or float32 [.., n] (gaussian)."""
    out = self.forward(params, obs)
    if self.kind == "discrete":
      a = jax.random.categorical(key, out)
      return a.astype(jnp.int32), _cat_logp(out, a)
    std = jnp.exp(params["log_std"])
    a = out + std * jax.random.normal(key, out.shape)
    return a, _gauss_logp(out, params["log_std"], a)

  def log_prob_entropy(self, params, obs, action):
    """(log_prob [..], entropy [..]) of `action` under the policy at obs."""
    out = self.forward(params, obs)
    if self.kind == "discrete":
      logp_all = jax.nn.log_softmax(out)
      return _cat_logp(out, action), -jnp.sum(jnp.exp(logp_all) * logp_all, axis=-1)
    ent = jnp.sum(params["log_std"] + 0.5 * np.log(2 * np.pi * np.e)) * jnp.ones(out.shape[:-1])
    return _gauss_logp(out, params["log_std"], action), ent

  def mode(self, params, obs):
    """Deterministic action: argmax (discrete) or the mean (gaussian)."""
    out = self.forward(params, obs)
    return jnp.argmax(out, axis=-1).astype(jnp.int32) if self.kind == "discrete" else out


def _cat_logp(logits, a):
  return jnp.take_along_axis(jax.nn.log_softmax(logits), a[..., None].astype(jnp.int32), axis=-1)[..., 0]


def _gauss_logp(mean, log_std, a):
  z = (a - mean) / jnp.exp(log_std)
  return jnp.sum(-0.5 * z * z - log_std - 0.5 * np.log(2 * np.pi), axis=-1)


def value_module(hidden: Sequence[int], activation: str = "tanh", dtype: str = "float32") -> MLP:
  """State-value network obs -> [.., 1] (float32; `dtype`: the layers' compute dtype, see DTYPES)."""
  return MLP(tuple(hidden) + (1,), activation, 1.0, dtype)


def residual_cost(setpoint, speeds, active, cost: float):
  """The SpecGuard agent's cost of a residual setpoint (TrainConfig.action_cost): cost * sum((setpoint / speeds)^2) / 3
  over its outputs, where the residual is in effect (active [...] 0/1), in reward units per step: 0 for no residual,
  `cost` for a full-scale velocity residual, and as much again for a full-scale attitude residual (each output weighs
  the same with or without one). setpoint [..., n]; speeds [n] (TrainConfig.action_scales: m/s per axis, then m/s^2
  of an attitude residual). An output of scale 0 (no authority on it: its setpoint is always 0) costs nothing,
  rather than 0 / 0."""
  speeds = jnp.asarray(speeds, jnp.float32)
  scaled = jnp.where(speeds > 0, setpoint / jnp.where(speeds > 0, speeds, 1.0), 0.0)
  effort = jnp.sum(jnp.square(scaled), axis=-1) / 3.0
  return cost * active * effort


def to_setpoint(kind: str, action, speeds):
  """SpecGuard's action -> setpoint [.., n] (yaw frame): velocity [3] m/s, then, for a gaussian head of 6 outputs
  (EnvConfig.override_attitude), the acceleration residual [3] m/s^2. speeds: [n], the scale of each output."""
  speeds = jnp.asarray(speeds, jnp.float32)
  if kind == "discrete":
    return jnp.asarray(DIRECTIONS)[action] * speeds
  return jnp.tanh(action) * speeds
