#!/usr/bin/env bash
# The GPU check on a lent GPU machine, from the repository's root there, with .gpu_bundle carried
# (built here by `make gpu-bundle`: benchmarks/gpu_bundle.py says what it holds):
#   1. the bundle unpacked into /tmp/gpu_bundle: the packages (site/) and the raw meshes;
#   2. the GPU tests (tests/test_gpu.py: the solver, the renderer and the plasticity's device
#      work on CUDA against the CPU), which also prove the CUDA arch was really taken;
#   3. on CUDA, the physics' roofline at the paper's particle count (benchmarks/bench_roofline.py
#      --device cuda --markdown; COMMIT names the commit in its section): docs/performance.md with
#      the section filled in comes back in $OUT;
#   4. the paper profile's frame on CUDA (benchmarks/bench_morph.py --profile paper --device cuda;
#      PROFILE, DEVICE and FRAMES change it: DEVICE=cpu PROFILE=test checks a bundle on a CPU).
# Each step's output goes to the terminal and to $OUT (the device tool's folder; else
# /tmp/gpu_check); the exit status is the first failed step's.
set -uo pipefail
cd "$(dirname "$0")/.."
BUNDLE=${GPU_BUNDLE:-.gpu_bundle}
OUT=${OUT:-/tmp/gpu_check}
FRAMES=${FRAMES:-3}
PROFILE=${PROFILE:-paper}
DEVICE=${DEVICE:-cuda}
mkdir -p "$OUT"
if [ ! -f "$BUNDLE/bundle.tar.xz" ] || [ ! -f "$BUNDLE/MANIFEST.txt" ]; then
    echo "gpu_check: $BUNDLE/bundle.tar.xz or its MANIFEST.txt is missing: run \`make gpu-bundle\` on the development machine and carry $BUNDLE" >&2
    exit 2
fi
want=$(awk '$1 == "python" {print $2}' "$BUNDLE/MANIFEST.txt")
have=$(python3 -c 'import sys; print("%d.%d" % sys.version_info[:2])')
if [ "$want" != "$have" ]; then
    echo "gpu_check: the bundle was built for Python $want, this machine's python3 is $have: rebuild it with \`make gpu-bundle PYTHON_DEVICE=$have\`" >&2
    exit 2
fi
UNPACKED=/tmp/gpu_bundle
rm -rf "$UNPACKED" && mkdir -p "$UNPACKED" && tar -xJf "$BUNDLE/bundle.tar.xz" -C "$UNPACKED" || exit 2
export PYTHONPATH=$UNPACKED/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
export PHYSMORPH_MESH_DIR=$UNPACKED/meshes
export PYTHONUNBUFFERED=1
status=0
step() {  # step NAME COMMAND...: run it, its output also into $OUT/NAME.txt; keep the first failure
    local name=$1
    shift
    echo "=== $name: $*"
    "$@" 2>&1 | tee "$OUT/$name.txt"
    local rc=${PIPESTATUS[0]}
    echo "=== $name: exit $rc"
    if [ "$status" -eq 0 ] && [ "$rc" -ne 0 ]; then status=$rc; fi
}
step device nvidia-smi
step gpu_tests python3 -m pytest -p no:cacheprovider -m gpu -n 0 -rs tests/test_gpu.py
if [ "$DEVICE" = cuda ]; then
    step roofline_cuda python3 benchmarks/bench_roofline.py --device cuda --n 471282 --res 64 --reps 2 --markdown \
        ${COMMIT:+--commit "$COMMIT"}
    cp docs/performance.md "$OUT/performance.md"
fi
step "frame_${PROFILE}_$DEVICE" python3 benchmarks/bench_morph.py --profile "$PROFILE" --frames "$FRAMES" --device "$DEVICE" \
    --mesh-dir "$PHYSMORPH_MESH_DIR" --workdir /tmp/physmorph_bench_morph
exit $status
