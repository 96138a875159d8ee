#!/usr/bin/env bash
# Training throughput of train.py (phase 1 only) against Brax's own ppo.train on the same env and sizes: 16,384 envs x
# 32-step unroll, 8 minibatches x 4 epochs, hidden 256 x 3 (BENCHMARKS.md, "Training vs Brax").
# Usage on the GPU machine, from the repo root, with the wheels of ../shared/tools/gpu-wheels.sh installed:
#   bash bench/trainer_vs_brax.sh OUT_DIR [flags for both trainers, e.g. --ekf-kernel xla]
# Env: STEPS (default 40000000); VARIANTS: ';'-separated extra train.py flags, one run each (default: one run with
# none; e.g. VARIANTS=';--matmul-precision bf16'); BRAX=0 skips Brax. Prints each train.py run's env steps/s per
# compiled call (from its metrics.jsonl; the first call carries the compile) and Brax's line.
set -uo pipefail
out=${1:?OUT_DIR}; shift
mkdir -p "$out"
steps=${STEPS:-40000000}
IFS=';' read -r -a variants <<< "${VARIANTS:-}"
[ ${#variants[@]} -eq 0 ] && variants=("")
i=0
for v in "${variants[@]}"; do
  run="$out/train_$i"; i=$((i + 1))
  # shellcheck disable=SC2086
  python3 train.py --phase1-steps "$steps" --phase2-steps 0 --eval-missions 0 --no-export --compile-cache off \
    --no-progress --out "$run" "$@" $v > "$run.log" 2>&1 || { echo "train.py $* $v failed:"; tail -5 "$run.log"; continue; }
  python3 - "$run/metrics.jsonl" "train.py $* $v" <<'PY'
import json, statistics, sys
recs = [json.loads(l) for l in open(sys.argv[1])]
sps = sorted({(r["iteration"], r["sps"]) for r in recs if r.get("phase") == 1})
per_call = []
for _, s in sps:
  if not per_call or per_call[-1] != s:
    per_call.append(s)
steady = per_call[1:]
print(f"{sys.argv[2].strip()}: {len(per_call)} calls, first {per_call[0]/1e6:.3f} M env steps/s (compile), then "
      f"median {statistics.median(steady)/1e6:.3f} M, max {max(steady)/1e6:.3f} M", flush=True)
PY
done
if [ "${BRAX:-1}" != 0 ]; then
  python3 bench/brax_ppo.py --envs 16384 --steps "$steps" --unroll 32 --minibatches 8 --epochs 4 --hidden 256 256 256 \
    --no-evals "$@" 2>&1 | grep -v -i warn | tail -2
fi
