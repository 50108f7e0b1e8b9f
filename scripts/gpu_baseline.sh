#!/usr/bin/env bash
# Issue 13's "before" figures on the GPU machine, in one call: one fox-dark training alone (wall time), the FPS
# bench on it at 640x360 and 500x375, and torch.profiler tables of training steps and of frames.
#   bash scripts/gpu_baseline.sh      (carry .data and .whl; output under $OUT)
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
[ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__, torch.version.cuda)"
t1=$(date +%s)
python3 -m retinexgs train --data /tmp/fox-dark --out /tmp/runs/fox --device cuda --quiet ${TRAIN_ARGS:-} \
  > "$OUT/train.log" 2>&1
echo "train fox-dark default, alone: exit $? in $(( $(date +%s) - t1 )) s (wall, incl. start-up)"
tail -3 "$OUT/train.log"
python3 -c "import json; m=json.load(open('/tmp/runs/fox/metrics.json')); print(json.dumps(m.get('mean'))); print(json.dumps(m.get('train')))"
python3 -m retinexgs.bench fps --run /tmp/runs/fox --device cuda 2>&1 | tee "$OUT/fps.txt"
python3 -m retinexgs.bench fps --run /tmp/runs/fox --device cuda --width 500 --height 375 2>&1 | tee -a "$OUT/fps.txt"
[ "${PROFILE:-1}" = 1 ] && python3 scripts/profile_train.py /tmp/fox-dark --steps 300 --profile 30 > "$OUT/profile_train.txt" 2>&1
[ "${PROFILE:-1}" = 1 ] && python3 scripts/profile_frame.py /tmp/runs/fox > "$OUT/profile_frame.txt" 2>&1
head -3 "$OUT/profile_train.txt" 2>/dev/null
echo "total: $(( $(date +%s) - t0 )) s"
