"""Loading a medium leaves the process idle.

A BLAS call on a long vector (numpy's ``dot``, ``@``) wakes OpenBLAS's
worker threads, which then spin on a core for about 0.1 s: on two cores the
first frames after a load ran at half speed, and every benchmark pass that
timed a frame just after loading its scene measured that
(docs/performance/frame-cost.md section 3). The check: the process's CPU
time while the caller sleeps right after the load stays far below that of
a BLAS call's spin.
"""

import time

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.bench.harness import process_cpu_seconds

from conftest import random_amr

SLEEP_S = 0.3
#: CPU seconds allowed while sleeping SLEEP_S after a load (a BLAS spin
#: costs about 0.1 s on two cores; an idle process about 0.02 s)
IDLE_CPU_S = 0.06


def cpu_while_sleeping() -> float:
    c0 = process_cpu_seconds()
    time.sleep(SLEEP_S)
    return process_cpu_seconds() - c0


@pytest.fixture(scope="module")
def blas_spins():
    """Whether a BLAS call leaves threads spinning here (not on one core)."""
    x = np.ones(1 << 18)
    float(np.dot(x, x))
    return cpu_while_sleeping() > IDLE_CPU_S


@pytest.mark.parametrize("kw", [{}, {"grid_refinement": 2}, {"traversal": "kdtree"},
                                {"traversal": "abr", "sampling": "abr"}, {"traversal": "brick", "sampling": "brick"}])
def test01_load_leaves_no_spinning_threads(llvm, blas_spins, kw):
    if not blas_spins:
        pytest.skip("BLAS does not spin worker threads on this machine: nothing to detect")
    cells = random_amr(seed=4, n=48, levels=4)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    cpu_while_sleeping()                       # let anything before the load settle
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 30.0,
                        "grid_resolution": 32, **kw})
    spent = cpu_while_sleeping()
    assert spent < IDLE_CPU_S, (f"{kw}: {spent:.3f} s of CPU while idle for {SLEEP_S} s after the load "
                                f"(at most {IDLE_CPU_S}): some thread keeps spinning, e.g. after a BLAS call")
    del med
