"""Integer boxes expanded to the grid points they cover (vectorised numpy).

Boxes are inclusive index ranges ``i0..i1`` (shape (B, 3), x y z); points are
enumerated with x fastest, matching the flat index ``x + rx (y + ry z)`` of
every grid in mi-amr.
"""

from __future__ import annotations

import numpy as np


def _runs(base: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``base[r], base[r] + 1, ..., base[r] + counts[r] - 1`` for every row
    ``r``, concatenated (no division, no modulo)."""
    start = np.cumsum(counts) - counts
    return np.repeat(base - start, counts) + np.arange(int(counts.sum()), dtype=base.dtype)


def enumerate_boxes(i0: np.ndarray, i1: np.ndarray):
    """Every integer point of the boxes ``i0..i1`` (inclusive, (B, 3)), x
    fastest: ``(x, y, z, owner)`` with the index of the box of each point.
    Built by three nested repeats: boxes into z-rows, z-rows into y-rows,
    y-rows into points."""
    i0 = np.asarray(i0, dtype=np.int64)
    counts = np.asarray(i1, dtype=np.int64) - i0 + 1
    owner = np.arange(len(i0))
    x0, y0, cx, cy = i0[:, 0], i0[:, 1], counts[:, 0], counts[:, 1]
    z = _runs(i0[:, 2], counts[:, 2])                        # z-rows
    owner, x0, y0, cx, cy = (np.repeat(a, counts[:, 2]) for a in (owner, x0, y0, cx, cy))
    y = _runs(y0, cy)                                         # y-rows
    owner, x0, cx, z = (np.repeat(a, cy) for a in (owner, x0, cx, z))
    x = _runs(x0, cx)                                         # points
    owner, y, z = (np.repeat(a, cx) for a in (owner, y, z))
    return x, y, z, owner


def expand_boxes(i0: np.ndarray, i1: np.ndarray, res: np.ndarray):
    """Flat macrocell indices (x fastest) of every box ``i0..i1`` (inclusive),
    with the index of the box each entry came from."""
    x, y, z, owner = enumerate_boxes(i0, i1)
    return x + res[0] * (y + res[1] * z), owner
