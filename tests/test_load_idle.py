"""Loading a medium leaves the process idle.

A BLAS call on a long vector (numpy's ``dot``, ``@``) wakes OpenBLAS's
worker threads, which then spin on a core for about 0.1 s: on two cores the
first frames after a load ran at half speed, and every benchmark pass that
timed a frame just after loading its scene measured that
(docs/performance/frame-cost.md section 3; ``python -m mi_amr.bench``
waits for an idle process before each timed frame, ``harness.wait_idle``).

The check counts, not times: BLAS's worker threads are the threads of this
process that run for a BLAS call of a long vector and for nothing else
(Linux's per-thread run time, ``/proc/self/task/TID/schedstat``, in
nanoseconds); a load that makes no such call leaves their run time as it
was, however loaded the machine. The check itself is shown to see a BLAS
call made where the load would be.
"""

import os
import threading
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import mi_amr

from conftest import random_amr, wait_until

#: A vector this long makes OpenBLAS hand a dot product to its worker threads.
BLAS_LENGTH = 1 << 18


def run_times() -> dict[int, int]:
    """Nanoseconds each thread of this process has run (Linux's schedstat)."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            out[int(tid)] = int(Path(f"/proc/self/task/{tid}/schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):     # a thread that ended meanwhile
            pass
    return out


def quiet(threads, poll: float = 0.05) -> dict[int, int]:
    """Wait until none of ``threads`` runs for ``poll`` seconds (a spin
    after a BLAS call ends by itself); their run times then."""
    last = {}

    def still():
        nonlocal last
        now = {t: v for t, v in run_times().items() if t in threads}
        done = now == last
        last = now
        return done
    wait_until(still, "quiet BLAS threads", poll=poll)
    return last


def blas_call():
    x = np.ones(BLAS_LENGTH)
    return float(np.dot(x, x))


def ran_during(action) -> set[int]:
    """The threads of this process, but this one, that ran during ``action()``."""
    me = threading.get_native_id()
    r0 = run_times()
    action()
    r1 = run_times()
    return {t for t, v in r1.items() if t in r0 and v > r0[t] and t != me}


@pytest.fixture(scope="module")
def blas_threads():
    """The threads that run for a BLAS call of a long vector and not while
    the process rests (a thread polling on a timer runs in both):
    OpenBLAS's workers. Empty on a machine where BLAS keeps to the caller's
    thread (one core, or OPENBLAS_NUM_THREADS=1): nothing spins there."""
    for _ in range(10):
        resting = ran_during(lambda: time.sleep(0.2))
        workers = ran_during(lambda: (blas_call(), time.sleep(0.3))) - resting
        if workers:
            quiet(workers)                            # their spin ended ...
            if not ran_during(lambda: time.sleep(0.2)) & workers:      # ... and they rest with the process
                return workers
    assert (os.cpu_count() or 1) == 1 or os.environ.get("OPENBLAS_NUM_THREADS") == "1", \
        "a BLAS call of a long vector ran on no worker thread of its own here, though the machine has several cores"
    return set()


@pytest.mark.parametrize("kw", [{}, {"grid_refinement": 2}, {"traversal": "kdtree"},
                                {"traversal": "abr", "sampling": "abr"}, {"traversal": "brick", "sampling": "brick"}])
def test01_load_leaves_no_spinning_threads(llvm, blas_threads, kw):
    """BLAS's worker threads do not run while a medium loads (built with
    each structure); a BLAS call where the load is would be seen."""
    cells = random_amr(seed=4, n=48, levels=4)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    before = quiet(blas_threads)
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 30.0,
                        "grid_resolution": 32, **kw})
    after = quiet(blas_threads)
    ran = {t: after[t] - before[t] for t in before if after.get(t, before[t]) != before[t]}
    assert not ran, (f"{kw}: BLAS's worker threads ran {ran} ns during the load: some code made a BLAS call "
                     f"of a long vector, whose workers then spin (np.dot, @)")
    del med
    if blas_threads and not kw:                       # the check's power: a BLAS call in the same place
        before = quiet(blas_threads)
        blas_call()
        after = quiet(blas_threads)
        assert any(after[t] > before[t] for t in before)
