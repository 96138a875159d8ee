#!/usr/bin/env bash
# Wheel smoke test (CI, after the test suite): build the wheel of this checkout, install it NON-editable (with its
# dependencies) into a fresh venv, and from a directory outside the checkout make both envs (reset + one step) and
# run a tiny `specguard-train` to completion. Any error fails. Everything is written under a scratch directory in
# /tmp (removed at exit): nothing lands in the checkout, where pytest or git would see it.
# Env: PYTHON (default python3) makes the venv; KEEP=1 keeps the scratch directory.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d /tmp/specguard_wheel_smoke.XXXXXX)"
[ "${KEEP:-0}" = 1 ] || trap 'rm -rf "$work"' EXIT
t0=$SECONDS
# The checkout's files (tracked, plus untracked ones git does not ignore) copied to $work/src: setuptools writes
# build/ and *.egg-info beside the sources it builds.
mkdir "$work/src"
(cd "$root" && git ls-files -z --cached --others --exclude-standard | tar --null --ignore-failed-read -T - -cf -) \
  | tar -C "$work/src" -xf -
"${PYTHON:-python3}" -m venv "$work/venv"
py="$work/venv/bin/python"
"$py" -m pip install --quiet --upgrade pip
"$py" -m pip wheel --quiet --no-deps -w "$work/dist" "$work/src"
"$py" -m pip install --quiet "$work"/dist/specguard_jax-*.whl
rm -rf "$work/src"                                   # the installed wheel must stand alone
echo "[wheel smoke] built and installed $(basename "$work"/dist/*.whl) in $((SECONDS - t0)) s"
cd "$work"
JAX_PLATFORMS=cpu "$py" - <<'PY'
import os

import jax
import jax.numpy as jnp
import numpy as np

import envs
import specguard_jax
from specguard_jax import assets

site = os.path.dirname(os.path.dirname(specguard_jax.__file__))
assert site.endswith("site-packages") and os.path.dirname(envs.__file__).startswith(site), (specguard_jax.__file__,
                                                                                            envs.__file__)
assert assets.ASSETS_DIR == os.path.join(os.path.dirname(specguard_jax.__file__), "_assets"), assets.ASSETS_DIR
shipped = {f"{kind}_{v}.json" for kind in ("detector", "dynamics") for v in envs.VEHICLES} | {"drone.xml", "rover.xml"}
assert shipped <= set(os.listdir(assets.ASSETS_DIR)), os.listdir(assets.ASSETS_DIR)
data = os.path.join(os.path.dirname(envs.__file__), "data")
assert any(f.endswith(".plan") for f in os.listdir(data)), os.listdir(data)
for vehicle in envs.VEHICLES:
  env = envs.make(vehicle)
  state = jax.jit(env.reset)(jax.random.PRNGKey(0))
  state = jax.jit(env.step)(state, jnp.zeros(env.action_size))
  assert np.all(np.isfinite(np.asarray(state.obs))), vehicle
  print(f"[wheel smoke] {vehicle}: reset + step from {assets.ASSETS_DIR}")
PY
t1=$SECONDS
# Phase 1 only (phase 2 adds minutes of compile and no packaging); the held-out evaluation flies the attacked env
# with the detector preset and the fitted dynamics, and the export writes the ONNX policy.
JAX_PLATFORMS=cpu "$work/venv/bin/specguard-train" --vehicle drone --phase1-steps 2048 --phase2-steps 0 --envs 8 \
  --unroll 16 --eval-missions 2 --no-progress --compile-cache off --out "$work/run"
test -s "$work/run/summary.json" && test -s "$work/run/policy.onnx"
echo "[wheel smoke] specguard-train: $((SECONDS - t1)) s; smoke total $((SECONDS - t0)) s"
