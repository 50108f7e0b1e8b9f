#!/usr/bin/env bash
# One device call for quality and the frame path together: the quality groups of scripts/gpu_quality.sh (which
# builds first), the CUDA tests once the build is there (beside the trainings: nothing in them is timed), then,
# with the GPU free again, the FPS bench on the fox-dark default run of seed 0 if a group trained it (FPS_RUN: another
# run folder on the device, e.g. /tmp/runs/fox-dark/ablations-NAME/seed0).
#   TESTS="tests/test_cuda_frame.py ..." [TEST_LIMIT=200] OUT=... WHL=.whl DATA=.data LIMIT=540 bash scripts/gpu_session.sh GROUP...
# GROUP as in gpu_quality.sh (SEEDS:CONFIG[,CONFIG]:SCENE[,SCENE]:JOBS).
# ALONE="0,:default:fox-dark:1" first trains that group with the GPU to itself (a training time to report: the
# others share the GPU), results under $OUT/alone, before the groups and the tests start; the limit covers both.
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
t0=$(date +%s)
if [ -n "${ALONE:-}" ]; then
  OUT="$OUT/alone" bash scripts/gpu_quality.sh "$ALONE" > "$OUT/alone.log" 2>&1
  grep -E "^(build|ok|FAIL|reused)" "$OUT/alone.log"
  export LIMIT=$(( ${LIMIT:-520} - ($(date +%s) - t0) ))
fi
bash scripts/gpu_quality.sh "$@" > "$OUT/quality.log" 2>&1 &
qpid=$!
if [ -n "${TESTS:-}" ]; then
  until grep -q "^build:" "$OUT/quality.log" 2>/dev/null; do kill -0 $qpid 2>/dev/null || break; sleep 5; done
  if grep -q "^build:" "$OUT/quality.log"; then
    PYTHONPATH="/tmp/site:$PWD" timeout "${TEST_LIMIT:-200}" python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short -rf \
      $TESTS > "$OUT/test_cuda.log" 2>&1
    echo "tests: exit $? at $(( $(date +%s) - t0 )) s"; grep -E "^FAILED|passed|failed" "$OUT/test_cuda.log" | head -20
  fi
fi
wait $qpid
cat "$OUT/quality.log"
run=${FPS_RUN:-/tmp/runs/fox-dark/default/seed0}
if [ -f "$run/metrics.json" ]; then
  for size in "" "--width 500 --height 375"; do
    PYTHONPATH="/tmp/site:$PWD" timeout 60 python3 -m retinexgs.bench fps --run "$run" --device cuda $size 2>&1 \
      | grep -v -i "warn" | tee -a "$OUT/fps.txt"
  done
fi
echo "session total: $(( $(date +%s) - t0 )) s"
