#!/usr/bin/env bash
# Sets up .venv with the CPU build of PyTorch, then this package and its test tools
# (with --test, also Chromium for the report's browser test).
# torch is installed first and pinned, so that no CUDA build is ever pulled in.
set -euo pipefail
cd "$(dirname "$0")/.."
# apt waits up to 10 minutes for another apt or dpkg to release its lock, instead of failing at once
APT=(apt-get -o DPkg::Lock::Timeout=600)
apt_install() {
    if fuser /var/lib/dpkg/lock-frontend >/dev/null 2>&1; then
        echo "setup: another apt or dpkg is running; waiting for its lock (up to 10 minutes)..." >&2
    fi
    "${APT[@]}" update -qq && DEBIAN_FRONTEND=noninteractive "${APT[@]}" install -y -qq "$@" >/dev/null
}
# open3d links against libusb-1.0 (a Debian package, not on a fresh machine).
if ! ldconfig -p | grep -q "libusb-1.0.so.0"; then
    if [ "$(id -u)" = 0 ]; then
        apt_install libusb-1.0-0
    else
        echo "open3d needs libusb-1.0: run 'sudo apt-get install libusb-1.0-0'" >&2
        exit 1
    fi
fi
# --test: the report's browser test renders it in headless Chromium (a Debian package); it skips without one.
if [ "${1:-}" = "--test" ] && ! command -v chromium >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then
        apt_install chromium \
            || echo "chromium could not be installed: the report's browser test will skip" >&2
    else
        echo "note: 'sudo apt-get install chromium' lets the report's browser test run (it skips otherwise)" >&2
    fi
fi
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
