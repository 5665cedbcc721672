#!/bin/sh
# Render the whole benchmark (4 shapes x 5 materials, 256 x 256, 16 lights) with the fast
# llvm_ad_rgb variant and print the total render time; then run the table.
#   benchmarks/pbr/all.sh [OUT_DIR] [extra render.py arguments]
set -eu
out=${1:-/work/pbr-data/256}
[ $# -gt 0 ] && shift
python=${PYTHON:-python}
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    for lib in /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 /usr/lib/x86_64-linux-gnu/libLLVM-19.so; do
        if [ -e "$lib" ]; then
            export DRJIT_LIBLLVM_PATH="$lib"
            break
        fi
    done
fi
here=$(dirname "$0")
"$python" "$here/render.py" --all --size 256 --spp 64 --out-dir "$out" "$@"
"$python" "$here/run.py" "$out"/*-256.npz --auto --check --json "$out/lambertian.json"
