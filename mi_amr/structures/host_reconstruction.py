"""Reconstruction on the host: vectorised numpy over a `BlockVolume`.

Used to resample dense reference grids. ``x`` in finest-level cell units;
methods as in `mi_amr.data.reconstruction` (docs/design.md section 3).
"""

from __future__ import annotations

import numpy as np

from ..data.blocks import BlockVolume
from ..data.cells import AMRCells
from ..data.reconstruction import WEIGHT_EPS, check_method


class HostReconstruction:
    """Vectorised numpy reconstruction through the blocks of the data."""

    def __init__(self, data: AMRCells | BlockVolume):
        self.volume = BlockVolume.from_cells(data) if isinstance(data, AMRCells) else data

    def __call__(self, x, method: str = "tent"):
        """``(value, found)`` at points ``x`` (M, 3), absolute finest units."""
        check_method(method)
        x = np.asarray(x, dtype=np.float64) - self.volume.origin
        levels = [int(L) for L in self.volume.levels]
        val = np.zeros(len(x))
        found = np.zeros(len(x), dtype=bool)
        if method == "nearest":
            for L in levels:                       # finest first
                q = np.floor(x / (1 << L)).astype(np.int64)
                v, hit = self.volume.lookup(L, q)
                new = hit & ~found
                val[new] = v[new]
                found |= hit
            return val, found
        sw = np.zeros(len(x))
        for L in levels:
            w = float(1 << L)
            base = np.floor(x / w - 0.5).astype(np.int64)
            for corner in range(8):
                off = np.array([(corner >> a) & 1 for a in range(3)])
                q = base + off
                phi = np.prod(np.maximum(0.0, 1.0 - np.abs(x / w - (q + 0.5))), axis=1)
                v, hit = self.volume.lookup(L, q)
                phi = np.where(hit, phi, 0.0)
                sw += phi
                val += phi * v
        found = sw > WEIGHT_EPS
        return np.where(found, val / np.maximum(sw, 1e-300), 0.0), found
