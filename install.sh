#!/usr/bin/env bash
# One-step set-up of saft on Debian (run as root, or with sudo for the apt step).
#   bash install.sh          install saft and its runtime dependencies
#   bash install.sh --dev    ... plus the test tools
# On a machine without an NVIDIA GPU torch is installed as the CPU build (torch==2.13.0) BEFORE saft,
# so that no multi-GB CUDA packages are ever downloaded there.
set -euo pipefail
cd "$(dirname "$0")"
extras=""
[ "${1:-}" = "--dev" ] && extras="dev"

# Mitsuba's CPU backend (appearance phase) needs a system LLVM >= 19.
if command -v apt-get >/dev/null 2>&1 && ! ldconfig -p 2>/dev/null | grep -q 'libLLVM\(-\|\.so\.\)19'; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libllvm19 >/dev/null \
        || echo "saft install: could not install libllvm19; the appearance phase will be unavailable on CPU" >&2
fi

PIP="python3 -m pip"
if ! python3 -c "import torch" 2>/dev/null; then
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
        $PIP install -q "torch>=2.2"
        extras="${extras:+$extras,}cuda"
    else
        # CPU build. Elsewhere than here, set PIP_INDEX_URL to PyTorch's CPU wheel index for this step.
        $PIP install -q "torch==2.13.0"
    fi
fi
$PIP install -q -e ".${extras:+[$extras]}"
