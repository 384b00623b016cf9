#!/usr/bin/env bash
# Set up triplet_cl on this machine: an OpenCL runtime (Debian's PoCL when no platform exists),
# a virtual environment in .venv and the package installed into it (editable).
#   ./setup.sh          runtime dependencies
#   ./setup.sh --test   plus the test extra (pytest, hypothesis, ruff, pygltflib) and, best effort, the
#                       glTF checkers gltfpack (apt) and the Khronos glTF-Validator (npm)
set -euo pipefail
cd "$(dirname "$0")"

extra=""
[ "${1:-}" = "--test" ] && extra="[test]"
PY=${PYTHON:-python3}

if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv || {
        echo "setup.sh: could not create a virtual environment with $PY." >&2
        echo "  On Debian/Ubuntu: sudo apt-get install -y python3-venv" >&2
        exit 1
    }
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".${extra}"

have_platform() {
    .venv/bin/python - <<'PYEOF' >/dev/null 2>&1
import sys, pyopencl as cl
try:
    devs = [d for p in cl.get_platforms() for d in p.get_devices()]
except cl.Error:
    sys.exit(1)
sys.exit(0 if devs else 1)
PYEOF
}

if ! have_platform; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup.sh: no OpenCL platform found; installing Debian's PoCL (CPU OpenCL runtime)"
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd ocl-icd-libopencl1 >/dev/null
    else
        echo "setup.sh: no OpenCL platform found. Install a GPU vendor's OpenCL driver, or the CPU runtime:" >&2
        echo "    sudo apt-get install -y pocl-opencl-icd ocl-icd-libopencl1" >&2
        echo "  (not PyPI's pocl-binary-distribution: its LLVM cannot target many current CPUs)" >&2
        exit 1
    fi
    have_platform || { echo "setup.sh: PoCL was installed but OpenCL still reports no device" >&2; exit 1; }
fi
if [ -n "$extra" ]; then
    # Optional third-party checkers of the exported glTF (tests skip without them): Debian's gltfpack and the
    # Khronos glTF-Validator (npm). Best effort: no network or no node only means those tests skip.
    if ! command -v gltfpack >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        { DEBIAN_FRONTEND=noninteractive timeout 300 apt-get install -y -qq gltfpack >/dev/null 2>&1 \
          || { timeout 300 apt-get update -qq >/dev/null 2>&1 \
               && DEBIAN_FRONTEND=noninteractive timeout 300 apt-get install -y -qq gltfpack >/dev/null 2>&1; }; } \
            || echo "setup.sh: gltfpack not installed (its test will skip)"
    fi
    if command -v npm >/dev/null 2>&1 && [ ! -d "$HOME/.cache/triplet_cl/node/node_modules/gltf-validator" ]; then
        timeout 300 npm install -s --prefix "$HOME/.cache/triplet_cl/node" gltf-validator >/dev/null 2>&1 \
            || echo "setup.sh: Khronos glTF-Validator not installed (its test will skip)"
    fi
fi
echo "setup.sh: ready (.venv/bin/triplet)"
