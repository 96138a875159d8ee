"""A mission's own geofence: QGroundControl inclusion / exclusion polygons and circles, and the home-centred fence of
an autopilot's parameters (PX4 GF_MAX_HOR_DIST / GF_MAX_VER_DIST, ArduPilot FENCE_RADIUS / FENCE_ALT_MAX).

Zones are 2D (a QGC .plan's `geoFence` has no altitudes: they hold at every height); the vertical limit is the
parameters' maximum altitude, which `envs.worlds.with_geofence` turns into the world's ceiling. Frames: world ENU
metres, home at the origin (every mission's home, generated or loaded).

Margins (m, > 0 on the allowed side): inclusion polygon / circle: the distance to its edge from inside (negative
outside); exclusion: the distance to its edge from outside (negative inside); the home fence: radius - |xy|.
Several inclusion zones combine as the autopilot does: PX4 (drone) needs the vehicle inside at least one of them
(their margins' maximum), ArduPilot (rover) inside all of them (their minimum); `any_inclusion` says which.

The arrays have exactly the plan's zone count (no padding between zones; polygons with fewer vertices than the
largest repeat their last vertex, a zero-length edge that changes no distance and no crossing count). An empty
geofence has zero-size arrays and costs the env step nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import geometry as geo


@struct.dataclass
class Geofence:
  """Geofence zones (add leading axes for a batch). P polygons of V vertices, C circles.

  polygons: [P, V, 2] vertices (x, y) m, in order (either orientation), implicitly closed.
  polygon_inclusion: [P] bool, True: the vehicle must stay inside; False: outside (exclusion).
  circles: [C, 3] (x, y, radius) m.  circle_inclusion: [C] bool, as polygon_inclusion.
  max_radius: static float, the home-centred fence's radius, m (0: none).
  any_inclusion: static bool, True: inside one inclusion zone is enough (PX4), False: inside all (ArduPilot).
  """

  polygons: jnp.ndarray
  polygon_inclusion: jnp.ndarray
  circles: jnp.ndarray
  circle_inclusion: jnp.ndarray
  max_radius: float = struct.field(pytree_node=False, default=0.0)
  any_inclusion: bool = struct.field(pytree_node=False, default=True)

  @property
  def n_zones(self) -> int:
    return int(self.polygons.shape[-3]) + int(self.circles.shape[-2])

  @property
  def active(self) -> bool:
    """Static: whether there is any zone or home fence (else the env step leaves the geofence out)."""
    return self.n_zones > 0 or self.max_radius > 0


def make_geofence(polygons=(), polygon_inclusion=(), circles=(), circle_inclusion=(), max_radius: float = 0.0,
                  any_inclusion: bool = True) -> Geofence:
  """A Geofence from Python lists: polygons a sequence of [V_i, 2] vertex lists (V_i >= 3), circles of (x, y, r)."""
  polys = [np.asarray(p, np.float32).reshape(-1, 2) for p in polygons]
  v = max((len(p) for p in polys), default=0)
  arr = np.zeros((len(polys), v, 2), np.float32)
  for i, p in enumerate(polys):
    arr[i, :len(p)] = p
    arr[i, len(p):] = p[-1]
  circ = np.asarray(circles, np.float32).reshape(-1, 3)
  return Geofence(polygons=jnp.asarray(arr), polygon_inclusion=jnp.asarray(np.asarray(polygon_inclusion, bool)),
                  circles=jnp.asarray(circ), circle_inclusion=jnp.asarray(np.asarray(circle_inclusion, bool)),
                  max_radius=float(max_radius), any_inclusion=bool(any_inclusion))


def empty_geofence() -> Geofence:
  """No zones and no home fence (zero-size arrays)."""
  return make_geofence()


def merge(a: Geofence, b: Geofence) -> Geofence:
  """The zones of both (unbatched), the smaller non-zero home radius; a's any_inclusion."""
  polys = [np.asarray(p)[:_n_vertices(p)] for g in (a, b) for p in np.asarray(g.polygons)]
  radii = [float(r) for r in (a.max_radius, b.max_radius) if float(r) > 0]
  return make_geofence(polys, np.concatenate([np.asarray(a.polygon_inclusion), np.asarray(b.polygon_inclusion)]),
                       np.concatenate([np.asarray(a.circles), np.asarray(b.circles)]),
                       np.concatenate([np.asarray(a.circle_inclusion), np.asarray(b.circle_inclusion)]),
                       min(radii, default=0.0), a.any_inclusion)


def _n_vertices(poly: np.ndarray) -> int:
  """Vertices of a padded polygon [V, 2] before its repeated last vertex."""
  n = len(poly)
  while n > 1 and np.array_equal(poly[n - 1], poly[n - 2]):
    n -= 1
  return n


def sdf_polygon(p_xy: jnp.ndarray, verts: jnp.ndarray) -> jnp.ndarray:
  """Signed horizontal distance from p_xy [2] to the simple polygon verts [V, 2] (< 0 inside, even-odd rule), m."""
  a, b = verts, jnp.roll(verts, -1, axis=0)
  d = jnp.min(jax.vmap(geo.dist_point_segment, (None, 0, 0))(p_xy, a, b))
  crosses = (a[:, 1] > p_xy[1]) != (b[:, 1] > p_xy[1])
  dy = jnp.where(crosses, b[:, 1] - a[:, 1], 1.0)
  x_at = a[:, 0] + (p_xy[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
  inside = jnp.sum(crosses & (p_xy[0] < x_at)) % 2 == 1
  return jnp.where(inside, -d, d)


def zone_margins(fence: Geofence, p_xy: jnp.ndarray) -> jnp.ndarray:
  """The margin [] (m, > 0 allowed) of p_xy [2] to the fence's zones and home fence (module docstring); geo.FAR
  when there is none."""
  far = jnp.float32(geo.FAR)
  sd_p = (jax.vmap(sdf_polygon, (None, 0))(p_xy, fence.polygons) if fence.polygons.shape[0]
          else jnp.zeros((0,), jnp.float32))
  sd_c = geo.safe_norm(p_xy[None] - fence.circles[:, :2]) - fence.circles[:, 2]
  sd = jnp.concatenate([sd_p, sd_c])
  inclusion = jnp.concatenate([fence.polygon_inclusion, fence.circle_inclusion])
  margin = jnp.where(inclusion, -sd, sd)
  excl = jnp.min(jnp.where(inclusion, far, margin), initial=far)
  incl_vals = jnp.where(inclusion, margin, -far if fence.any_inclusion else far)
  if fence.any_inclusion:
    incl = jnp.where(jnp.any(inclusion), jnp.max(incl_vals, initial=-far), far)
  else:
    incl = jnp.min(incl_vals, initial=far)
  home = fence.max_radius - geo.safe_norm(p_xy) if fence.max_radius > 0 else far
  return jnp.minimum(jnp.minimum(excl, incl), home)
