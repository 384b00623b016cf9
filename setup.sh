#!/usr/bin/env bash
# Set up triplet_cl on this machine: an OpenCL runtime (Debian's PoCL when no platform exists),
# a virtual environment in .venv and the package installed into it (editable).
#   ./setup.sh          runtime dependencies
#   ./setup.sh --test   plus the test extra (pytest, hypothesis, ruff)
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
echo "setup.sh: ready (.venv/bin/triplet)"
