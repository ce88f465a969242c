#!/bin/sh
# Idempotent set-up of the optional benchmark peers (`make peers`):
# .venv-eradiate with Eradiate's Mitsuba fork (eradiate-mitsuba 0.5.0, which
# pins drjit 1.2.0, so it cannot share .venv's Mitsuba 3.9 / Dr.Jit 1.5) and
# numpy. `python -m mi_amr.bench --peers eradiate` runs
# mi_amr/bench/peer_eradiate.py in it. Safe to run every time.
set -e
cd "$(dirname "$0")/.."
ERADIATE_MITSUBA_VERSION=0.5.0
VENV=.venv-eradiate
if ! tools/find-llvm19 >/dev/null; then
    echo "== libLLVM 19 is missing: run make setup first (Dr.Jit's LLVM backend needs it)" >&2
    exit 1
fi
DRJIT_LIBLLVM_PATH="$(tools/find-llvm19)"
export DRJIT_LIBLLVM_PATH
PY=${PYTHON:-python3}
if [ ! -x $VENV/bin/python ]; then
    echo "== creating $VENV"
    $PY -m venv $VENV
fi
have=$($VENV/bin/python -c "import importlib.metadata as m; print(m.version('eradiate-mitsuba'))" 2>/dev/null || true)
if [ "$have" != "$ERADIATE_MITSUBA_VERSION" ] || ! $VENV/bin/python -c "import numpy" 2>/dev/null; then
    echo "== installing eradiate-mitsuba==$ERADIATE_MITSUBA_VERSION (+ its pinned drjit) and numpy into $VENV"
    $VENV/bin/python -m pip install -q --upgrade pip >/dev/null
    $VENV/bin/python -m pip install -q "eradiate-mitsuba==$ERADIATE_MITSUBA_VERSION" numpy
fi
# a check that the fork's LLVM variant loads with this libLLVM
$VENV/bin/python -c "import importlib.metadata as m, mitsuba as mi, drjit as dr; mi.set_variant('llvm_ad_rgb'); \
print('$VENV: eradiate-mitsuba', m.version('eradiate-mitsuba'), '(Mitsuba', mi.__version__ + '), drjit', dr.__version__, '- llvm_ad_rgb loads')"
