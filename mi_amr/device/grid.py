"""The macrocell grid in Dr.Jit: value ranges, level masks and majorants.

Macrocell ``(i, j, k)`` of an ``(rx, ry, rz)`` grid spans
``[i/rx, (i+1)/rx] x ...`` of the medium's local unit cube.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .structs import jit_struct


@jit_struct(res="Vector3i", vmin="Float", vmax="Float", level_bits="UInt32", majorant="Float")
class DeviceMacrocellGrid:
    """A `MacrocellGrid` in Dr.Jit: ranges, level masks and majorants."""

    def __init__(self, grid):
        self.host = grid
        self.res = mi.Vector3i(*[int(r) for r in grid.res])
        self.vmin = mi.Float(grid.vmin)
        self.vmax = mi.Float(grid.vmax)
        self.level_bits = mi.UInt32(grid.level_bits)
        self.majorant = dr.zeros(mi.Float, grid.vmin.size)
        dr.make_opaque(self.res, self.vmin, self.vmax, self.level_bits)

    @property
    def size(self) -> int:
        return self.host.vmin.size

    def update_majorants(self, tf, density_scale):
        """Per-macrocell majorant ``density_scale * max alpha`` over the
        table entries covering the macrocell's value range (one kernel)."""
        self.majorant = density_scale * tf.range_max_alpha(self.vmin, self.vmax)
        dr.make_opaque(self.majorant)

    def cell_of(self, u: mi.Vector3f) -> mi.Vector3i:
        """Macrocell containing local point ``u`` (clamped to the grid)."""
        return dr.clip(mi.Vector3i(dr.floor(u * mi.Vector3f(self.res))), 0, self.res - 1)

    def flat(self, c: mi.Vector3i) -> mi.UInt32:
        return mi.UInt32(c.x + self.res.x * (c.y + self.res.y * c.z))
