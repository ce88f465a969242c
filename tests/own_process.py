"""Run a test that switches Mitsuba variants in a process of its own.

The suite's process stays in the rgb variant its fixtures assume: a
variant switch re-registers every plugin and reloads Mitsuba's Python
integrators, and a test that fails half-way would leave the next tests in
spectral or mono. A fresh Python starts in about 0.6 s and reads the
kernels from the same disk cache.
"""

from __future__ import annotations

import contextlib
import functools
import os
import subprocess
import sys
from pathlib import Path

import mitsuba as mi

TESTS = Path(__file__).resolve().parent
#: The variant the child starts in (conftest's ``llvm`` fixture's).
RGB = os.environ.get("MI_AMR_VARIANT") or "llvm_ad_rgb"
#: The backend's prefix of the other variants (``cuda_ad_`` where the suite runs on CUDA).
PREFIX = "cuda_ad_" if RGB.startswith("cuda") else "llvm_ad_"


@contextlib.contextmanager
def in_variant(kind: str):
    """``kind`` (``spectral``, ``mono`` or a full name) for the block, then the rgb variant again."""
    mi.set_variant(kind if "_" in kind else PREFIX + kind)
    try:
        yield
    finally:
        mi.set_variant(RGB)


def in_own_process(test):
    """Decorator: the test body runs in a fresh Python with the same
    arguments (plain values: pytest parameters, no fixtures); its failure
    (the assertion and traceback) fails the test here."""
    @functools.wraps(test)
    def run(*args, **kwargs):
        code = (f"import sys; sys.path.insert(0, {str(TESTS)!r})\n"
                f"import mi_amr, mitsuba as mi\n"
                f"mi.set_variant({RGB!r})\n"          # as the suite's process starts its tests
                f"import {test.__module__} as m\n"
                f"m.{test.__name__}.__wrapped__(*{args!r}, **{kwargs!r})\n")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                             cwd=str(TESTS.parent), env=dict(os.environ))
        assert out.returncode == 0, f"{test.__name__} in its own process:\n{out.stderr[-4000:]}"
    return run
