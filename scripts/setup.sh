#!/usr/bin/env bash
# Creates .venv with everything rgbd-gt needs. Safe to run again: each step checks first.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

# open3d's binary links against libusb-1.0 (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing the system package libusb-1.0-0 (needed by open3d)"
        apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 \
            || { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null; }
    else
        echo "setup: error: open3d needs the system library libusb-1.0 (Debian/Ubuntu package 'libusb-1.0-0')." >&2
        echo "setup: install it as root: apt-get install libusb-1.0-0" >&2
        exit 1
    fi
fi

# The pick page's test drives Debian's chromium (no browser is downloaded at run time); without
# it that test skips, saying why.
if ! command -v chromium >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing the system package chromium (for the pick page's browser test)"
    apt-get install -y -q chromium >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null 2>&1; } \
        || echo "setup: chromium could not be installed: the browser test will skip"
fi

if [ ! -x .venv/bin/python ]; then
    echo "setup: creating .venv"
    "$PYTHON" -m venv .venv
fi
PIP=".venv/bin/python -m pip"
$PIP install -q --upgrade pip >/dev/null
# torch first, pinned to the CPU build on this machine's disk; pyproject asks only for a
# range it satisfies, so the next step does not fetch a CUDA build.
if ! .venv/bin/python -c 'import torch' 2>/dev/null; then
    echo "setup: installing torch 2.13.0"
    $PIP install -q torch==2.13.0
fi
echo "setup: installing rgbd-gt and its dependencies"
$PIP install -q -e '.[dev]'
