#!/usr/bin/env bash
# One device call for the acceptance figures of the training, rendering and reliability issues: build with
# CUDA, the CUDA fuzz corpus against the CPU kernels, a full default training run on fox-dark, the FPS of the
# trained scene at 640x360 and 500x375 (full enhanced render vs rasterization alone vs gsplat), and export +
# render through the CLI. Output under $OUT (or ./gpu_out). The scene travels as the carried folder
# .data/fox-dark (a copy of shared/data/fox-dark, never committed); gsplat and plyfile as wheels in .whl.
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
fi
export PYTHONPATH="$PWD:/tmp/site"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
t0=$(date +%s)
python3 setup.py build_ext --inplace > /tmp/build.log 2>&1 || { tail -30 /tmp/build.log; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
t0=$(date +%s)
timeout 120 python3 scripts/fuzz_cuda.py --cases ${FUZZ_CASES:-300} > "$OUT/fuzz_cuda.log" 2>&1
echo "fuzz_cuda: exit $? in $(( $(date +%s) - t0 )) s"; grep -c "^FAIL" "$OUT/fuzz_cuda.log"; tail -3 "$OUT/fuzz_cuda.log" | cut -c1-600
[ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
RUN=/tmp/runs/default; rm -rf $RUN; t0=$(date +%s)
timeout ${TRAIN_TIMEOUT:-300} python3 -m retinexgs train --data /tmp/fox-dark --out $RUN --device cuda --quiet \
  > "$OUT/train.log" 2>&1
echo "train: exit $? in $(( $(date +%s) - t0 )) s"; grep -vE "^\s*$" "$OUT/train.log" | tail -4
cp $RUN/metrics.json "$OUT/" 2>/dev/null
for size in "" "--width 500 --height 375"; do
  timeout 200 python3 -m retinexgs.bench fps --run $RUN --device cuda --vs gsplat $size 2>&1 | grep -v Warn \
    | tee -a "$OUT/fps.txt" | tail -8
done
t0=$(date +%s)
python3 -m retinexgs export --run $RUN --out /tmp/fox.ply --device cuda --quiet 2>&1 | tail -2
python3 -m retinexgs render --run $RUN --views test --maps enhanced,R,L --device cuda --out /tmp/r --quiet 2>&1 | tail -1
echo "export + render: $(( $(date +%s) - t0 )) s"
cp /tmp/runs/default/renders/test/0021.png "$OUT/panel_0021.png" 2>/dev/null
