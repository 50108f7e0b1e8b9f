#!/usr/bin/env bash
# The quality benchmark on the GPU machine, several groups side by side on one GPU:
#   bash scripts/gpu_quality.sh SEEDS:CONFIG[,CONFIG]:SCENE[,SCENE]:JOBS ...
# e.g. 0,:default:fox-dark,lom/buu,lom/sofa,lom/bike:4 0,1:paper:lom/buu:1 . SEEDS as bench quality's --seeds: a
# list has a comma ("0," is seed 0), a bare number is a count ("3" is seeds 0-2; "0" trains nothing). Scenes are
# read from the carried folder $DATA (default .data: copies of shared/data, never committed). Each group stops
# after ${LIMIT:-520} s (finished runs are kept; on a machine still warm, the same command again resumes cut-off
# runs from their checkpoints, every 2000 steps). Sizing, H100: a fresh machine builds in 130-170 s; 8 trainings
# side by side need about 420 s, 6 about 340, 4 about 225; the small results (metrics, logs, tables, contact
# sheets) are packed into $OUT/runs.tgz, beside $OUT/quality.md.
# The device machine has neither pydantic (a requirement since issue 15) nor pycolmap (the scenes' COLMAP points):
# carry their wheels as .whl (device README: pydantic, pydantic-core, annotated-types, typing-inspection, pycolmap,
# plyfile for Python 3.12, manylinux x86_64).
set -uo pipefail
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
WHL=${WHL:-.whl}; DATA=${DATA:-.data}  # carried folders: wheels, scene copies without their caches (64 MiB in all)
if ! python3 -c "import pydantic, pycolmap, plyfile" 2>/dev/null; then
  [ -d "$WHL" ] || { echo "pydantic, pycolmap or plyfile is missing here: carry its wheels in $WHL" \
    "(see the comment above)"; exit 1; }
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site "$WHL"/*.whl || exit 1
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
t0=$(date +%s)
python3 setup.py build_ext --inplace > "$OUT/build.log" 2>&1 || { tail -20 "$OUT/build.log"; exit 1; }
echo "build: $(( $(date +%s) - t0 )) s"; rm -f "$OUT/build.log"; mkdir -p /tmp/runs
[ -d /tmp/data ] || cp -r "$DATA" /tmp/data
left=$(( ${LIMIT:-520} - ($(date +%s) - t0) ))
i=0; all_configs=(); all_scenes=()
for group in "$@"; do
  IFS=: read -r seeds configs scenes jobs <<< "$group"
  dirs=(); for s in ${scenes//,/ }; do dirs+=("/tmp/data/$s"); done
  all_configs+=(${configs//,/ }); all_scenes+=("${dirs[@]}")
  timeout "$left" python3 -m retinexgs.bench quality --scenes "${dirs[@]}" --configs ${configs//,/ } --seeds "$seeds" \
    --runs /tmp/runs --jobs "$jobs" --device cuda --out "/tmp/runs/group$i.md" > "/tmp/runs/group$i.log" 2>&1 &
  i=$((i + 1))
done
wait
# One table and one contact sheet per scene over every group (nothing is trained here).
python3 -m retinexgs.bench quality --no-train --scenes $(printf '%s\n' "${all_scenes[@]}" | awk '!s[$0]++') \
  --configs $(printf '%s\n' "${all_configs[@]}" | awk '!s[$0]++') --seeds "${SEEDS_ALL:-0,1,2}" --runs /tmp/runs \
  --out "$OUT/quality.md" > /dev/null 2>&1
nvidia-smi --query-gpu=name --format=csv,noheader
# Every group's outcome; a group that trained nothing (a bad seed spec such as "0", which is a count of zero: "0,"
# is seed 0) shows its error instead of an empty line.
for f in /tmp/runs/group*.log; do echo "== $f"; grep -E "^(ok|FAIL|reused)|runs in" "$f" || tail -3 "$f"; done
# The contact sheets travel inside runs.tgz only: the device tool returns at most 8 files from $OUT, and
# gpu_session.sh's logs, an ALONE group's table and archive and this call's need all 8.
tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='tb' --exclude='renders' -C /tmp runs 2>/dev/null
echo "total: $(( $(date +%s) - t0 )) s"
