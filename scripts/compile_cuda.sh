#!/usr/bin/env bash
# Compile every CUDA source of csrc/cuda with nvcc for sm_89 and sm_90, without torch and without a GPU:
# the kernels only see raw pointers and csrc/include, so a syntax or type error fails here.
set -euo pipefail
cd "$(dirname "$0")/.."
shopt -s nullglob
srcs=(csrc/cuda/*.cu)
if [ ${#srcs[@]} -eq 0 ]; then echo "no CUDA sources"; exit 0; fi
out=$(mktemp -d)
for f in "${srcs[@]}"; do
  nvcc -std=c++20 -O3 -Icsrc/include -gencode arch=compute_89,code=sm_89 -gencode arch=compute_90,code=sm_90 \
       -Xcompiler -Wall -c "$f" -o "$out/$(basename "${f%.cu}").o"
  echo "nvcc ok: $f (sm_89, sm_90)"
done
rm -rf "$out"
