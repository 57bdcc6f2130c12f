#!/usr/bin/env bash
# One-step set-up of saft on Debian (run as root, or with sudo for the apt step).
#   bash install.sh          install saft and its runtime dependencies (Ray for `saft batch` included)
#   bash install.sh --dev    ... plus the test tools
# On a machine without an NVIDIA GPU torch is installed as the CPU build (torch==2.13.0) BEFORE saft,
# so that no multi-GB CUDA packages are ever downloaded there.
set -euo pipefail
cd "$(dirname "$0")"
dev=""
[ "${1:-}" = "--dev" ] && dev="yes"
extras="batch${dev:+,dev,bench}"    # batch: Ray, for `saft batch`; bench: Newton, for the tests of the independent scenes

# System packages: Mitsuba's CPU backend (appearance phase) needs LLVM >= 19; the tests use headless
# Chromium (HTML report) and the Khronos glTF validator (npm).
apt_packages=""
ldconfig -p 2>/dev/null | grep -q 'libLLVM\(-\|\.so\.\)19' || apt_packages="libllvm19"
if [ -n "$dev" ] && ! command -v chromium >/dev/null 2>&1; then apt_packages="$apt_packages chromium"; fi
if [ -n "$apt_packages" ] && command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq $apt_packages >/dev/null; } \
        || echo "saft install: could not install $apt_packages (appearance on CPU / browser test unavailable)" >&2
fi
if [ -n "$dev" ] && command -v npm >/dev/null 2>&1 && [ ! -d "$(npm root -g 2>/dev/null)/gltf-validator" ]; then
    npm install -g --silent gltf-validator >/dev/null 2>&1 \
        || echo "saft install: gltf-validator not installed; the glTF validator test will be skipped" >&2
fi

PIP="python3 -m pip"
gpu=""
command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1 && gpu="yes"
[ -n "$gpu" ] && extras="${extras:+$extras,}cuda"          # cuda: nvdiffrast (diffrp-nvdiffrast)
if ! python3 -c "import torch" 2>/dev/null; then
    if [ -n "$gpu" ]; then
        $PIP install -q "torch>=2.2"
    else
        # CPU build. Elsewhere than here, set PIP_INDEX_URL to PyTorch's CPU wheel index for this step.
        $PIP install -q "torch==2.13.0"
    fi
fi
$PIP install -q -e ".${extras:+[$extras]}"
if [ -n "$gpu" ]; then
    # nvdiffrast compiles its CUDA plugin on first use (about 30 s): do it now, and say whether it works.
    python3 -c "from saft.render.nvdiffrast_backend import nvdiffrast_status as s; ok, why = s(); \
print('saft install: nvdiffrast ' + ('works' if ok else 'does not work here (' + why + '); saft renders with PyTorch'))" \
        || echo "saft install: could not check nvdiffrast" >&2
fi
