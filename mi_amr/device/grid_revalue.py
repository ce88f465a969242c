"""New values of the same cells in a built macrocell grid, in place
(docs/design.md section 13): the grid's value ranges from two
scatter-reductions over its incidence pairs (`MacrocellGrid.incidence`),
its value masks (``nearest``: a cell's own bin, over the new values' range
as a build makes them) from two more. Milliseconds, no build; the
majorants are recomputed afterwards by the caller, as after a TF change.

`GridRevaluer` is the grid component's own update on new values
(`mi_amr.building.components`); it keeps the incidence pairs, made on its
first call, for the next ones.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..memory import MemoryLimitError
from ..reconstruction import Reconstruction
from ..structures.value_masks import N_BINS, ValueBins
from .grid import DeviceTwoLevelGrid

#: At most this many (cell, macrocell) pairs per cell are kept (a cell's
#: support overlaps 1-8 macrocells where macrocells are at least as wide as
#: the cells); beyond, new values rebuild the grid.
REVALUE_PAIRS_PER_CELL = 64

_FILL = {"vmin": float("inf"), "vmax": -float("inf"), "mask_lo": 0, "mask_hi": 0}


class GridRevaluer:
    """Puts new values of the same cells into one built macrocell grid
    (`DeviceMacrocellGrid` or the fine level of a `DeviceTwoLevelGrid`)."""

    def __init__(self, grid, method: Reconstruction, memory_limit: float | None):
        self.grid, self.method, self.memory_limit = grid, method, memory_limit
        self._pairs = None                   # (slots, macrocells, block order); False: too many

    def __call__(self, old_volume, volume, values: mi.Float) -> bool:
        """New ranges (and masks) from ``values``, the device array of
        ``volume`` (`BlockVolume.with_values` of ``old_volume``). False,
        with nothing changed, where the grid cannot take them in place
        (too many incidence pairs; masks of a method whose masks are not a
        cell's own bin): the caller rebuilds."""
        grid = self.grid
        two_level = isinstance(grid, DeviceTwoLevelGrid)
        fine = grid.fine if two_level else grid
        host = fine.host
        if self._pairs is False or (fine.has_masks and self.method.name != "nearest"):
            return False
        if self._pairs is None:
            try:
                pairs = host.incidence(old_volume, self.method,
                                       REVALUE_PAIRS_PER_CELL * max(len(old_volume), 1), self.memory_limit)
            except MemoryLimitError:          # the rebuild checks its own peak
                pairs = None
            if pairs is None:
                self._pairs = False
                return False
            order = mi.Int32(grid.blocked(np.arange(host.vmin.size, dtype=np.int32), -1)) if two_level else None
            self._pairs = (mi.UInt32(pairs[0]), mi.UInt32(pairs[1]), order)
        slots, macrocells, order = self._pairs
        v = dr.gather(mi.Float, dr.detach(values), slots)
        n = host.vmin.size
        reduced = {"vmin": (dr.ReduceOp.Min, dr.full(mi.Float, float("inf"), n), v),
                   "vmax": (dr.ReduceOp.Max, dr.full(mi.Float, -float("inf"), n), v)}
        if fine.has_masks:                # nearest: each cell sets its value's bin, the bins
            bins = ValueBins.of(volume)   # over the new values' range (as a build makes them)
            b = mi.UInt32(dr.clip(dr.floor((mi.Float64(v) - bins.lo) / bins.width), 0, N_BINS - 1))
            one = mi.UInt32(1)
            reduced["mask_lo"] = (dr.ReduceOp.Or, dr.zeros(mi.UInt32, n), dr.select(b < 32, one << (b & 31), 0))
            reduced["mask_hi"] = (dr.ReduceOp.Or, dr.zeros(mi.UInt32, n), dr.select(b >= 32, one << (b & 31), 0))
        for name, (op, target, value) in reduced.items():
            dr.scatter_reduce(op, target, value, macrocells)
        dr.eval(*[t for _, t, _ in reduced.values()])
        host.vmin, host.vmax = reduced["vmin"][1].numpy(), reduced["vmax"][1].numpy()
        if fine.has_masks:
            host.masks = (reduced["mask_hi"][1].numpy().astype(np.uint64) << np.uint64(32)) \
                | reduced["mask_lo"][1].numpy().astype(np.uint64)
            host.bins = bins
            fine.bin_lo, fine.bin_hi = (mi.Float(e) for e in bins.edges())
            dr.make_opaque(fine.bin_lo, fine.bin_hi)
        for name, (_, target, _) in reduced.items():
            if two_level:                 # the device keeps the fine level in block order
                target = dr.select(order < 0, _FILL[name],
                                   dr.gather(type(target), target, mi.UInt32(dr.maximum(order, 0))))
            setattr(fine, name, target)
            dr.make_opaque(getattr(fine, name))
        return True
