#!/usr/bin/env bash
# One device call's worth of GPU measurements (see BENCHMARKS.md). Usage on the GPU machine, from the repo root:
#   bash bench/gpu_suite.sh env|stl|fly|train [OUT_DIR]   (train: TRAIN_ARGS='--steps N ...')
#   bash bench/gpu_suite.sh cmd OUT_DIR python3 ...          (any command with the wheels installed)
# Expects the wheels of ../shared/tools/gpu-wheels.sh in .whl/ (mujoco, mujoco-mjx, brax are not in that image).
set -uo pipefail
what=${1:-env}
out=${2:-${OUT:-/tmp/out}}
mkdir -p "$out"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=$PWD:/tmp/site || exit 1
fi
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
case "$what" in
  env) python3 bench/env_throughput.py --envs ${ENVS:-4096 65536 262144} --steps ${STEPS:-20} --json "$out/env_throughput.json" 2>&1 | grep --line-buffered -v "import warp" | tee "$out/env_throughput.txt" ;;
  stl) python3 bench/stl_throughput.py --backend gpu 2>&1 | tee "$out/stl_throughput.txt" ;;
  fly) for v in ${VEHICLES:-drone rover}; do
         python3 -m envs.fly --vehicle $v --world all --missions ${MISSIONS:-1000} --json > "$out/fly_$v.json" 2> "$out/fly_$v.err"
         python3 -c "import json; d=json.load(open('$out/fly_$v.json')); [print('$v', r['world'], r['missions'], r['completion_rate'], r['collisions'], r['geofence_entries'], r['crashes'], r['stalls'], r['nan_resets'], r['truncated'], r['env_steps'], round(r['wall_s'],1)) for r in d['worlds']]" || tail -5 "$out/fly_$v.err"
       done ;;
  train) python3 train.py ${TRAIN_ARGS:-} --out "$out/run" 2>&1 | grep --line-buffered -v "import warp" | tee "$out/train.txt"
         cp "$out/run/summary.json" "$out/" 2>/dev/null; rm -rf "$out/run/checkpoints" ;;
  cmd) shift 2; "$@" 2>&1 | grep --line-buffered -v "import warp" ;;
esac
