"""Small rotation helpers (pure jnp, any leading batch axes broadcast).

Quaternions are (w, x, y, z) rotating body -> world (MuJoCo). Euler angles are (roll, pitch, yaw), intrinsic Z-Y-X in
the ENU/FLU frames of `specguard_jax.types` (note: with FLU, a positive pitch tips the nose DOWN).
"""

import jax.numpy as jnp


def quat_to_rot(q):
  """[..., 4] quaternion -> [..., 3, 3] rotation matrix (body -> world)."""
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  r = jnp.stack([
      1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)
  return r.reshape(q.shape[:-1] + (3, 3))


def quat_to_euler(q):
  """[..., 4] quaternion -> [..., 3] (roll, pitch, yaw) in radians."""
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
  pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
  yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
  return jnp.stack([roll, pitch, yaw], axis=-1)


def euler_to_quat(e):
  """[..., 3] (roll, pitch, yaw) -> [..., 4] quaternion (w, x, y, z)."""
  cr, sr = jnp.cos(e[..., 0] / 2), jnp.sin(e[..., 0] / 2)
  cp, sp = jnp.cos(e[..., 1] / 2), jnp.sin(e[..., 1] / 2)
  cy, sy = jnp.cos(e[..., 2] / 2), jnp.sin(e[..., 2] / 2)
  return jnp.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                    cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=-1)


def quat_mul(a, b):
  """Hamilton product a * b of [..., 4] quaternions."""
  aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
  bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
  return jnp.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                    aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conj(q):
  return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


def yaw_rot2(yaw):
  """[...] yaw -> [..., 2, 2] planar rotation matrix."""
  c, s = jnp.cos(yaw), jnp.sin(yaw)
  return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def wrap_angle(a):
  """Wrap radians to (-pi, pi]."""
  return jnp.arctan2(jnp.sin(a), jnp.cos(a))


# Small-vector products written component-wise. jnp.linalg.norm / jnp.dot / `@` on [2]-[4] vectors lower to reductions
# and batched dots, and under vmap on a GPU every reduction or dot is a kernel of its own that XLA cannot fuse with its
# neighbours (written this way the PX4 cascade is about half as many kernels per tick). Sums of
# products of slices are elementwise over the batch and fuse into the surrounding kernels.


def hypot(*xs):
  """Euclidean norm of the components xs (arrays of one shape): sqrt of the sum of their squares."""
  return jnp.sqrt(sum(x * x for x in xs))


def norm(v):
  """[..., n] -> [...] Euclidean norm over the last axis (n small), as a sum of squares of its components."""
  return hypot(*(v[..., k] for k in range(v.shape[-1])))


def dot(a, b):
  """[..., n] . [..., n] -> [...] over the last axis (n small)."""
  return sum(a[..., k] * b[..., k] for k in range(a.shape[-1]))


def matvec(m, v):
  """[..., r, c] @ [..., c] -> [..., r] (c small)."""
  return sum(m[..., :, k] * v[..., None, k] for k in range(m.shape[-1]))


def matvec_t(m, v):
  """[..., r, c]' @ [..., r] -> [..., c] (r small): m transposed times v, without a transpose."""
  return sum(m[..., k, :] * v[..., k, None] for k in range(m.shape[-2]))


def with_component(v, k: int, x):
  """v [..., n] with component k (static) replaced by x [...]: `v.at[..., k].set(x)` as a select, which fuses."""
  return jnp.where(jnp.arange(v.shape[-1]) == k, jnp.expand_dims(x, -1), v)


def scale_head(v, k: int, f):
  """v [..., n] with its first k (static) components multiplied by f [...]: `v.at[..., :k].multiply(f)` as a select."""
  return jnp.where(jnp.arange(v.shape[-1]) < k, v * jnp.expand_dims(f, -1), v)


def rotvec_to_quat(v):
  """[3] rotation vector (rad) -> [4] unit quaternion; smooth at 0."""
  a2 = dot(v, v)
  small = a2 < 1e-8
  a = jnp.sqrt(jnp.where(small, 1.0, a2))
  s = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * a) / a)
  c = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * a))
  return jnp.concatenate([c[None], s * v])


def normalize_quat(q):
  """[4] -> [4] unit quaternion; the identity where q is not finite or ~0."""
  n = norm(q)
  ok = jnp.isfinite(n) & (n > 1e-6)
  return jnp.where(ok, q / jnp.where(ok, n, 1.0), jnp.array([1.0, 0.0, 0.0, 0.0]))
