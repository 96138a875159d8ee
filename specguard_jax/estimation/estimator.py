"""The interface of an in-tick recovery estimator (the prior-work baselines' SSR and UnRocker hooks, estimation.hooks).

Subclasses override what they change; the defaults pass readings and estimate through.
"""

from __future__ import annotations


class Estimator:
  """Identity hooks; subclasses override what they change."""

  def init(self, ekf, readings):
    raise NotImplementedError

  def pre_ekf(self, sim, readings):
    return sim, readings

  def post_ekf(self, sim, est, readings):
    del readings
    return sim, est
