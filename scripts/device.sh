#!/usr/bin/env bash
# The one entry point for work on the GPU (device) machine: build the CUDA extension, then one MODE.
#
#   bash scripts/device.sh MODE [--option VALUE ...] [ARG ...]      (bash scripts/device.sh help: this text)
#
# Through the device tool: `run` executes a bash command in the repository root of a copy of this working tree
# on a GPU machine and returns what the command wrote under $OUT (at most 8 files, 2 folders down; every mode
# below keeps to that and packs the rest into $OUT/logs.tgz). Nothing can be fetched there, and a fresh machine
# is bare, so carry (git-ignored folders, 64 MiB in all, see /work/.library/device/README.md):
#   .data  the scenes, copied once from the shared data folder beside the checkout (../shared/data travels only
#          as a shared/ folder inside the checkout; if the checkout has one, shared/data is used when .data is
#          absent): mkdir -p .data && cp -r ../shared/data/fox-dark ../shared/data/lom .data/
#   .whl   the wheels the machine lacks, for Python 3.12 manylinux x86_64 (the README's `pip download` line):
#          pydantic, pydantic-core, annotated-types, typing-inspection (a requirement since issue 15), pycolmap
#          (the scenes' COLMAP points), plyfile; gsplat for --vs gsplat. Installed into /tmp/site.
# e.g. run(command="bash scripts/device.sh quality '0,:default:fox-dark,lom/buu,lom/sofa,lom/bike:4'",
#          carry=[".data", ".whl"], timeout_s=600)
# On a machine still warm, a second call reuses the build (build/), the wheels, the scene copy (/tmp/data) and
# finished runs (RUNS, /tmp/runs). Environment: OUT (default ./gpu_out), DATA (.data), WHL (.whl), RUNS (quality's
# runs; give each mode run side by side its own, so that their groups' logs and noise ladders do not collide),
# KEEP_BUILD (1: the CUDA build comes back under $OUT/cbuild; copied to .cbuild and carried, a later call on a fresh
# machine reuses it while csrc/, setup.py, the arch list and torch are unchanged), TORCH_CUDA_ARCH_LIST (9.0: H100/H200), MAX_JOBS (16), SKIP_SETUP (1: no wheel install or build, for modes run side by
# side on one machine, one per GPU with CUDA_VISIBLE_DEVICES and each its own OUT, after one `build`: they would race). Every option below may also be given as the upper-case
# environment variable (--fps-run X = FPS_RUN=X).
#
# Modes and what each writes under $OUT (always also logs.tgz: build log and every other log):
#   quality [GROUP...]  the quality benchmark: each GROUP = SEEDS:CONFIG[,CONFIG]:SCENE[,SCENE]:JOBS trains its
#       configs x scenes x seeds with `python -m retinexgs.bench quality` (JOBS side by side), all groups at once
#       on the one GPU; then one table over every group. Without GROUP, one group from --seeds (default "0,"),
#       --configs (default), --scenes (fox-dark,lom/buu,lom/sofa,lom/bike), --jobs (4); lists with commas or
#       spaces, e.g. quality --seeds 3 --configs "default ablations/baseline_pre" --jobs 6. SEEDS as bench quality's --seeds: a list has a comma ("0," is seed 0, "0,1,2"), a bare
#       number is a count ("3" = seeds 0-2). SCENE: a folder under .data. Options: --limit S (520: the groups
#       stop S s after the call began; finished runs stay, and the same command on the warm machine resumes
#       cut-off runs from their checkpoints, every 2000 steps), --steps N (override every config's steps),
#       --set KEY=VALUE (repeatable, every run), --seeds-all LIST (seeds of the final table; default: those of
#       the groups), --alone GROUP (trained first with the GPU to itself: a training time to report),
#       --tests "FILES" (pytest beside the trainings: nothing there is timed), --test-limit S (200), --ladder 1
#       (each SCENE's high/ photos darkened at every noise-ladder level, bench quality --noise-ladder: one group
#       a scene, since a group darkens its scenes as it starts),
#       --fps-run RUN (after the trainings, the FPS bench on that run; default the fox-dark default seed-0 run
#       when trained). Sizing, H100: build 130-170 s on a fresh machine; 8 trainings side by side about 420 s,
#       6 about 340, 4 about 225.
#       -> quality.md (table + contact sheets' names), runs.tgz (metrics, logs, tables, contact sheets; no
#          checkpoints or renders), alone.md (--alone), tests.log (--tests), fps.txt (--fps-run / fox-dark seed 0)
#   train [JOB...]  trainings through `python -m retinexgs train`, JOB = NAME[:CONFIG[:SCENE[:SEED]]] (default
#       `default`: configs/default.yaml on --scene fox-dark, --seed 0); prints each one's wall time, training
#       seconds, Gaussians, PSNR / SSIM. Options: --jobs N (1: in turn; N side by side, e.g. the same seed twice
#       for the run-to-run spread), --steps N, --set KEY=VALUE, --scene, --seed, --gpus G (job i on GPU i mod G: side by side
#       on a machine of G GPUs, each alone on its card).
#       -> train.txt (the summary), runs.tgz (metrics, configs, logs)
#   speed [STAGE...]  timings (default stages: train fps trainspeed raster profile):
#       train      a --scene training alone for each --seeds' first seed, the others side by side (wall time)
#       fps        `bench fps` on the trained run (or --run RUN) at 640x360 and 500x375, --fps-runs times
#                  (fused frame vs torch path vs rasterization; launches per frame; --vs gsplat adds gsplat)
#       trainspeed `bench train-speed` on synthetic scenes (--vs gsplat) and on --scene after 3100 warm-up steps
#       stream     `bench train-speed` on --scene with train.stream_views=never, always (the store pinned whole),
#                  always with train.views_pinned_gb=0 (staged view by view), --repeats times
#       raster     `bench raster --vs ${VS:-reference}`, --raster-runs times
#       profile    scripts/profiling.py train on --scene (PROFILE_WARMUP=300 warm-up steps, 30 profiled)
#       fprofile   scripts/profiling.py frame --fused on the run      rprofile  scripts/profiling.py raster
#       lr3m       scripts/profiling.py lr3m on --scene's first low-light photo
#       bigphoto   `bench lr3m` on --scene's first photo resized to 3000x4000 (12 MP), on tiles (tile_memory_share=0),
#                  whole (tile_pixels=1e9) and as the default decides: time and peak GPU memory, no metrics
#       export     `retinexgs export` and `retinexgs render --maps enhanced,R,L` of the run, timed
#       ab         A/B training time against another checkout --old DIR (a plain copy, e.g. `git archive REV |
#                  tar x -C .ab_old`, carried; its .cbuild, a copy of the LPIPS weights and a build of the same
#                  kernel sources are reused): old, new, old, new... (--repeats 2) on one card, so that a
#                  speed change is compared on the same card (cards of one kind differ by a few per cent)
#       Options: --scene fox-dark, --seeds "0" (e.g. "0 1 2"), --config NAME, --set KEY=VALUE, --run RUN,
#       --vs gsplat (its kernels JIT-build, ~80 s, started beside our build), --fps-runs 1, --raster-runs 1,
#       --old DIR, --repeats 2.
#       -> STAGE.txt for each stage run (train.txt, fps.txt, trainspeed.txt, raster.txt, profile.txt, ...);
#          more than 8 files in all are packed into all.tgz
#   tests [TEST...] [-- PYTEST_OPTION...]  the GPU tests: pytest on TEST (default tests/test_cuda*.py
#       tests/test_fused_colors.py tests/test_raster_finite_check.py), the CUDA fuzz (scripts/fuzz_cuda.py: CUDA vs
#       the CPU kernels over the shared corpus) and compute-sanitizer on scripts/sanitize.py's targets. Options:
#       --test-limit S (200), --fuzz-cases N (300; 0 skips), --sanitizer "memcheck racecheck" (none skips),
#       --targets "raster frame". Exit status 1 if any part failed.
#       -> tests.log, fuzz_cuda.log, sanitizer.log
#   scale [ARGS...]  the large-scene benchmark, `python -m retinexgs.bench scale ARGS` (its --help): a synthetic
#       dark scene (default 1000 views at 1920x1080, generated on the GPU into /tmp/retinexgs-scale while the
#       extension builds, reused on a warm machine) or --scene NAME (a folder under .data, or a path), trained with
#       each --gpus count at equal --views-seen. Options of this script: --limit S (560: the benchmark stops S s
#       after the call began; the tables keep the runs that finished). Tables and runs go to --out (default
#       /tmp/scale). E.g. run(command="bash scripts/device.sh scale --gpus 1,2,4 --views-seen 2000 --decompose none",
#       kind="nvidia-h100-x4", carry=[".whl"]). Where retinexgs/bench/scale.py is missing it exits 2.
#       -> scale.md (the table, the memory estimate), scale.json (every figure), runs.tgz (metrics, configs, logs)
#   bigraw [ARGS...]  the 12 MP raw night scene end to end (issue 65), `python -m retinexgs.bench bigraw ARGS` (its
#       --help): the demo's large scene (default 40 + 4 views at 4000x3000, generated on the GPU into
#       /tmp/retinexgs-scale while the extension builds, not timed, reused on a warm machine), `darken --raw` once
#       (timed, --jobs: one per core), then each row of --configs trains the DNGs in turn from cold caches, decode +
#       denoise + LR3M inside the timed training. --configs "ROW|ROW|...": a ROW is a config name and/or KEY=VALUE
#       overrides separated by spaces, e.g. --configs "default steps=3000|train.resolution=[[0.8,4],[0.95,2]]|
#       data.downscale=2" (the last: the same views at half size). --steps N: every row's but a row's own steps=;
#       --set KEY=VALUE: every row; --gpu-memory-gb G: each training under a G GB cap (24: a 4090's memory);
#       --side-by-side: every row at once (a PSNR comparison; times shared). Each run's log line carries its second.
#       Options of this script: --limit S (560: the running training gets SIGINT about
#       S - 40 s after the call began, later rows are not run; the tables keep what finished, and the same command on
#       the warm machine reads finished rows back and runs the rest). Tables and runs go to --out (default
#       /tmp/bigraw). E.g. run(command="bash scripts/device.sh bigraw --steps 10000 --configs
#       'train.resolution=[[0.8,4],[0.95,2]]|data.downscale=2'", carry=[".whl"]).
#       -> bigraw.md (the table), bigraw.json (every figure), runs.tgz (metrics, configs, logs; no checkpoints,
#          renders, caches or photos)
#   build  the set-up alone (wheels, build, GPU and torch versions); -> nothing but logs.tgz
#   compile  every csrc/cuda/*.cu through nvcc for sm_89 and sm_90, without torch, a GPU or the set-up (what CI
#       runs where nvcc exists): a syntax or type error in a kernel fails here.
set -uo pipefail
cd "$(dirname "$0")/.." || exit 1
T0=$(date +%s)
OUT=${OUT:-gpu_out}
DATA=${DATA:-}
WHL=${WHL:-.whl}
LOGS=/tmp/device-logs
SETS=()

die() { echo "device.sh: $*" >&2; exit 1; }
elapsed() { echo $(( $(date +%s) - T0 )); }
usage() { sed -n '2,/^set -uo/p' "$0" | sed '$d; s/^# \{0,1\}//'; }

# parse "OPTION..." ARGS...: --option VALUE or --option=VALUE sets $OPTION (upper case, - as _), --set KEY=VALUE
# adds to SETS; anything else goes to the array ARGS, and everything after -- to the array PASS.
parse() {
  local allowed=" $1 " k v; shift
  ARGS=() PASS=()
  while [ $# -gt 0 ]; do
    case $1 in
      --) shift; PASS=("$@"); break ;;
      --*=*) k=${1%%=*}; v=${1#*=}; shift ;;
      --*) k=$1; [ $# -ge 2 ] || die "$1 needs a value"; v=$2; shift 2 ;;
      *) ARGS+=("$1"); shift; continue ;;
    esac
    k=${k#--}
    if [ "$k" = set ]; then SETS+=(--set "$v"); continue; fi
    [[ $allowed == *" $k "* ]] || die "unknown option --$k for $MODE (options:${allowed% })"
    k=${k//-/_}
    printf -v "${k^^}" '%s' "$v"
  done
}

# The shared set-up of every GPU mode: wheels, environment, build with CUDA; the scenes with stage_data.
setup() { setup_env; setup_build; }
setup_env() {  # the wheels and the environment (enough for code that needs no compiled extension)
  mkdir -p "$OUT" "$LOGS"
  export PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
  SITE=
  if [ "${SKIP_SETUP:-0}" = 1 ]; then  # a mode beside another on one machine: the wheels are installed already
    [ -d /tmp/site ] && SITE=/tmp/site
  elif compgen -G "$WHL/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      "$WHL"/*.whl > "$LOGS/wheels.log" 2>&1 || { tail -20 "$LOGS/wheels.log"; die "the wheels in $WHL did not install"; }
    SITE=/tmp/site
  fi
  export PYTHONPATH="$PWD${SITE:+:$SITE}${PYTHONPATH:+:$PYTHONPATH}"
  python3 -c "import pydantic" 2> /dev/null \
    || die "pydantic is missing here: carry its wheels in $WHL (see the header of scripts/device.sh)"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  python3 -c "import torch; print('torch', torch.__version__, 'CUDA', torch.version.cuda)"
}
has_cuda_build() { python3 -c "import sys, torch, retinexgs._C as C; sys.exit(0 if C.has_cuda else 1)"; }
setup_build() {  # the CUDA extension (setup_env first)
  local t=$SECONDS
  if [ "${SKIP_SETUP:-0}" = 1 ]; then  # a re-run of setup.py would re-copy the .so under a running mode
    has_cuda_build || die "SKIP_SETUP=1 but no CUDA build here: run \`bash scripts/device.sh build\` first"
    echo "build: skipped (SKIP_SETUP=1)"; return
  fi
  local stamp; stamp=$(build_stamp)
  if [ -f .cbuild/stamp ] && [ "$(cat .cbuild/stamp)" = "$stamp" ] && compgen -G ".cbuild/_C*.so.gz" > /dev/null; then
    local gz; for gz in .cbuild/_C*.so.gz; do gunzip -c "$gz" > "retinexgs/$(basename "${gz%.gz}")"; done
    # (a build of these very sources, carried back from an earlier call)
    has_cuda_build && { echo "build: reused from .cbuild (sources unchanged)"; return; }
  fi
  python3 setup.py build_ext --inplace > "$LOGS/build.log" 2>&1 \
    || { grep -E "error" -A3 "$LOGS/build.log" | head -40; tail -20 "$LOGS/build.log"; cp "$LOGS/build.log" "$OUT/";
         die "build failed (build.log)"; }
  has_cuda_build || die "retinexgs._C was built without its CUDA kernels (see build.log in logs.tgz)"
  echo "build: $(( SECONDS - t )) s (TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST)"
  if [ "${KEEP_BUILD:-0}" = 1 ]; then  # the build back under $OUT/cbuild: copy it to .cbuild and carry it next time
    mkdir -p "$OUT/cbuild" && echo "$stamp" > "$OUT/cbuild/stamp"  # gzipped: a file comes back only up to 16 MiB
    local so; for so in retinexgs/_C*.so; do  # without its debug sections: smaller, the same code
      strip -g -o /tmp/cbuild.so "$so" 2> /dev/null || cp "$so" /tmp/cbuild.so
      gzip -9 -c /tmp/cbuild.so > "$OUT/cbuild/$(basename "$so").gz"
    done
  fi
}
# What a build depends on: the kernel sources, setup.py, the arch list, torch's and Python's versions.
build_stamp() {
  { find csrc -type f | LC_ALL=C sort | xargs sha256sum; sha256sum setup.py; echo "$TORCH_CUDA_ARCH_LIST";
    python3 -c "import sys, torch; print(torch.__version__, sys.version_info[:2])"; } | sha256sum | cut -c1-16
}

# Copy the scenes to /tmp/data (missing files only: a warm machine keeps the earlier copy).
stage_data() {
  local src=$DATA
  if [ -z "$src" ]; then
    for d in .data shared/data; do [ -d "$d" ] && { src=$d; break; }; done
  fi
  [ -n "$src" ] && [ -d "$src" ] || die "no scenes: carry .data (a copy of ../shared/data), or set DATA"
  mkdir -p /tmp/data && { cp -rn "$src"/. /tmp/data/ 2>&1 | grep -v "behavior of -n is non-portable"; true; }
}
need_scene() { [ -d "/tmp/data/$1" ] || die "scene $1 is not under ${DATA:-.data} (/tmp/data has: $(ls /tmp/data))"; }
# A scene trained as it is needs its dark photos (a copy made for the raw ladder keeps high/ and the poses only).
need_photos() {
  need_scene "$1"
  if [ -f "/tmp/data/$1/transforms_train.json" ] && [ ! -d "/tmp/data/$1/low" ]; then
    die "scene $1 has no low/ photos under ${DATA:-.data}: copy them in (cp -r ../shared/data/$1/low ${DATA:-.data}/$1/)"
  fi
}
need_train_wheels() {
  python3 -c "import pycolmap, plyfile" 2> /dev/null \
    || die "pycolmap or plyfile is missing here: carry their wheels in $WHL (see the header)"
}

# Each mode ends here: the logs into logs.tgz; more than the 8 files the device tool returns into all.tgz.
finish() {
  local rc=${1:-0}
  [ -d "$LOGS" ] && tar czf "$OUT/logs.tgz" -C "$LOGS" . 2> /dev/null
  if [ "$(find "$OUT" -type f | wc -l)" -gt 8 ]; then
    tar czf /tmp/device-all.tgz -C "$OUT" . && find "$OUT" -mindepth 1 -delete && mv /tmp/device-all.tgz "$OUT/all.tgz"
    echo "(more than 8 files under \$OUT: packed into all.tgz)"
  fi
  echo "total: $(elapsed) s"
  exit "$rc"
}

metrics() {  # metrics LABEL RUN: one line of a run's metrics.json
  python3 - "$1" "$2" << 'EOF'
import json, sys
label, run = sys.argv[1:]
try:
    m = json.load(open(f"{run}/metrics.json"))
except OSError:
    sys.exit(print(f"{label}: no metrics.json"))
t, mean = m.get("train", {}), m.get("mean", {})
print(f"{label}: train {t.get('train_seconds', '?')} s, {t.get('gaussians', '?')} Gaussians, "
      f"PSNR {mean.get('psnr', float('nan')):.3f}, SSIM {mean.get('ssim', float('nan')):.4f}")
EOF
}

commas() { tr -s ', ' '\n' <<< "$1" | grep -v '^$' | paste -sd, -; }  # "a b,c" -> a,b,c

seeds_of() {  # a bench-quality seed spec -> its seeds, one a line
  if [[ $1 == *,* ]]; then tr ',' '\n' <<< "$1" | grep -v '^$'; elif [ "$1" -gt 0 ] 2> /dev/null; then seq 0 $(( $1 - 1 )); fi
}

fps_bench() {  # fps_bench RUN FILE: the FPS bench at 640x360 and 500x375
  local size
  for size in "" "--width 500 --height 375"; do
    # shellcheck disable=SC2086  # $size: two options or none
    timeout 120 python3 -m retinexgs.bench fps --run "$1" --device cuda $size ${VS:+--vs "$VS"} 2>&1 \
      | grep -v -i warn | tee -a "$2"
  done
}

# ---------------------------------------------------------------------------------------------------- quality
# quality's groups: SEEDS:CONFIGS:SCENES:JOBS. note_group checks one and adds it to the final table's lists;
# run_group NAME GROUP trains it with `bench quality` until --limit.
note_group() {
  local seeds configs scenes jobs s
  IFS=: read -r seeds configs scenes jobs <<< "$1"
  [ -n "$jobs" ] && [ -n "$scenes" ] && [ -n "$configs" ] || die "group $1 is not SEEDS:CONFIGS:SCENES:JOBS"
  # shellcheck disable=SC2206  # configs: comma-separated names
  ALL_CONFIGS+=(${configs//,/ })
  for s in ${scenes//,/ }; do need_scene "$s"; ALL_SCENES+=("/tmp/data/$s"); done
  mapfile -t -O "${#ALL_SEEDS[@]}" ALL_SEEDS < <(seeds_of "$seeds")
}
run_group() {
  local seeds configs scenes jobs s dirs=() left
  IFS=: read -r seeds configs scenes jobs <<< "$2"
  for s in ${scenes//,/ }; do dirs+=("/tmp/data/$s"); done
  left=$(( LIMIT - $(elapsed) ))
  [ "$left" -gt 0 ] || { echo "group $1 ($2): no time left under --limit $LIMIT"; return; }
  # shellcheck disable=SC2086  # configs: comma-separated names
  timeout "$left" python3 -m retinexgs.bench quality --scenes "${dirs[@]}" --configs ${configs//,/ } \
    --seeds "$seeds" --runs "$RUNS" --jobs "$jobs" --device cuda "${EXTRA[@]}" --out "$RUNS/$1.md" \
    > "$RUNS/$1.log" 2>&1
}

mode_quality() {
  LIMIT=${LIMIT:-520} STEPS=${STEPS:-} SEEDS_ALL=${SEEDS_ALL:-} ALONE=${ALONE:-} TESTS=${TESTS:-}
  TEST_LIMIT=${TEST_LIMIT:-200} FPS_RUN=${FPS_RUN:-}
  SEEDS=${SEEDS:-0,} CONFIGS=${CONFIGS:-default} SCENES=${SCENES:-fox-dark,lom/buu,lom/sofa,lom/bike} JOBS=${JOBS:-4}
  LADDER=${LADDER:-0} RUNS=${RUNS:-/tmp/runs}
  parse "seeds configs scenes jobs limit steps seeds-all alone tests test-limit fps-run ladder" "$@"
  local groups=("${ARGS[@]}")
  if [ ${#groups[@]} -eq 0 ]; then  # one group from the options (lists: commas or spaces)
    groups=("$SEEDS:$(commas "$CONFIGS"):$(commas "$SCENES"):$JOBS")
  fi
  setup; need_train_wheels; stage_data
  mkdir -p "$RUNS"
  EXTRA=("${SETS[@]}"); [ -n "$STEPS" ] && EXTRA+=(--steps "$STEPS")
  local ladder=(); [ "$LADDER" = 1 ] && ladder=(--noise-ladder) && EXTRA+=(--noise-ladder)
  local group i=0 pids=()
  ALL_CONFIGS=() ALL_SCENES=() ALL_SEEDS=()
  for group in ${ALONE:+"$ALONE"} "${groups[@]}"; do note_group "$group"; done  # every scene there, first
  if [ -n "$ALONE" ]; then
    run_group alone "$ALONE"
    cp "$RUNS/alone.md" "$OUT/alone.md" 2> /dev/null
    echo "== alone ($ALONE):"; grep -E "^(ok|FAIL|reused)" "$RUNS/alone.log"
  fi
  for group in "${groups[@]}"; do
    run_group "group$i" "$group" &
    pids+=($!); i=$((i + 1))
  done
  if [ -n "$TESTS" ]; then  # beside the trainings: nothing in the tests is timed
    # shellcheck disable=SC2086  # a list of test files
    timeout "$TEST_LIMIT" python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short -rf $TESTS \
      > "$OUT/tests.log" 2>&1
    echo "tests: exit $? at $(elapsed) s"; grep -E "^FAILED|passed|failed" "$OUT/tests.log" | head -20
  fi
  wait "${pids[@]}"
  [ -n "$SEEDS_ALL" ] || SEEDS_ALL=$(printf '%s\n' "${ALL_SEEDS[@]}" | sort -nu | paste -sd, -)
  [[ $SEEDS_ALL == *,* ]] || SEEDS_ALL="$SEEDS_ALL,"
  # One table and one contact sheet per scene over every group (nothing is trained here).
  # shellcheck disable=SC2046  # one word a scene / config
  python3 -m retinexgs.bench quality --no-train --scenes $(printf '%s\n' "${ALL_SCENES[@]}" | awk '!s[$0]++') \
    --configs $(printf '%s\n' "${ALL_CONFIGS[@]}" | awk '!s[$0]++') --seeds "$SEEDS_ALL" --runs "$RUNS" \
    "${ladder[@]}" --out "$OUT/quality.md" > "$LOGS/table.log" 2>&1 || tail -5 "$LOGS/table.log"
  # Every group's outcome; a group that trained nothing (a bad seed spec such as "0", a count of zero: "0," is
  # seed 0) shows its error instead.
  for f in "$RUNS"/group*.log; do echo "== $f"; grep -E "^(ok|FAIL|reused)|runs in" "$f" || tail -3 "$f"; done
  local run=${FPS_RUN:-$RUNS/fox-dark/default/seed0}
  [ -f "$run/metrics.json" ] && fps_bench "$run" "$OUT/fps.txt"
  tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='tb' --exclude='renders' --exclude="$(basename "$RUNS")/ladder" -C "$(dirname "$RUNS")" "$(basename "$RUNS")" 2> /dev/null
  finish 0
}

# ------------------------------------------------------------------------------------------------------ bench
# bench "ARGS" ["ARGS" ...]: each quoted argument one `python -m retinexgs.bench quality ARGS --runs $RUNS
# --device cuda`, all side by side (give each its own --gpus/--jobs share), scenes named as /tmp/data/SCENE or as
# ladder folders under $RUNS/ladder; a first ARGS with --no-train (e.g. making a --raw-ladder) runs alone first.
# Options: --limit S (540: every bench stops S s after the call began; the same call on the warm machine reuses
# finished runs and resumes cut-off ones). -> quality-N.md per bench, runs.tgz (metrics, logs, sheets)
mode_bench() {
  LIMIT=${LIMIT:-540} RUNS=${RUNS:-/tmp/runs}
  parse "limit" "$@"
  setup; need_train_wheels; stage_data
  python3 -c "import rawpy, exifread" 2> /dev/null || die "rawpy or exifread is missing here: carry their wheels"
  mkdir -p "$RUNS"
  local i=0 pids=() a
  for a in "${ARGS[@]}" "${PASS[@]}"; do
    local left=$(( LIMIT - $(elapsed) ))
    # shellcheck disable=SC2086  # ARGS: one bench's arguments, split on spaces
    if [[ $a == *--no-train* ]]; then
      timeout "$left" python3 -m retinexgs.bench quality $a --runs "$RUNS" --device cuda > "$RUNS/bench$i.log" 2>&1
      echo "bench$i (no training): exit $? at $(elapsed) s"; tail -3 "$RUNS/bench$i.log"
    else
      timeout "$left" python3 -m retinexgs.bench quality $a --runs "$RUNS" --device cuda --out "$RUNS/quality-$i.md" \
        > "$RUNS/bench$i.log" 2>&1 &
      pids+=($!)
    fi
    i=$((i + 1))
  done
  wait "${pids[@]}"
  for f in "$RUNS"/bench*.log; do echo "== $f"; grep -E "^(ok|FAIL|reused)|runs in" "$f" | sed 's/^/  /' | tail -80; done
  cp "$RUNS"/quality-*.md "$OUT/" 2> /dev/null
  tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='*.ply' --exclude='*.bin' --exclude='tb' --exclude='renders' \
    --exclude="$(basename "$RUNS")/ladder" -C "$(dirname "$RUNS")" "$(basename "$RUNS")" 2> /dev/null
  finish 0
}

# ------------------------------------------------------------------------------------------------------ train
mode_train() {
  JOBS=${JOBS:-1} STEPS=${STEPS:-} SCENE=${SCENE:-fox-dark} SEED=${SEED:-0} GPUS=${GPUS:-1}
  parse "jobs steps scene seed gpus" "$@"
  local specs=("${ARGS[@]}"); [ ${#specs[@]} -gt 0 ] || specs=(default)
  setup; need_train_wheels; stage_data
  local extra=("${SETS[@]}"); [ -n "$STEPS" ] && extra+=(--set "steps=$STEPS")
  local spec name cfg scene seed args i=0
  mkdir -p /tmp/train
  for spec in "${specs[@]}"; do
    i=$((i + 1))
    IFS=: read -r name cfg scene seed <<< "$spec"
    scene=${scene:-$SCENE}; seed=${seed:-$SEED}; need_photos "$scene"
    args=(); [ -n "$cfg" ] && args+=(--config "$cfg")
    while [ "$(jobs -rp | wc -l)" -ge "$JOBS" ]; do wait -n; done
    rm -rf "/tmp/train/$name"
    (
      t=$SECONDS
      CUDA_VISIBLE_DEVICES=$(( (i - 1) % GPUS )) python3 -m retinexgs train --data "/tmp/data/$scene" \
        --out "/tmp/train/$name" --device cuda --quiet \
        "${args[@]}" --set "seed=$seed" "${extra[@]}" > "/tmp/train/$name.log" 2>&1
      echo "== $name (${cfg:-default}, $scene, seed $seed): exit $? in $(( SECONDS - t )) s wall"
      metrics "   $name" "/tmp/train/$name"
    ) | tee -a "$OUT/train.txt" &
  done
  wait
  tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='tb' --exclude='renders' -C /tmp train 2> /dev/null
  finish 0
}

# ------------------------------------------------------------------------------------------------------ speed
mode_speed() {
  SCENE=${SCENE:-fox-dark} SEEDS=${SEEDS:-0} CONFIG=${CONFIG:-} RUN=${RUN:-} VS=${VS:-} FPS_RUNS=${FPS_RUNS:-1}
  RASTER_RUNS=${RASTER_RUNS:-1} OLD=${OLD:-} REPEATS=${REPEATS:-2}
  parse "scene seeds config run vs fps-runs raster-runs old repeats" "$@"
  [ ${#PASS[@]} -eq 0 ] || die "speed takes no arguments after --"
  local stages=" ${ARGS[*]:-train fps trainspeed raster profile} "
  has() { [[ $stages == *" $1 "* ]]; }
  for s in $stages; do
    [[ " train fps trainspeed stream raster profile fprofile rprofile lr3m bigphoto export ab " == *" $s "* ]] \
      || die "unknown speed stage $s"
  done
  setup
  if [ "$VS" = gsplat ]; then  # JIT-build gsplat's kernels now: nothing is timed before the wait below
    (python3 -c "
import torch, gsplat
n = 64; d = 'cuda'
gsplat.rasterization(torch.randn(n, 3, device=d), torch.randn(n, 4, device=d), torch.rand(n, 3, device=d) * .1,
    torch.rand(n, device=d), torch.rand(n, 3, device=d), torch.eye(4, device=d)[None],
    torch.tensor([[[50., 0, 32], [0, 50., 32], [0, 0, 1]]], device=d), 64, 64)
print('gsplat ready')" > "$LOGS/gsplat_build.log" 2>&1; echo "gsplat JIT: exit $? at $(elapsed) s") &
  fi
  local cfg=(); [ -n "$CONFIG" ] && cfg=(--config "$CONFIG")
  local scene=/tmp/data/$SCENE slug=${SCENE//\//-} t s
  read -r -a seeds <<< "$SEEDS"
  local run=${RUN:-/tmp/speed/$slug/seed${seeds[0]}} train=0
  # A trained run for fps / fprofile / export: --run, else the train stage's first seed (trained if missing).
  if [ -n "$RUN" ]; then
    [ -f "$RUN/config.yaml" ] || die "--run $RUN: no trained run there"
  elif has fps || has fprofile || has export; then
    [ -f "$run/metrics.json" ] || train=1
  fi
  has train && train=1
  if [ $train = 1 ] || has trainspeed || has stream || has profile || has lr3m || has bigphoto || has ab; then
    need_train_wheels; stage_data; need_photos "$SCENE"
  fi
  wait  # gsplat's build, before anything is timed
  if [ $train = 1 ]; then
    t=$SECONDS
    python3 -m retinexgs train --data "$scene" --out "/tmp/speed/$slug/seed${seeds[0]}" --device cuda --quiet \
      "${cfg[@]}" --set "seed=${seeds[0]}" "${SETS[@]}" > "$LOGS/train${seeds[0]}.log" 2>&1
    echo "train $SCENE seed ${seeds[0]} alone: exit $? in $(( SECONDS - t )) s wall" | tee -a "$OUT/train.txt"
    t=$SECONDS
    for s in "${seeds[@]:1}"; do
      python3 -m retinexgs train --data "$scene" --out "/tmp/speed/$slug/seed$s" --device cuda --quiet \
        "${cfg[@]}" --set "seed=$s" "${SETS[@]}" > "$LOGS/train$s.log" 2>&1 &
    done
    wait
    [ ${#seeds[@]} -gt 1 ] && echo "seeds ${seeds[*]:1} side by side: $(( SECONDS - t )) s wall" | tee -a "$OUT/train.txt"
    for s in "${seeds[@]}"; do metrics "seed $s" "/tmp/speed/$slug/seed$s" | tee -a "$OUT/train.txt"; done
  fi
  if has fps && [ -f "$run/config.yaml" ]; then
    for _ in $(seq "$FPS_RUNS"); do fps_bench "$run" "$OUT/fps.txt"; done  # frames move run to run
  fi
  if has trainspeed; then
    timeout 150 python3 -m retinexgs.bench train-speed --device cuda ${VS:+--vs "$VS"} 2>&1 | tee "$OUT/trainspeed.txt"
    timeout 100 python3 -m retinexgs.bench train-speed --device cuda --data "$scene" "${cfg[@]}" --warmup 3100 \
      --steps 30 2>&1 | tee -a "$OUT/trainspeed.txt"
  fi
  if has stream; then  # streamed vs preloaded views, alternated --repeats times on this card (issue 34's ≤ 1.05×)
    for _ in $(seq "$REPEATS"); do
      for mode in never always always:0; do  # always:0 = streamed through the staging thread (views_pinned_gb=0)
        echo "== train.stream_views=$mode" >> "$OUT/stream.txt"
        local pin=()
        [ "${mode#*:}" = 0 ] && pin=(--set train.views_pinned_gb=0)
        timeout 120 python3 -m retinexgs.bench train-speed --device cuda --data "$scene" "${cfg[@]}" --warmup 3100 \
          --steps 200 --set "train.stream_views=${mode%%:*}" "${pin[@]}" 2>&1 | tee -a "$OUT/stream.txt"
      done
    done
  fi
  if has raster; then  # ratios move run to run: --raster-runs 2 repeats the bench in the same call
    for _ in $(seq "$RASTER_RUNS"); do
      timeout 150 python3 -m retinexgs.bench raster --device cuda --vs "${VS:-reference}" 2>&1 | tee -a "$OUT/raster.txt"
    done
  fi
  if has profile; then
    timeout 150 python3 scripts/profiling.py train "$scene" --steps "${PROFILE_WARMUP:-300}" --profile 30 "${cfg[@]}" > "$OUT/profile.txt" 2>&1
    grep -v -i warn "$OUT/profile.txt" | head -4
  fi
  if has fprofile; then
    timeout 100 python3 scripts/profiling.py frame "$run" --fused > "$OUT/fprofile.txt" 2>&1; head -1 "$OUT/fprofile.txt"
  fi
  if has rprofile; then
    timeout 200 python3 scripts/profiling.py raster > "$OUT/rprofile.txt" 2>&1; grep "==" "$OUT/rprofile.txt"
  fi
  if has lr3m; then
    local img; img=$(find "$scene/low" -maxdepth 1 -type f | sort | head -1)
    timeout 200 python3 scripts/profiling.py lr3m "$img" 2>&1 | tee "$OUT/lr3m.txt"
  fi
  if has bigphoto; then
    local param
    for param in tile_memory_share=0 tile_pixels=1000000000 tile_memory_share=0.5; do  # tiles, whole, the default
      echo "== $param" >> "$OUT/bigphoto.txt"
      timeout 300 python3 -m retinexgs.bench lr3m --data "$scene" --device cuda --methods lr3m --limit 1 \
        --resize 3000x4000 --no-metrics --param "$param" 2>&1 | tee -a "$OUT/bigphoto.txt" | grep "lr3m "
    done
  fi
  if has export; then
    t=$SECONDS
    python3 -m retinexgs export --run "$run" --out /tmp/speed/export.ply --device cuda --quiet 2>&1 | tail -2
    python3 -m retinexgs render --run "$run" --views test --maps enhanced,R,L --device cuda --out /tmp/speed/render \
      --quiet 2>&1 | tail -1
    echo "export + render: $(( SECONDS - t )) s" | tee "$OUT/export.txt"
  fi
  if has ab; then
    [ -n "$OLD" ] && [ -d "$OLD" ] || die "speed ab needs --old DIR (a carried copy of the other commit's files)"
    local old new=$PWD i side dir
    old=$(cd "$OLD" && pwd)
    t=$SECONDS
    # The LPIPS weights (9 MB) need not travel twice: the old copy reads the new one's where it has none.
    [ -d "$old/retinexgs/evaluate/weights" ] || cp -r retinexgs/evaluate/weights "$old/retinexgs/evaluate/"
    local gz reused=0 ostamp; ostamp=$(cd "$old" && build_stamp)
    if [ -f "$old/.cbuild/stamp" ] && [ "$(cat "$old/.cbuild/stamp")" = "$ostamp" ]; then  # its own build, carried
      for gz in "$old"/.cbuild/_C*.so.gz; do gunzip -c "$gz" > "$old/retinexgs/$(basename "${gz%.gz}")"; done
      reused=1
    elif [ "$ostamp" = "$(build_stamp)" ]; then  # the same kernel sources as the new side: its build
      cp retinexgs/_C*.so "$old/retinexgs/"; reused=1
    fi
    if [ $reused = 0 ]; then
      (cd "$old" && python3 setup.py build_ext --inplace > "$LOGS/build_old.log" 2>&1) || die "the --old build failed"
    fi
    echo "old build: $(( SECONDS - t )) s$([ $reused = 1 ] && echo ' (reused)')"
    for i in $(seq "$REPEATS"); do
      for side in old new; do
        dir=$old; [ $side = new ] && dir=$new
        rm -rf "/tmp/ab/$side-$i"
        (cd "$dir" && PYTHONPATH="$dir${SITE:+:$SITE}" python3 -m retinexgs train --data "$scene" "${cfg[@]}" \
          --set seed=0 "${SETS[@]}" --out "/tmp/ab/$side-$i" --device cuda --quiet > "$LOGS/ab-$side-$i.log" 2>&1)
        metrics "$side-$i" "/tmp/ab/$side-$i" | tee -a "$OUT/ab.txt"
        # a run that failed says why in its log's last line; the others would fail alike (missing photos, a wheel)
        [ -f "/tmp/ab/$side-$i/metrics.json" ] || die "speed ab: the $side run failed: $(tail -1 "$LOGS/ab-$side-$i.log")"
      done
    done
    # Each side's median training time and their ratio (the spread of one card is the figure to beat).
    python3 - "$OUT/ab.txt" << 'EOF2' | tee -a "$OUT/ab.txt"
import re, statistics, sys
t = {"old": [], "new": []}
for line in open(sys.argv[1]):
    m = re.match(r"(old|new)-\d+: train ([\d.]+) s", line)
    if m:
        t[m[1]].append(float(m[2]))
if t["old"] and t["new"]:
    o, n = statistics.median(t["old"]), statistics.median(t["new"])
    print(f"median: old {o:.1f} s ({min(t['old']):.1f}-{max(t['old']):.1f}, n={len(t['old'])}), "
          f"new {n:.1f} s ({min(t['new']):.1f}-{max(t['new']):.1f}, n={len(t['new'])}), new/old {n / o:.3f}")
EOF2
  fi
  finish 0
}

# ------------------------------------------------------------------------------------------------------ tests
mode_tests() {
  TEST_LIMIT=${TEST_LIMIT:-200} FUZZ_CASES=${FUZZ_CASES:-300} SANITIZER=${SANITIZER:-memcheck racecheck}
  TARGETS=${TARGETS:-raster frame}
  parse "test-limit fuzz-cases sanitizer targets" "$@"
  local tests=("${ARGS[@]}") rc=0 status tool target
  [ ${#tests[@]} -gt 0 ] || tests=(tests/test_cuda*.py tests/test_fused_colors.py tests/test_raster_finite_check.py)
  setup
  timeout "$TEST_LIMIT" python3 -X faulthandler -m pytest -q -p no:cacheprovider --tb=short -rfs "${tests[@]}" "${PASS[@]}" \
    > "$OUT/tests.log" 2>&1
  status=$?; [ $status -eq 0 ] || rc=1
  echo "tests: exit $status"; grep -E "^FAILED|passed|failed|launches per frame" "$OUT/tests.log" | head -30
  if [ "$FUZZ_CASES" -gt 0 ]; then  # CUDA against the CPU kernels over the fuzz corpus
    timeout 120 python3 scripts/fuzz_cuda.py --cases "$FUZZ_CASES" > "$OUT/fuzz_cuda.log" 2>&1
    status=$?; [ $status -eq 0 ] || rc=1
    echo "fuzz_cuda: exit $status, $(grep -c "^FAIL" "$OUT/fuzz_cuda.log") failing"; tail -1 "$OUT/fuzz_cuda.log" | cut -c1-400
  fi
  if [ "$SANITIZER" != none ]; then
    command -v compute-sanitizer > /dev/null || { echo "compute-sanitizer is not on this machine"; TARGETS=; rc=1; }
    for target in $TARGETS; do
      for tool in $SANITIZER; do
        echo "===== compute-sanitizer --tool $tool: scripts/sanitize.py $target" >> "$OUT/sanitizer.log"
        timeout 200 compute-sanitizer --tool "$tool" --error-exitcode 9 python3 scripts/sanitize.py "$target" \
          >> "$OUT/sanitizer.log" 2>&1
        status=$?; [ $status -eq 0 ] || rc=1
        echo "compute-sanitizer $tool $target: exit $status ($(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' \
          "$OUT/sanitizer.log" | tail -1))"
      done
    done
  fi
  finish $rc
}

# The arguments of a large-scene bench mode (scale, bigraw): every one goes to the benchmark but --limit (this
# script's); --scene NAME not an existing path is a scene under .data (staged to /tmp/data); without --out the tables
# go to DEFAULT_OUT (generated scenes stay in /tmp). Usage: bench_args DEFAULT_OUT ARG...; sets BARGS (the
# benchmark's arguments), BOUT (its --out) and BSTAGE (1: stage_data is needed).
bench_args() {
  BOUT=$1; shift
  BARGS=() BSTAGE=0
  local have_out=0 a next=
  for a in "$@"; do
    case $next in
      limit) LIMIT=$a; next=; continue ;;
      scene) [[ $a == /* ]] || [ -e "$a" ] || { a=/tmp/data/$a; BSTAGE=1; }; next= ;;
      out) BOUT=$a; next= ;;
    esac
    case $a in
      --limit) next=limit; continue ;;
      --limit=*) LIMIT=${a#*=}; continue ;;
      --scene) next=scene ;;
      --scene=*) a=${a#*=}; [[ $a == /* ]] || [ -e "$a" ] || { a=/tmp/data/$a; BSTAGE=1; }; a=--scene=$a ;;
      --out) next=out; have_out=1 ;;
      --out=*) BOUT=${a#*=}; have_out=1 ;;
    esac
    BARGS+=("$a")
  done
  [ -n "$next" ] && die "--$next needs a value"
  [ $have_out = 1 ] || BARGS+=(--out "$BOUT")
}

# The set-up of a large-scene bench mode: its arguments (bench_args; LIMIT defaults to 560 s), the environment, the
# scenes where --scene names one under .data, then the large scene of `python -m retinexgs.bench BENCH ARGS`
# generated (on the GPU) while the extension builds (it needs neither the build nor the wheels); the build and the
# training wheels are ready after it. Usage: large_scene_setup BENCH DEFAULT_OUT ARG...; sets BARGS and BOUT.
large_scene_setup() {
  local bench=$1 default_out=$2; shift 2
  LIMIT=${LIMIT:-560}
  bench_args "$default_out" "$@"
  setup_env
  [ "$BSTAGE" = 1 ] && stage_data
  timeout "$LIMIT" python3 -m retinexgs.bench "$bench" "${BARGS[@]}" --generate-only > "$LOGS/generate.log" 2>&1 &
  local gen=$!
  setup_build; need_train_wheels
  wait $gen || { tail -20 "$LOGS/generate.log"; die "the scene's generation failed (generate.log in logs.tgz)"; }
  grep -E "^scene:|views/s" "$LOGS/generate.log" | tail -2
}

# ------------------------------------------------------------------------------------------------------ scale
mode_scale() {
  if [ ! -f retinexgs/bench/scale.py ] && [ ! -f retinexgs/bench/scale/__init__.py ]; then
    echo "device.sh scale: the large-scene benchmark (retinexgs.bench.scale) is not available in this build" >&2
    exit 2
  fi
  large_scene_setup scale /tmp/scale "$@"
  local args=("${BARGS[@]}") out=$BOUT
  local left=$(( LIMIT - $(elapsed) )) rc
  [ "$left" -gt 0 ] || die "no time left under --limit $LIMIT"
  timeout "$left" python3 -m retinexgs.bench scale "${args[@]}" 2>&1 | tee "$LOGS/scale.log"
  rc=${PIPESTATUS[0]}
  [ "$rc" = 124 ] && echo "device.sh scale: cut off at --limit $LIMIT s; the tables hold the runs that finished"
  cp "$out/scale.md" "$out/scale.json" "$OUT/" 2> /dev/null
  tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='tb' --exclude='renders' -C "$out" . 2> /dev/null
  finish "$rc"
}

# ----------------------------------------------------------------------------------------------------- bigraw
mode_bigraw() {
  [ -f retinexgs/bench/bigraw.py ] || { echo "device.sh bigraw: retinexgs.bench.bigraw is not in this build" >&2; exit 2; }
  large_scene_setup bigraw /tmp/bigraw "$@"
  local args=("${BARGS[@]}") out=$BOUT
  # The benchmark's own --limit stops a training cleanly (SIGINT, 30 s grace) 40 s before this script's: the
  # tables and the copy below still get done; timeout is the backstop.
  local left=$(( LIMIT - $(elapsed) )) rc
  [ "$left" -gt 60 ] || die "no time left under --limit $LIMIT"
  timeout "$left" python3 -m retinexgs.bench bigraw "${args[@]}" --limit $(( left - 40 )) 2>&1 | tee "$LOGS/bigraw.log"
  rc=${PIPESTATUS[0]}
  [ "$rc" = 124 ] && echo "device.sh bigraw: killed at --limit $LIMIT s; the tables hold the rows that finished"
  cp "$out/bigraw.md" "$out/bigraw.json" "$OUT/" 2> /dev/null
  cp "$out/darken.log" "$LOGS/" 2> /dev/null
  tar czf "$OUT/runs.tgz" --exclude='*.pt' --exclude='renders' --exclude='caches' --exclude='dark' -C "$out" . 2> /dev/null
  finish "$rc"
}

# ---------------------------------------------------------------------------------------------------- compile
mode_compile() {
  command -v nvcc > /dev/null || die "nvcc not found"
  shopt -s nullglob
  local srcs=(csrc/cuda/*.cu) f out
  if [ ${#srcs[@]} -eq 0 ]; then echo "no CUDA sources"; exit 0; fi
  out=$(mktemp -d)
  for f in "${srcs[@]}"; do
    nvcc -std=c++20 -O3 -Icsrc/include -gencode arch=compute_89,code=sm_89 -gencode arch=compute_90,code=sm_90 \
      -Xcompiler -Wall -c "$f" -o "$out/$(basename "${f%.cu}").o" || { rm -rf "$out"; exit 1; }
    echo "nvcc ok: $f (sm_89, sm_90)"
  done
  rm -rf "$out"
}

MODE=${1:-help}; shift || true
case $MODE in
  quality | train | speed | tests | scale | bigraw | compile | bench) "mode_$MODE" "$@" ;;
  build) parse "" "$@"; setup; finish 0 ;;
  help | -h | --help) usage ;;
  *) usage >&2; echo >&2; die "unknown mode $MODE" ;;
esac
