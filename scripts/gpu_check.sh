#!/usr/bin/env bash
# Everything the GPU machine must check, in one call: build with CUDA, CUDA-vs-CPU tests, compute-sanitizer,
# gsplat agreement and the side-by-side benchmark. Output under $OUT (or ./gpu_out).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
t0=$(date +%s)
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1; grep -E "retinexgs\]|error" "$OUT/build.log" | head -20
echo "build: $(( $(date +%s) - t0 )) s"
python3 -c "import torch, retinexgs._C as C; print('CUDA kernels built:', C.has_cuda)"
[ "${SKIP_TESTS:-0}" = 1 ] || python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short ${TEST_ARGS:-} tests/test_cuda.py > "$OUT/test_cuda.log" 2>&1; grep -E "passed|failed|Error|error|assert" "$OUT/test_cuda.log" | head -40
if [ "${SKIP_SANITIZER:-0}" != 1 ] && command -v compute-sanitizer >/dev/null; then
  for tool in memcheck racecheck; do
    compute-sanitizer --tool $tool --error-exitcode 9 python3 scripts/sanitize_small.py > "$OUT/sanitizer_$tool.log" 2>&1
    echo "compute-sanitizer $tool: exit $? ($(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$OUT/sanitizer_$tool.log" | tail -1))"
  done
fi
[ "${SKIP_BENCH:-0}" = 1 ] || python3 -m retinexgs.bench raster --device cuda --vs gsplat ${BENCH_ARGS:-} 2>&1 | tee "$OUT/bench_raster_cuda.txt"
