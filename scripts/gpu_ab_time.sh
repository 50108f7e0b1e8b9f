#!/usr/bin/env bash
# Training time of two checkouts on one GPU machine, alone and interleaved (A B A B ...), so that a speed change is
# compared on the same card: the cards of one kind differ by a few per cent between machines.
#   OLD=.ab_old OUT=... WHL=.whl DATA=.data [CONFIG=default] [SCENE=fox-dark] [REPEATS=2] bash scripts/gpu_ab_time.sh
# OLD: a plain copy of the other commit's files (`git archive REV | tar x -C .ab_old`, ignored, carried); this
# checkout is "new". Prints each run's training-loop seconds (metrics.json), Gaussians and PSNR / SSIM.
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
WHL=${WHL:-.whl}; DATA=${DATA:-.data}; OLD=${OLD:?OLD: the other checkout}
if ! python3 -c "import pydantic, pycolmap, plyfile" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site "$WHL"/*.whl || exit 1
  export SITE=/tmp/site
fi
export PYTHONUNBUFFERED=1 MAX_JOBS=8 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
new=$PWD; old=$(cd "$OLD" && pwd)
for d in "$new" "$old"; do  # both builds at once
  (cd "$d" && python3 setup.py build_ext --inplace > build.log 2>&1 || { tail -20 build.log; exit 1; }) &
done
wait
echo "builds: $(( $(date +%s) - t0 )) s"
[ -d /tmp/data ] || cp -r "$DATA" /tmp/data
for i in $(seq "${REPEATS:-2}"); do
  for side in old new; do
    dir=$([ $side = old ] && echo "$old" || echo "$new"); run=/tmp/ab/$side-$i
    (cd "$dir" && PYTHONPATH="${SITE:+$SITE:}$dir" python3 -m retinexgs train --data /tmp/data/${SCENE:-fox-dark} \
      --config ${CONFIG:-default} --set seed=0 --out $run --device cuda --quiet > "$OUT/$side-$i.log" 2>&1)
    python3 -c "import json; m=json.load(open('$run/metrics.json')); t=m['train']; print('$side-$i', \
t['train_seconds'], 's', t['gaussians'], 'Gaussians', round(m['mean']['psnr'], 3), round(m['mean']['ssim'], 4))"
  done
done
nvidia-smi --query-gpu=name --format=csv,noheader
echo "total: $(( $(date +%s) - t0 )) s"
