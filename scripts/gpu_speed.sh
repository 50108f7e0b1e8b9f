#!/usr/bin/env bash
# Issue 13 on the GPU machine, in one call: build, CUDA tests, a timed fox-dark training alone (+ more seeds side
# by side), the FPS bench on it, train-speed and raster benches against gsplat, the step profile. Each stage writes
# under $OUT as it goes. Pick stages with STAGES (default: all):
#   STAGES="tests fuzz train fps trainspeed raster rprofile profile" SEEDS="0 1 2" VS=gsplat bash scripts/gpu_speed.sh
# Carry .data/fox-dark (copy of shared/data/fox-dark, never committed) and the wheels the machine lacks (pydantic,
# pycolmap, plyfile; gsplat for VS=gsplat: its kernels are JIT-built, ~80 s, started in the background first).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
STAGES=" ${STAGES:-tests train fps trainspeed raster profile} "
has() { [[ "$STAGES" == *" $1 "* ]]; }
WHL=${WHL:-.whl}
if [ -d "$WHL" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHL"/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD:${PYTHONPATH:-}" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; date -u
if [ "${VS:-}" = gsplat ]; then  # JIT-build gsplat's kernels while ours build
  (python3 -c "
import torch, gsplat
n = 64; d = 'cuda'
gsplat.rasterization(torch.randn(n, 3, device=d), torch.randn(n, 4, device=d), torch.rand(n, 3, device=d) * .1,
    torch.rand(n, device=d), torch.rand(n, 3, device=d), torch.eye(4, device=d)[None],
    torch.tensor([[[50., 0, 32], [0, 50., 32], [0, 0, 1]]], device=d), 64, 64)
print('gsplat ready')" > "$OUT/gsplat_build.log" 2>&1; echo "gsplat JIT: exit $? at $(( $(date +%s) - t0 )) s") &
fi
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { grep -E "error" -A3 "$OUT/build.log" | head -40; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
[ -d /tmp/fox-dark ] || cp -r "${FOX:-.data/fox-dark}" /tmp/fox-dark  # FOX: a copy of shared/data/fox-dark
if has tests; then
  timeout 150 python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short -rf tests/test_cuda*.py \
    tests/test_fused_colors.py tests/test_raster_finite_check.py > "$OUT/test_cuda.log" 2>&1
  echo "tests: exit $?"; grep -E "^FAILED|passed|failed" "$OUT/test_cuda.log" | head -30
fi
if has fuzz; then  # CUDA against the CPU kernels over the fuzz corpus
  timeout 120 python3 scripts/fuzz_cuda.py --cases ${FUZZ_CASES:-300} > "$OUT/fuzz_cuda.log" 2>&1
  echo "fuzz_cuda: exit $?"; grep -c "^FAIL" "$OUT/fuzz_cuda.log"; tail -3 "$OUT/fuzz_cuda.log" | cut -c1-400
fi
wait  # gsplat's build, before anything is timed
seeds=(${SEEDS:-0})
if has train; then
  t1=$(date +%s)
  python3 -m retinexgs train --data /tmp/fox-dark --out /tmp/runs/fox${seeds[0]} --device cuda --quiet \
    --set seed=${seeds[0]} ${TRAIN_ARGS:-} > "$OUT/train${seeds[0]}.log" 2>&1
  echo "train fox-dark seed ${seeds[0]} alone: exit $? in $(( $(date +%s) - t1 )) s wall"
  grep -E "trained|test views|graph|eager" "$OUT/train${seeds[0]}.log"
  t1=$(date +%s)
  for s in "${seeds[@]:1}"; do
    python3 -m retinexgs train --data /tmp/fox-dark --out /tmp/runs/fox$s --device cuda --quiet --set seed=$s \
      ${TRAIN_ARGS:-} > "$OUT/train$s.log" 2>&1 &
  done
  wait
  [ ${#seeds[@]} -gt 1 ] && echo "seeds ${seeds[*]:1} side by side: $(( $(date +%s) - t1 )) s wall"
  for s in "${seeds[@]}"; do
    python3 -c "import json; m=json.load(open('/tmp/runs/fox$s/metrics.json')); print('seed $s', json.dumps({**m['mean'], **m['train']}))" 2>&1 | tail -1
  done
fi
run=/tmp/runs/fox${seeds[0]}
if has fps && [ -f "$run/config.yaml" ]; then
  for r in $(seq "${FPS_RUNS:-1}"); do  # FPS_RUNS > 1: the bench again in the same call (frames move run to run)
    for size in "" "--width 500 --height 375"; do
      timeout 120 python3 -m retinexgs.bench fps --run "$run" --device cuda $size 2>&1 | grep -v -i warn \
        | tee -a "$OUT/fps.txt"
    done
  done
fi
if has trainspeed; then
  timeout 150 python3 -m retinexgs.bench train-speed --device cuda ${VS:+--vs $VS} 2>&1 | tee "$OUT/train_speed.txt"
  timeout 100 python3 -m retinexgs.bench train-speed --device cuda --data /tmp/fox-dark --warmup 3100 --steps 30 2>&1 \
    | tee -a "$OUT/train_speed.txt"
fi
if has raster; then  # RASTER_RUNS > 1: the same bench again in the same call (its ratios move run to run)
  for r in $(seq "${RASTER_RUNS:-1}"); do
    timeout 150 python3 -m retinexgs.bench raster --device cuda --vs ${VS:-reference} 2>&1 | tee -a "$OUT/bench_raster.txt"
  done
fi
has rprofile && timeout 200 python3 scripts/profile_raster.py > "$OUT/profile_raster.txt" 2>&1; \
  has rprofile && grep "==" "$OUT/profile_raster.txt"
has profile && timeout 100 python3 scripts/profile_train.py /tmp/fox-dark --steps 300 --profile 30 > "$OUT/profile_train.txt" 2>&1 \
  && head -5 "$OUT/profile_train.txt" | grep -v -i warn
echo "total: $(( $(date +%s) - t0 )) s"
