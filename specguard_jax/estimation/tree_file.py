"""Pytrees of arrays with a JSON meta record in one msgpack file: the fitted models the baselines' in-tick estimators
load (software sensors' force model, UnRocker's DAE) and the baseline caches.
"""

from __future__ import annotations

import json
import os

import flax.serialization
import jax
import numpy as np


def save_tree(path: str, tree, meta: dict) -> None:
  """msgpack of {'meta': json string, 'tree': pytree of arrays}, written atomically."""
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  blob = flax.serialization.msgpack_serialize({"meta": json.dumps(meta),
                                               "tree": flax.serialization.to_state_dict(
                                                   jax.tree.map(np.asarray, tree))})
  tmp = path + ".tmp"
  with open(tmp, "wb") as f:
    f.write(blob)
  os.replace(tmp, path)


def load_tree(path: str, template=None):
  """(tree, meta) from save_tree's file; restored into `template`'s structure when given. Missing, corrupt or
  mismatched file -> one-line ValueError naming it."""
  try:
    with open(path, "rb") as f:
      d = flax.serialization.msgpack_restore(f.read())
    meta = json.loads(d["meta"])
    tree = d["tree"]
    if template is not None:
      tree = flax.serialization.from_state_dict(template, tree)
      bad = [(a.shape, b.shape) for a, b in zip(jax.tree.leaves(template), jax.tree.leaves(tree))
             if np.shape(a) != np.shape(b)]
      if bad or len(jax.tree.leaves(template)) != len(jax.tree.leaves(tree)):
        raise ValueError(f"shapes {bad[:2]} do not match")
  except Exception as e:  # noqa: BLE001 - msgpack/flax raise many unrelated types on corrupt input
    raise ValueError(f"corrupt baseline cache {path}: {' '.join(f'{type(e).__name__}: {e}'.split())[:200]} "
                     f"(delete it to retrain)") from None
  return tree, meta
