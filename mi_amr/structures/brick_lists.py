"""Per-macrocell lists of the bricks whose extended domain overlaps it."""

from __future__ import annotations

import numpy as np

from ..memory import BYTES_PER_MACROCELL, require
from .boxes import expand_boxes
from ..reconstruction import DEFAULT_METHOD, Reconstruction
from .bricks import Bricks

#: Peak build bytes per (list cell, brick) entry: expansion and sort.
BYTES_PER_LIST_ENTRY = 120


class BrickLists:
    """Per-cell lists of the bricks whose extended domain (under the
    reconstruction ``method``: `Bricks.domains`) overlaps the cell,
    on a uniform grid of ``res`` cells over ``[lo, lo + extent]`` (finest
    units). Host arrays: ``count``, ``offset`` (per cell, x fastest) and
    ``items`` (brick ids)."""

    def __init__(self, bricks: Bricks, lo, extent, res, memory_limit: float | None = None,
                 method: Reconstruction = DEFAULT_METHOD):
        res = np.asarray(res, dtype=np.int64)
        dlo, dhi = bricks.domains(method)
        scale = res / np.asarray(extent, dtype=np.float64)
        i0 = np.clip(np.floor((dlo - lo) * scale), 0, res - 1).astype(np.int64)
        i1 = np.clip(np.floor((dhi - lo) * scale), 0, res - 1).astype(np.int64)
        entries = float((i1 - i0 + 1).prod(axis=1).sum())
        require(BYTES_PER_LIST_ENTRY * entries + BYTES_PER_MACROCELL * float(np.prod(res)),
                f"brick lists with {entries:.3g} entries", memory_limit)
        idx, owner = expand_boxes(i0, i1, res)
        order = np.argsort(idx, kind="stable")
        idx, owner = idx[order], owner[order]
        n = int(np.prod(res))
        count = np.bincount(idx, minlength=n).astype(np.uint32)
        offset = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.uint32)
        self.res = res
        self.max_list = int(count.max())
        self.count = count
        self.offset = offset
        self.items = owner.astype(np.uint32)

    @property
    def nbytes(self) -> int:
        return self.count.nbytes + self.offset.nbytes + self.items.nbytes
