#!/usr/bin/env bash
# Issue 13 on the GPU machine, in one call: build, CUDA tests, sanitizers, a timed fox-dark training alone, the
# FPS bench on it, step profile, train-speed and raster benches. Pick stages with STAGES (default: all):
#   STAGES="tests sanitize train fps profile trainspeed raster" bash scripts/gpu_speed.sh
# Carry .data/fox-dark (copy of shared/data/fox-dark, never committed) and .whl (pydantic, pycolmap, gsplat
# wheels: see the device README). VS=gsplat adds gsplat to the benches (its kernels are JIT-built: minutes).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
STAGES=" ${STAGES:-tests sanitize train fps profile trainspeed raster} "
has() { [[ "$STAGES" == *" $1 "* ]]; }
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD:${PYTHONPATH:-}" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; date -u
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { grep -E "error" -A3 "$OUT/build.log" | head -40; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
[ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
if has tests; then
  python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short tests/test_cuda*.py > "$OUT/test_cuda.log" 2>&1
  grep -E "passed|failed|Error|assert" "$OUT/test_cuda.log" | head -30
fi
if has sanitize && command -v compute-sanitizer >/dev/null; then
  for tool in memcheck racecheck; do
    compute-sanitizer --tool $tool --error-exitcode 9 python3 scripts/sanitize_small.py > "$OUT/sanitizer_$tool.log" 2>&1
    echo "compute-sanitizer $tool: exit $? ($(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$OUT/sanitizer_$tool.log" | tail -1))"
  done
fi
if has train; then
  for seed in ${SEEDS:-0}; do
    t1=$(date +%s)
    python3 -m retinexgs train --data /tmp/fox-dark --out /tmp/runs/fox$seed --device cuda --quiet --set seed=$seed \
      ${TRAIN_ARGS:-} > "$OUT/train$seed.log" 2>&1
    echo "train fox-dark seed $seed alone: exit $? in $(( $(date +%s) - t1 )) s wall"; grep -E "trained|test views" "$OUT/train$seed.log"
  done
fi
run=/tmp/runs/fox${SEEDS%% *}; run=${run% }
if has fps && [ -f "$run/config.yaml" ]; then
  for size in "" "--width 500 --height 375"; do
    python3 -m retinexgs.bench fps --run "$run" --device cuda $size ${VS:+--vs $VS} 2>&1 | tee -a "$OUT/fps.txt"
  done
fi
has profile && python3 scripts/profile_train.py /tmp/fox-dark --steps 300 --profile 30 > "$OUT/profile_train.txt" 2>&1 \
  && head -4 "$OUT/profile_train.txt" | grep -v Warn
if has trainspeed; then
  python3 -m retinexgs.bench train-speed --device cuda --data /tmp/fox-dark --warmup 3100 --steps 30 2>&1 | tee "$OUT/train_speed.txt"
  python3 -m retinexgs.bench train-speed --device cuda ${VS:+--vs $VS} 2>&1 | tee -a "$OUT/train_speed.txt"
fi
has raster && python3 -m retinexgs.bench raster --device cuda --vs ${VS:-reference} ${RASTER_ARGS:-} 2>&1 | tee "$OUT/bench_raster.txt"
echo "total: $(( $(date +%s) - t0 )) s"
