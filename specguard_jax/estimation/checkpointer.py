"""Checkpointer: a fixed-size ring buffer of trusted states and controls, frozen while the detector's alarm is up.

Entries are vectors: state [n_x] (see recon.CKPT_FIELDS: pos, vel, acc, quat, rate, gyro_bias, accel_bias) and
controls [n_u]. Pure JAX, jittable and vmappable (add leading batch axes with vmap).
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class CheckpointState:
  """states [W, n_x], controls [W, n_u]: the ring; head [] int32: slot of the NEXT write; count [] int32: valid
  entries (<= W); frozen [] bool: the alarm was up at the last update (no write happened)."""
  states: jnp.ndarray
  controls: jnp.ndarray
  head: jnp.ndarray
  count: jnp.ndarray
  frozen: jnp.ndarray


def ckpt_init(window: int, n_x: int, n_u: int) -> CheckpointState:
  """Empty buffer of `window` entries."""
  return CheckpointState(states=jnp.zeros((window, n_x)), controls=jnp.zeros((window, n_u)),
                         head=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32),
                         frozen=jnp.zeros((), bool))


def ckpt_update(c: CheckpointState, x, u, alarm) -> CheckpointState:
  """Record (x [n_x], u [n_u]) unless `alarm` ([] bool/0-1) is up; while it is, the buffer is frozen untouched and
  recording resumes on the first update after it clears.

  Writes the head row only (with its old value while frozen): a one-row scatter, which XLA does in place in a loop,
  where a select between the old and the updated ring rewrites all W rows every tick."""
  alarm = jnp.asarray(alarm) > 0
  w = c.states.shape[0]
  states = c.states.at[c.head].set(jnp.where(alarm, c.states[c.head], x))
  controls = c.controls.at[c.head].set(jnp.where(alarm, c.controls[c.head], u))
  head = jnp.where(alarm, c.head, (c.head + 1) % w)
  count = jnp.where(alarm, c.count, jnp.minimum(c.count + 1, w))
  return CheckpointState(states=states, controls=controls, head=head.astype(jnp.int32),
                         count=count.astype(jnp.int32), frozen=alarm)


def ckpt_slot(c: CheckpointState, k):
  """Ring slot (int32, any shape) of the ordered indices k (oldest -> newest, as in `ckpt_ordered`; clipped to the
  ring): reads one entry where `ckpt_ordered` gathers all W."""
  w = c.states.shape[0]
  return (c.head + jnp.clip(k, 0, w - 1)) % w


def ckpt_get(c: CheckpointState, age):
  """Entry `age` writes before the newest (age 0 = newest; clipped to the oldest valid one).
  Returns (state [n_x], controls [n_u], clipped age [] int32)."""
  w = c.states.shape[0]
  age = jnp.clip(jnp.asarray(age, jnp.int32), 0, jnp.maximum(c.count - 1, 0))
  idx = (c.head - 1 - age) % w
  return c.states[idx], c.controls[idx], age


def ckpt_ordered(c: CheckpointState):
  """The ring oldest -> newest: (states [W, n_x], controls [W, n_u], valid [W] bool)."""
  w = c.states.shape[0]
  idx = ckpt_slot(c, jnp.arange(w))
  valid = jnp.arange(w) >= w - c.count
  return c.states[idx], c.controls[idx], valid
