"""Progress bars (tqdm) for loading and building: shown on a terminal once a
step has run for a second, silent otherwise (and in tests). Listeners
(`listen`) hear every bar's progress too, terminal or not: the viewer shows
a load's progress in its page with them."""

from __future__ import annotations

import threading

from tqdm import tqdm

_listeners: list = []
_lock = threading.Lock()


def listen(callback):
    """Call ``callback(desc, done, total or None)`` on every step of every
    bar (from the thread that makes progress), and with ``done = None`` when
    a bar closes. Returns a function that stops it."""
    with _lock:
        _listeners.append(callback)

    def stop():
        with _lock:
            if callback in _listeners:
                _listeners.remove(callback)
    return stop


def _told(bar, desc: str):
    """``bar`` with its ``update`` and ``close`` also telling the listeners
    (a disabled tqdm counts nothing, so the count is kept here)."""
    done = [0]
    update, close = bar.update, bar.close

    def told_update(n=1):
        done[0] += n
        for fn in list(_listeners):
            fn(desc, done[0], bar.total)
        return update(n)

    def told_close():
        if done[0] >= 0:
            for fn in list(_listeners):
                fn(desc, None, bar.total)
            done[0] = -1
        return close()
    bar.update, bar.close = told_update, told_close
    return bar


def progress(total=None, desc: str = "", unit: str = "cell"):
    """A tqdm bar over ``total`` units that appears after one second, on
    terminals only, and leaves no line behind."""
    bar = tqdm(total=total, desc=desc, unit=unit, unit_scale=True, delay=1.0, leave=False,
               disable=None, dynamic_ncols=True)
    return _told(bar, desc)
