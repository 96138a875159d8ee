"""Matplotlib figures of a mission: top-down map (obstacles, fences, boundary, the mission's own geofence zones and
rally points, path, trajectory) + altitude."""

from __future__ import annotations

import numpy as np


def plot_mission(path_png: str, world, mission, traj, title: str = "") -> None:
  """Write a PNG. world/mission: unbatched pytrees (numpy-able). traj: dict pos [T,3], est [T,3], valid [T]."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  from matplotlib.patches import Circle, Polygon, Rectangle

  w = {k: np.asarray(v) for k, v in vars(world).items() if k != "geofence"}
  fence = getattr(world, "geofence", None)
  valid = np.asarray(traj["valid"])
  pos = np.asarray(traj["pos"])[valid]
  est = np.asarray(traj["est"])[valid]
  n = int(mission.n_waypoints)
  wps = np.asarray(mission.waypoints)[:n]
  home = np.asarray(mission.home)
  fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.4, 1]})

  def prisms(arr, mask, **kw):
    for b, m in zip(arr, mask):
      if not m:
        continue
      cx, cy, hx, hy, yaw = b[:5]
      c, s = np.cos(yaw), np.sin(yaw)
      corners = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]]) @ np.array([[c, s], [-s, c]]) + [cx, cy]
      ax.add_patch(Polygon(corners, closed=True, **kw))

  for cyl, m in zip(w.get("cylinders", []), w.get("cylinder_mask", [])):
    if m:
      ax.add_patch(Circle(cyl[:2], cyl[2], color="forestgreen", alpha=0.6))
  prisms(w.get("boxes", []), w.get("box_mask", []), color="dimgray", alpha=0.6)
  prisms(w.get("fences", []), w.get("fence_mask", []), facecolor="red", alpha=0.15, edgecolor="red", hatch="//")
  if "boundary" in w and bool(w.get("boundary_on", w.get("has_boundary", False))):
    xmin, xmax, ymin, ymax = w["boundary"]
    ax.add_patch(Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, fill=False, edgecolor="red", lw=2, ls="--"))
  if fence is not None:   # the mission's own zones: inclusion green dashed, exclusion red hatched
    for poly, inc in zip(np.asarray(fence.polygons), np.asarray(fence.polygon_inclusion)):
      ax.add_patch(Polygon(poly, closed=True, fill=not inc, facecolor="red", alpha=0.15 if not inc else 1.0,
                           edgecolor="green" if inc else "red", lw=2, ls="--" if inc else "-",
                           hatch=None if inc else "xx"))
    for (cx, cy, r), inc in zip(np.asarray(fence.circles), np.asarray(fence.circle_inclusion)):
      ax.add_patch(Circle((cx, cy), r, fill=not inc, facecolor="red", alpha=0.15 if not inc else 1.0,
                          edgecolor="green" if inc else "red", lw=2, ls="--" if inc else "-"))
    if fence.max_radius > 0:
      ax.add_patch(Circle(home[:2], fence.max_radius, fill=False, edgecolor="green", lw=1.5, ls=":"))
  rally = w.get("rally_points", np.zeros((0, 3)))
  if len(rally):
    ax.scatter(rally[:, 0], rally[:, 1], c="orange", marker="P", s=90, zorder=6, label="rally points")
  path = np.vstack([home[None], wps])
  ax.plot(path[:, 0], path[:, 1], "k--", lw=1, label="mission path")
  ax.scatter(wps[:, 0], wps[:, 1], c="k", marker="x", zorder=5)
  for i, p in enumerate(wps):
    ax.add_patch(Circle(p[:2], float(mission.acceptance_radius), fill=False, color="k", lw=0.5))
    ax.annotate(f"W{i + 1}", p[:2], textcoords="offset points", xytext=(4, 4), fontsize=8)
  ax.plot(pos[:, 0], pos[:, 1], "b-", lw=1.5, label="true trajectory")
  ax.plot(est[:, 0], est[:, 1], "c:", lw=1, label="EKF estimate")
  ax.plot(home[0], home[1], "g^", ms=10, label="home")
  ax.set_aspect("equal")
  ax.set_xlabel("x east (m)")
  ax.set_ylabel("y north (m)")
  ax.legend(loc="best", fontsize=8)
  ax.set_title(title or "mission (top-down)")
  t = np.arange(len(pos)) * float(traj.get("dt", 0.1))
  ax2.plot(t, pos[:, 2], "b-", label="true altitude")
  ax2.plot(t, est[:, 2], "c:", label="EKF altitude")
  ax2.axhline(10, color="r", ls="--", lw=0.8, label="S3/S4 limits")
  ax2.axhline(20, color="r", ls="--", lw=0.8)
  ax2.set_xlabel("time (s)")
  ax2.set_ylabel("z (m)")
  ax2.legend(fontsize=8)
  ax2.set_title("altitude")
  fig.tight_layout()
  fig.savefig(path_png, dpi=110)
  plt.close(fig)
