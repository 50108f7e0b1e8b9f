#!/usr/bin/env bash
# Run-to-run spread at a fixed seed on the GPU machine: each scene trained twice with the same seed, side by side,
# to see how much of the seed-to-seed spread comes from the backward's float atomics (issue 12).
#   WHL=.whl6 DATA=.data2 SCENES="lom/buu lom/sofa lom/bike" SEED=0 bash scripts/gpu_repeat.sh
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
WHL=${WHL:-.whl}; DATA=${DATA:-.data}
if ! python3 -c "import pydantic" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$WHL"/*.whl || exit 1
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { tail -20 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"
[ -d /tmp/data ] || cp -r "$DATA" /tmp/data
for s in ${SCENES:-lom/buu lom/sofa lom/bike}; do
  for k in a b; do
    d=/tmp/rep/${s//\//-}-$k
    python3 -m retinexgs train --data /tmp/data/$s --out $d --device cuda --quiet --set seed=${SEED:-0} \
      > "$OUT/${s//\//-}-$k.log" 2>&1 &
  done
done
wait
for d in /tmp/rep/*; do
  python3 -c "import json; m=json.load(open('$d/metrics.json'))['mean']; print('$(basename $d)', round(m['psnr'], 3), round(m['ssim'], 4))"
done
echo "total: $(( $(date +%s) - t0 )) s"
