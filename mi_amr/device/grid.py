"""The macrocell grid in Dr.Jit: value ranges, level masks and majorants.

Macrocell ``(i, j, k)`` of an ``(rx, ry, rz)`` grid spans
``[i/rx, (i+1)/rx] x ...`` of the medium's local unit cube.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .structs import jit_struct


@jit_struct(res="Vector3i", vmin="Float", vmax="Float", level_bits="UInt32", majorant="Float",
            mask_lo="UInt32", mask_hi="UInt32", bin_lo="Float", bin_hi="Float")
class DeviceMacrocellGrid:
    """A `MacrocellGrid` in Dr.Jit: ranges, level masks, value masks (when
    the grid has them: ``mask_lo``/``mask_hi`` the low and high 32 bits, and
    the value bins' edges) and majorants."""

    def __init__(self, grid):
        self.host = grid
        self.res = mi.Vector3i(*[int(r) for r in grid.res])
        self.vmin = mi.Float(grid.vmin)
        self.vmax = mi.Float(grid.vmax)
        self.level_bits = mi.UInt32(grid.level_bits)
        self.majorant = dr.zeros(mi.Float, grid.vmin.size)
        self.has_masks = grid.masks is not None
        if self.has_masks:
            self.mask_lo = mi.UInt32((grid.masks & np.uint64(0xFFFFFFFF)).astype(np.uint32))
            self.mask_hi = mi.UInt32((grid.masks >> np.uint64(32)).astype(np.uint32))
            lo, hi = grid.bins.edges()
            self.bin_lo, self.bin_hi = mi.Float(lo), mi.Float(hi)
        else:
            self.mask_lo = self.mask_hi = dr.zeros(mi.UInt32, 1)
            self.bin_lo = self.bin_hi = dr.zeros(mi.Float, 1)
        dr.make_opaque(self.res, self.vmin, self.vmax, self.level_bits, self.mask_lo, self.mask_hi,
                       self.bin_lo, self.bin_hi)

    @property
    def size(self) -> int:
        return self.host.vmin.size

    def update_majorants(self, tf, density_scale):
        """Per-macrocell majorant ``density_scale * max alpha`` over the
        table entries covering the macrocell's value range and, with value
        masks, over the bins of its mask (the smaller of the two)."""
        alpha = tf.range_max_alpha(self.vmin, self.vmax)
        if self.has_masks:
            alpha = dr.minimum(alpha, self._mask_max_alpha(tf))
        self.majorant = density_scale * alpha
        dr.make_opaque(self.majorant)

    def _mask_max_alpha(self, tf):
        """Max alpha over the set bins of each value mask: per-bin maxima (64
        range look-ups), then one 256-entry table per mask byte (8 x 256
        entries), then one table look-up per byte of each mask."""
        bin_alpha = tf.range_max_alpha(self.bin_lo, self.bin_hi)
        dr.eval(bin_alpha)
        idx = dr.arange(mi.UInt32, 8 * 256)
        byte, j = idx & 255, idx >> 8
        table = mi.Float(0.0)
        for i in range(8):
            a = dr.gather(mi.Float, bin_alpha, 8 * j + i)
            table = dr.select(((byte >> i) & 1) != 0, dr.maximum(table, a), table)
        dr.eval(table)
        m = mi.Float(0.0)
        for j in range(8):
            word = self.mask_lo if j < 4 else self.mask_hi
            b = (word >> (8 * (j % 4))) & 255
            m = dr.maximum(m, dr.gather(mi.Float, table, 256 * j + b))
        return m

    def cell_of(self, u: mi.Vector3f) -> mi.Vector3i:
        """Macrocell containing local point ``u`` (clamped to the grid)."""
        return dr.clip(mi.Vector3i(dr.floor(u * mi.Vector3f(self.res))), 0, self.res - 1)

    def flat(self, c: mi.Vector3i) -> mi.UInt32:
        return mi.UInt32(c.x + self.res.x * (c.y + self.res.y * c.z))
