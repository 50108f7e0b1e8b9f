#!/usr/bin/env bash
# One device call for the render/reliability issues: build with CUDA, run the CUDA fuzz corpus against the
# CPU kernels, train fox-dark briefly (densification complete) and time the full enhanced render vs the
# rasterization alone at 640x360 and 500x375. Each stage is bounded; output under $OUT (or ./gpu_out).
# The scene travels as the carried folder .data/fox-dark (a copy of shared/data/fox-dark, never committed).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
STEPS=${STEPS:-4000}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
t0=$(date +%s)
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { tail -30 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
if [ -f scripts/fuzz_cuda.py ]; then
  t0=$(date +%s)
  timeout ${FUZZ_TIMEOUT:-30} python3 scripts/fuzz_cuda.py ${FUZZ_ARGS:---cases 200} > "$OUT/fuzz_cuda.log" 2>&1
  echo "fuzz_cuda: exit $? in $(( $(date +%s) - t0 )) s"; tail -8 "$OUT/fuzz_cuda.log"
fi
[ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
rm -rf /tmp/runs/fps; t0=$(date +%s)
timeout ${TRAIN_TIMEOUT:-150} python3 -m retinexgs train --data /tmp/fox-dark --out /tmp/runs/fps --device cuda --quiet \
  --set steps=$STEPS --set density.stop=$STEPS --set checkpoint.every=$STEPS > "$OUT/train.log" 2>&1
echo "train ($STEPS steps): exit $? in $(( $(date +%s) - t0 )) s"; grep -vE "^\s*$" "$OUT/train.log" | tail -4
cp /tmp/runs/fps/metrics.json "$OUT/" 2>/dev/null
for size in "" "--width 500 --height 375"; do
  timeout 40 python3 -m retinexgs.bench fps --run /tmp/runs/fps --device cuda $size 2>&1 | tee -a "$OUT/fps.txt"
done
