#!/usr/bin/env bash
# Issue 13's inference path on the GPU machine, in one call: build, the fused-colour / inference-renderer tests
# (CUDA vs CPU vs torch), compute-sanitizer on small frames, and the FPS bench (torch path, fused path, raster;
# launches per frame) at 640x360 and 500x375 plus a profile of the fused frame.
#   RUN=/path/to/trained/run bash scripts/gpu_frame.sh   (without RUN: trains fox-dark from .data first)
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD:${PYTHONPATH:-}" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { tail -20 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
python3 -m pytest -q -p no:cacheprovider --tb=short -rs tests/test_cuda_frame.py tests/test_fused_colors.py \
  > "$OUT/test_cuda_frame.log" 2>&1
grep -E "passed|failed|Error|error|assert|launches per frame" "$OUT/test_cuda_frame.log" | head -40
if [ "${SKIP_SANITIZER:-0}" != 1 ] && command -v compute-sanitizer >/dev/null; then
  for tool in memcheck racecheck; do
    compute-sanitizer --tool $tool --error-exitcode 9 python3 scripts/sanitize_frame.py > "$OUT/sanitizer_frame_$tool.log" 2>&1
    echo "compute-sanitizer $tool: exit $? ($(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$OUT/sanitizer_frame_$tool.log" | tail -1))"
  done
fi
RUN=${RUN:-}
if [ -z "$RUN" ]; then
  [ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
  RUN=/tmp/runs/fox
  [ -f "$RUN/metrics.json" ] || python3 -m retinexgs train --data /tmp/fox-dark --out "$RUN" --device cuda --quiet \
    > "$OUT/train.log" 2>&1
fi
python3 -m retinexgs.bench fps --run "$RUN" --device cuda 2>&1 | tee "$OUT/fps.txt"
python3 -m retinexgs.bench fps --run "$RUN" --device cuda --width 500 --height 375 2>&1 | tee -a "$OUT/fps.txt"
python3 scripts/profile_frame.py "$RUN" --fused > "$OUT/profile_frame_fused.txt" 2>&1
head -1 "$OUT/profile_frame_fused.txt"
echo "total: $(( $(date +%s) - t0 )) s"
