#!/usr/bin/env bash
# Train on fox-dark on the GPU machine: `bash scripts/gpu_train.sh NAME[:CONFIG] ...` runs each job in turn
# (CONFIG is a name in configs/, e.g. ablations/baseline_3dgs) and collects metrics under $OUT.
# The scene travels as the carried folder .data/fox-dark (a copy of shared/data/fox-dark, never committed).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { tail -20 "$OUT/build.log"; exit 1; }
[ -d /tmp/fox-dark ] || cp -r .data/fox-dark /tmp/fox-dark
for job in "$@"; do
  name=${job%%:*}; cfg=${job#*:}; args=()
  [ "$cfg" != "$job" ] && args+=(--config "$cfg")
  rm -rf "/tmp/runs/$name"
  t0=$(date +%s)
  python3 -m retinexgs train --data /tmp/fox-dark --out "/tmp/runs/$name" --device cuda --quiet "${args[@]}" \
    ${EXTRA_ARGS:-} > "/tmp/runs_$name.log" 2>&1
  echo "== $name ($cfg): exit $? in $(( $(date +%s) - t0 )) s"; grep -vE "^\s*$" "/tmp/runs_$name.log" | tail -4
  python3 -c "import json,sys; m=json.load(open('/tmp/runs/$name/metrics.json')); print('   ', json.dumps({**m.get('mean', {}), **m.get('train', {})}))" 2>/dev/null
done
tar czf "$OUT/runs.tgz" -C /tmp runs --exclude='*.pt' --exclude='tb' 2>/dev/null
