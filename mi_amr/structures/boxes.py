"""Integer boxes expanded to the grid points they cover (vectorised numpy).

Boxes are inclusive index ranges ``i0..i1`` (shape (B, 3), x y z); points are
enumerated with x fastest, matching the flat index ``x + rx (y + ry z)`` of
every grid in mi-amr.
"""

from __future__ import annotations

import numpy as np


def enumerate_boxes(i0: np.ndarray, i1: np.ndarray):
    """Every integer point of the boxes ``i0..i1`` (inclusive, (B, 3)), x
    fastest: ``(x, y, z, owner)`` with the index of the box of each point."""
    counts = i1 - i0 + 1
    total = counts.prod(axis=1)
    owner = np.repeat(np.arange(len(total)), total)
    local = np.arange(int(total.sum())) - np.repeat(np.cumsum(total) - total, total)
    cx, cy = counts[owner, 0], counts[owner, 1]
    x = i0[owner, 0] + local % cx
    y = i0[owner, 1] + (local // cx) % cy
    z = i0[owner, 2] + local // (cx * cy)
    return x, y, z, owner


def expand_boxes(i0: np.ndarray, i1: np.ndarray, res: np.ndarray):
    """Flat macrocell indices (x fastest) of every box ``i0..i1`` (inclusive),
    with the index of the box each entry came from."""
    x, y, z, owner = enumerate_boxes(i0, i1)
    return x + res[0] * (y + res[1] * z), owner
