#!/usr/bin/env bash
# Set up everything dm2 needs on a fresh machine: system library, virtual environment, package.
# Idempotent; re-running is cheap.
set -euo pipefail
cd "$(dirname "$0")/.."

# Usage: bash scripts/bootstrap.sh [--tests]
#   --tests also installs what only the test suite needs: Debian's chromium (the report and
#   3D-view tests render pages in headless Chromium).

apt_install() {  # apt_install PACKAGE WHY
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "installing Debian package $1 ($2)" >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq >/dev/null && apt-get install -y -qq "$1" >/dev/null
        apt-get clean  # the downloaded packages are not needed once installed
    else
        echo "error: $2: the Debian package $1 is missing." >&2
        echo "       install it first:  sudo apt-get install $1" >&2
        exit 1
    fi
}

# Open3D links against libusb-1.0 (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    apt_install libusb-1.0-0 "needed by Open3D"
fi
if [ "${1:-}" = "--tests" ] && ! command -v chromium >/dev/null 2>&1; then
    apt_install chromium "the browser tests render the report and the 3D view"
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
stamp=.venv/.dm2-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    # no download cache: the wheels (Open3D alone is several hundred MB) would be kept twice;
    # and pip unpacks them beside the environment, not in a /tmp that may be a small tmpfs
    pip_tmp=.venv/.pip-tmp
    mkdir -p "$pip_tmp"
    # pip's and setuptools' own chatter (build warnings) goes to a log, shown only on failure
    pip_log="$pip_tmp/install.log"
    if ! { TMPDIR="$PWD/$pip_tmp" .venv/bin/python -m pip install -q --no-cache-dir --upgrade pip \
            && TMPDIR="$PWD/$pip_tmp" .venv/bin/python -m pip install -q --no-cache-dir -e ".[dev]"
         } >"$pip_log" 2>&1; then
        cat "$pip_log" >&2
        echo "error: installing the package failed (pip's output above)" >&2
        exit 1
    fi
    rm -rf "$pip_tmp"
    touch "$stamp"
fi

# Compile the numba kernels once now: they are cached beside their sources (__pycache__/), so
# the first `dm2 run` does not spend one to two minutes compiling them. The default scenario,
# run once into a scratch folder, compiles every kernel a run uses; again only when a source
# file changed since.
compiled=.venv/.dm2-kernels-compiled
if [ ! -f "$compiled" ] || [ -n "$(find dm2 twin calib -name '*.py' -newer "$compiled" -print -quit)" ]; then
    echo "compiling the numba kernels once (the default scenario, 1-2 min) ..." >&2
    scratch=$(mktemp -d "${TMPDIR:-/tmp}/dm2-compile.XXXXXX")
    if ! .venv/bin/python -m dm2.cli.main run --no-record --out "$scratch/run" \
            >"$scratch/log" 2>&1; then
        cat "$scratch/log" >&2
        echo "error: the default scenario failed (its output above; kept in $scratch)" >&2
        exit 1
    fi
    rm -rf "$scratch"
    touch "$compiled"
fi
