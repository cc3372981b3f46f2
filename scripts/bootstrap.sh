#!/usr/bin/env bash
# Set up everything dm2 needs on a fresh machine: system library, virtual environment, package.
# Usage: bash scripts/bootstrap.sh        (idempotent; re-running is cheap)
set -euo pipefail
cd "$(dirname "$0")/.."

# Open3D links against libusb-1.0 (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "installing Debian package libusb-1.0-0 (needed by Open3D)" >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq >/dev/null && apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "error: Open3D needs the system library libusb-1.0." >&2
        echo "       install it first:  sudo apt-get install libusb-1.0-0" >&2
        exit 1
    fi
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
stamp=.venv/.dm2-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e ".[dev]"
    touch "$stamp"
fi
