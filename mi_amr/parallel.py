"""Host work on every core: an ordered map over a stream of chunks in threads.

numpy releases the GIL in its array loops, sorts and file reads, so chunks of
a load or a build can be worked on in threads of one process (no copies, no
pickling). `ordered_map` keeps a bounded number of chunks in flight (memory
stays that of a few chunks, whatever the length of the stream) and returns
the results in the order of the stream, so that whatever depends on order
(the first duplicate cell's index in an error, a fold into shared arrays) is
as it would be in one thread.
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator


def build_threads() -> int:
    """Threads for host loads and builds: the cores this process may run on."""
    return max(1, len(os.sched_getaffinity(0)))


def ordered_map(fn: Callable, items: Iterable, threads: int | None = None, ahead: int | None = None) -> Iterator:
    """``fn(item)`` for each item of ``items``, in threads, yielded in order.
    At most ``ahead`` (default: twice the threads) items are pulled from
    ``items`` before their results are taken; ``items`` is consumed in the
    calling thread (it may read a file). With one thread, a plain loop."""
    threads = build_threads() if threads is None else max(1, int(threads))
    if threads == 1:
        for item in items:
            yield fn(item)
        return
    ahead = 2 * threads if ahead is None else max(1, int(ahead))
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending = deque()
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) >= ahead:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for f in pending:               # an error or a consumer that stopped: drop the rest
                f.cancel()
