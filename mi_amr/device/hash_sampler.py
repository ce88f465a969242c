"""Point location and reconstruction through per-level hash tables (Dr.Jit).

``nearest`` probes a `CellHash` level by level, finest first; ``tent``
probes a `StencilHash` once per contributing level and gathers the level's
2x2x2 stencil (docs/design.md section 3).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..data.cells import AMRCells
from ..data.reconstruction import WEIGHT_EPS, check_method
from ..structures.cell_hash import CellHash, StencilHash, hash_u32, pack_key
from .ray import in_unit_cube
from .structs import jit_struct


@jit_struct(keys="UInt64", keys_z="UInt32", offset="UInt32", mask="UInt32", max_probe="UInt32",
            payload="UInt32", values="Float")
class DeviceReconstruction:
    """Per-level hash tables in Dr.Jit, and reconstruction through them.

    ``nearest`` probes a `CellHash` level by level, finest first, and stops
    at the first cell that contains ``x``. ``tent`` probes a `StencilHash`
    once per level that can contribute: a hit yields the level's whole
    2x2x2 stencil (8 gathers from contiguous memory), so a sample costs
    about one probe plus 8 gathers per contributing level.
    """

    def __init__(self, cells: AMRCells, method: str):
        self.method = check_method(method)
        self.hash = StencilHash(cells) if method == "tent" else CellHash(cells)
        self.origin = self.hash.origin
        self.keys = mi.UInt64(self.hash.keys)
        self.keys_z = mi.UInt32(self.hash.keys_z)
        self.wide = self.hash.wide
        self.offset = mi.UInt32(self.hash.offset)
        self.mask = mi.UInt32(self.hash.mask)
        self.max_probe = mi.UInt32(self.hash.max_probe)
        if method == "tent":                # slot -> stencil index -> 8 values
            self.payload = mi.UInt32(self.hash.payload)
            self.values = mi.Float(self.hash.values)
        else:                               # slot -> value
            self.payload = mi.UInt32(0)
            self.values = mi.Float(self.hash.payload)
        dr.make_opaque(self.keys, self.keys_z, self.payload, self.values, self.offset, self.mask, self.max_probe)

    @property
    def nbytes(self) -> int:
        return self.hash.nbytes

    @dr.syntax
    def eval(self, x: mi.Vector3f, level_bits: mi.UInt32, active=True):
        """Reconstruct at ``x`` (finest units relative to ``origin``).

        ``level_bits``: the levels that may contribute at ``x`` (from the
        macrocell grid). Returns ``(value, found)``. The loop does one probe
        per iteration and runs at most ``levels x max_probe`` iterations.
        """
        tent = self.method == "tent"
        remaining = dr.select(active, level_bits, 0)
        probe = mi.UInt32(0)
        sum_w = mi.Float(0.0)
        sum_wv = mi.Float(0.0)
        found = mi.Bool(False)
        while dr.hint(remaining != 0, label="amr_reconstruct", exclude=[self]):
            # ---- Key of the current level: the stencil base, or the cell ----
            L = dr.tzcnt(remaining)
            # x / 2^L is exact; fractions stay small numbers so that no
            # sub-cell offset is rounded away near 2^24 (float32 spacing 1)
            xl = x * dr.rcp(mi.Float(mi.UInt32(1) << L))
            fl = dr.floor(xl)
            frac = xl - fl
            if dr.hint(tent, mode="scalar"):
                upper = frac >= 0.5
                q = fl + dr.select(upper, 1.0, 0.0)           # stencil key s = b + 1
                t1 = dr.select(upper, frac - 0.5, frac + 0.5)  # offset from corner 0's centre
            else:
                q = fl
            in_range = dr.all((q >= 0.0) & (q < float(self.hash.coord_limit)))
            qi = mi.Vector3u(dr.select(in_range, q, 0.0))

            # ---- One linear-probing step in the level's table ----
            key = pack_key(mi.UInt64(qi.x), mi.UInt64(qi.y), mi.UInt64(qi.z), self.wide)
            h = hash_u32(qi.x, qi.y, qi.z)
            slot = dr.gather(mi.UInt32, self.offset, L) + ((h + probe) & dr.gather(mi.UInt32, self.mask, L))
            k = dr.gather(mi.UInt64, self.keys, slot, in_range)
            hit = in_range & (k == key)
            if dr.hint(self.wide, mode="scalar"):
                hit &= dr.gather(mi.UInt32, self.keys_z, slot, hit) == qi.z
            if dr.hint(tent, mode="scalar"):
                # Tent weights of the 8 stencil cells (Eq. phi_i, docs/design.md section 3)
                idx = dr.gather(mi.UInt32, self.payload, slot, hit) * 8
                t0 = 1.0 - t1
                for c in range(8):
                    wx = t1.x if c & 1 else t0.x
                    wy = t1.y if (c >> 1) & 1 else t0.y
                    wz = t1.z if (c >> 2) & 1 else t0.z
                    w = wx * wy * wz
                    v = dr.gather(mi.Float, self.values, idx + c, hit & (w > 0.0))
                    ok = hit & (w > 0.0) & ~dr.isnan(v)
                    sum_w += dr.select(ok, w, 0.0)
                    sum_wv += dr.select(ok, w * v, 0.0)
            else:
                v = dr.gather(mi.Float, self.values, slot, hit)
                sum_wv = dr.select(hit, v, sum_wv)
                found |= hit
            level_done = hit | ~in_range | (k == 0xFFFFFFFFFFFFFFFF) | (probe + 1 >= self.max_probe)

            # ---- Advance: next probe or next level ----
            probe = dr.select(level_done, 0, probe + 1)
            remaining = dr.select(level_done, remaining & (remaining - 1), remaining)
            if dr.hint(not tent, mode="scalar"):
                remaining = dr.select(found, 0, remaining)
        if dr.hint(tent, mode="scalar"):
            found = sum_w > WEIGHT_EPS
            value = dr.select(found, sum_wv / dr.maximum(sum_w, WEIGHT_EPS), 0.0)
        else:
            value = dr.select(found, sum_wv, 0.0)
        return value, found


class HashSampler:
    """Point sampler over a `DeviceReconstruction`: the macrocell grid's level
    masks limit the levels probed. A view over device structs."""

    def __init__(self, table: DeviceReconstruction, grid, offset, extent):
        self.table, self.grid = table, grid
        self.offset, self.extent = offset, extent

    def eval(self, u: mi.Vector3f, active=True):
        """``(value, found)`` at local points ``u``; nothing outside the unit cube."""
        active = mi.Bool(active) & in_unit_cube(u)
        g = self.grid
        level_bits = dr.gather(mi.UInt32, g.level_bits, g.flat(g.cell_of(u)), active)
        return self.table.eval(self.offset + u * self.extent, level_bits, active)
