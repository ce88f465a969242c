#!/bin/sh
# Idempotent set-up: libLLVM 19 for Dr.Jit's LLVM backend, Debian's chromium for
# the browser tests of mi-amr view, Debian's nodejs for the notebook page's module
# check, the .venv with mi-amr installed (editable, with test extras). Safe to run
# every time.
set -e
cd "$(dirname "$0")/.."
if ! tools/find-llvm19 >/dev/null; then
    echo "== installing libllvm19 (Dr.Jit's LLVM backend aborts with LLVM 14-16)"
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
if ! command -v chromium >/dev/null 2>&1; then
    echo "== installing chromium (the browser tests of mi-amr view drive it with Playwright)"
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
if ! command -v node >/dev/null 2>&1; then
    echo "== installing nodejs (tests/test_widget.py checks that node parses the notebook page's module)"
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq nodejs >/dev/null
fi
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "== creating .venv"
    $PY -m venv .venv
fi
if [ ! -f .venv/.installed ] || [ pyproject.toml -nt .venv/.installed ]; then
    echo "== installing mi-amr into .venv"
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null
    .venv/bin/python -m pip install -q -e '.[dev]'
    touch .venv/.installed
fi
