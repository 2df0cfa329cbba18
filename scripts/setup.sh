#!/usr/bin/env bash
# Sets up .venv with the CPU build of PyTorch, then this package and its test tools.
# torch is installed first and pinned, so that no CUDA build is ever pulled in.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
