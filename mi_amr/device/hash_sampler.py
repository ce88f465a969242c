"""Point location and reconstruction through a hash of blocks (Dr.Jit).

The data live in a `BlockVolume`: aligned B^3 blocks of same-level cells.
One hash table per level maps a block coordinate to its block; a cell's
value is then one gather (docs/design.md sections 3 and 9). ``nearest``
probes level by level, coarsest first, and stops at the first cell present
(leaf cells do not overlap, so any order finds the same cell; look-ups fall
uniformly in the volume of a macrocell and coarse cells fill most of it:
1.25-1.78 levels probed per look-up against 1.44-2.50 finest first on the
20k data, docs/performance/frame-cost.md section 7); ``tent`` visits the
2x2x2 stencil of every contributing level, probing once per distinct block
the stencil touches (usually one).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..data.blocks import BlockVolume
from ..data.cells import AMRCells
from ..data.reconstruction import WEIGHT_EPS, check_method
from ..structures.level_hash import LevelHash, hash_u32, pack_key
from .ray import in_unit_cube
from .structs import jit_struct
from .values import device_values, shares_host_values

#: Stencil corner c = dx + 2 dy + 4 dz.
CORNERS = [(c & 1, (c >> 1) & 1, (c >> 2) & 1) for c in range(8)]


class BlockHash(LevelHash):
    """Per-level hash of the block coordinates of a `BlockVolume`; payload:
    the block index. ``ghosts``, ``(coord, level)`` of blocks without values,
    are numbered after the volume's blocks."""

    def __init__(self, volume: BlockVolume, ghosts=None):
        coord, level = volume.coord, volume.level
        if ghosts is not None:
            coord, level = np.concatenate([coord, ghosts[0]]), np.concatenate([level, ghosts[1]])
        entries = {int(L): (coord[level == L], np.nonzero(level == L)[0].astype(np.uint32))
                   for L in np.unique(level)}
        super().__init__(entries, np.uint32, volume.source)


@jit_struct(keys="UInt64", keys_z="UInt32", offset="UInt32", mask="UInt32", max_probe="UInt32",
            payload="UInt32", values="Float", neighbours="UInt32", n_blocks="UInt32")
class DeviceReconstruction:
    """Reconstruction at points, in Dr.Jit, from the blocks of a `BlockVolume`
    (an `AMRCells` is converted first)."""

    def __init__(self, volume: BlockVolume | AMRCells, method: str):
        self.method = check_method(method)
        if isinstance(volume, AMRCells):
            volume = BlockVolume.from_cells(volume, method=method)
        self.volume = volume
        if method == "tent":                # ghost blocks and neighbours: one probe per stencil
            ghost_coord, ghost_level, neighbours = volume.stencil_index()
            self.hash = BlockHash(volume, (ghost_coord, ghost_level))
        else:
            self.hash, neighbours = BlockHash(volume), np.zeros(1, np.uint32)
        self.n_blocks = mi.UInt32(len(volume.level))
        self.origin = volume.origin
        self.block = volume.block
        self.log2_block = volume.log2_block
        self.keys = mi.UInt64(self.hash.keys)
        self.keys_z = mi.UInt32(self.hash.keys_z)
        self.wide = self.hash.wide
        self.offset = mi.UInt32(self.hash.offset)
        self.mask = mi.UInt32(self.hash.mask)
        self.max_probe = mi.UInt32(self.hash.max_probe)
        self.payload = mi.UInt32(self.hash.payload)
        self.values = device_values(volume)    # shared with every structure on the data
        self.neighbours = mi.UInt32(neighbours.ravel())
        dr.make_opaque(self.keys, self.keys_z, self.payload, self.offset, self.mask, self.max_probe,
                       self.neighbours, self.n_blocks)
        self.shares_values = shares_host_values(self.values)

    @property
    def nbytes(self) -> int:
        """Bytes of the hash, plus the device values unless they are the
        volume's own (CPU backend: counted once, in `BlockVolume.nbytes`)."""
        return (self.hash.nbytes + 4 * dr.width(self.neighbours)
                + (0 if self.shares_values else 4 * dr.width(self.values)))

    def _probe(self, qb: mi.Vector3u, L, probe, active):
        """One linear-probing step for block ``qb`` of level ``L``:
        ``(hit, finished, block index)``."""
        key = pack_key(mi.UInt64(qb.x), mi.UInt64(qb.y), mi.UInt64(qb.z), self.wide)
        h = hash_u32(qb.x, qb.y, qb.z)
        slot = dr.gather(mi.UInt32, self.offset, L, active) + \
            ((h + probe) & dr.gather(mi.UInt32, self.mask, L, active))
        k = dr.gather(mi.UInt64, self.keys, slot, active)
        hit = active & (k == key)
        if dr.hint(self.wide, mode="scalar"):
            hit &= dr.gather(mi.UInt32, self.keys_z, slot, hit) == qb.z
        finished = hit | ~active | (k == 0xFFFFFFFFFFFFFFFF) | (probe + 1 >= self.max_probe)
        return hit, finished, dr.gather(mi.UInt32, self.payload, slot, hit)

    def _local(self, q: mi.Vector3u):
        """Index of cell ``q`` (level coordinates) inside its block."""
        m = self.block - 1
        return (q.x & m) + self.block * ((q.y & m) + self.block * (q.z & m))

    @dr.syntax
    def eval(self, x: mi.Vector3f, level_bits: mi.UInt32, active=True):
        """Reconstruct at ``x`` (finest units relative to ``origin``).

        ``level_bits``: the levels that may contribute at ``x`` (from the
        macrocell grid). Returns ``(value, found)``. Each loop iteration does
        one probe; a level takes at most ``max_probe`` probes per block
        (``nearest``: one block; ``tent``: at most 8).
        """
        tent = self.method == "tent"
        limit = float(min(self.hash.coord_limit << self.log2_block, 1 << 31))
        b3 = self.block ** 3
        remaining = dr.select(active, level_bits, 0)
        probe = mi.UInt32(0)
        # loop state: only what this reconstruction changes (docs/design.md section 6)
        done = mi.UInt32(0) if tent else 0     # tent: stencil corners handled at this level
        sum_w = mi.Float(0.0) if tent else 0.0
        sum_wv = mi.Float(0.0)
        found = False if tent else mi.Bool(False)
        while dr.hint(remaining != 0, label="amr_reconstruct", exclude=[self, x]):
            if dr.hint(tent, mode="scalar"):
                L = dr.tzcnt(remaining)
            else:
                L = 31 - dr.lzcnt(remaining)       # coarsest first: see the module docstring
            # x / 2^L is exact; fractions stay small numbers so that no
            # sub-cell offset is rounded away near 2^24 (float32 spacing 1)
            xl = x * dr.rcp(mi.Float(mi.UInt32(1) << L))
            fl = dr.floor(xl)
            frac = xl - fl
            if dr.hint(tent, mode="scalar"):
                # Stencil b + {0,1}^3 with b = floor(xl - 1/2); tent weights
                # (Eq. phi_i, docs/design.md section 3) from t1, the offset
                # of x from corner 0's centre
                upper = frac >= 0.5
                base = fl - dr.select(upper, 0.0, 1.0)
                t1 = dr.select(upper, frac - 0.5, frac + 0.5)
                t0 = 1.0 - t1
                ok_corner = []
                for c, (dx, dy, dz) in enumerate(CORNERS):
                    qc = base + mi.Vector3f(dx, dy, dz)
                    w = (t1.x if dx else t0.x) * (t1.y if dy else t0.y) * (t1.z if dz else t0.z)
                    ok_corner.append(dr.all((qc >= 0.0) & (qc < limit)) & (w > 0.0))
                    done |= dr.select(ok_corner[c], 0, 1 << c)
                need = done != 0xFF
                # Probe the block of the base cell b (a ghost when it has no
                # cell but a neighbour does): its upper neighbours hold every
                # other corner, and no such block means no corner at this
                # level. At the data's lower edge (b < 0) probe the block of
                # the first corner not handled yet and take the corners in it.
                use_base = need & dr.all(base >= 0.0)
                c0 = dr.tzcnt(~done & 0xFF)
                q0 = base + mi.Vector3f(mi.Float(c0 & 1), mi.Float((c0 >> 1) & 1), mi.Float((c0 >> 2) & 1))
                target = dr.select(use_base, base, q0)
                qb = mi.Vector3u(dr.select(need, target, 0.0)) >> self.log2_block
                hit, finished, blk = self._probe(qb, L, probe, need)
                base_local = mi.Vector3u(dr.select(use_base, base, 0.0)) & (self.block - 1)
                for c, (dx, dy, dz) in enumerate(CORNERS):
                    qc = base + mi.Vector3f(dx, dy, dz)
                    qi = mi.Vector3u(dr.select(ok_corner[c], qc, 0.0))
                    open_c = finished & need & ok_corner[c] & ((done & (1 << c)) == 0)
                    # from the base block: the neighbour direction of corner c
                    d = (dr.select(base_local.x + 1 >= self.block, dx, 0)
                         | dr.select(base_local.y + 1 >= self.block, 2 * dy, 0)
                         | dr.select(base_local.z + 1 >= self.block, 4 * dz, 0))
                    via_nb = open_c & use_base & hit & (d != 0)
                    blk_c = dr.select(via_nb, dr.gather(mi.UInt32, self.neighbours, blk * 7 + d - 1, via_nb), blk)
                    mine = open_c & (use_base | dr.all((qi >> self.log2_block) == qb))
                    has = mine & hit & (blk_c < self.n_blocks)      # ghosts and "none" hold no values
                    w = (t1.x if dx else t0.x) * (t1.y if dy else t0.y) * (t1.z if dz else t0.z)
                    v = dr.gather(mi.Float, self.values, blk_c * b3 + self._local(qi), has)
                    use = has & ~dr.isnan(v)
                    sum_w += dr.select(use, w, 0.0)
                    sum_wv += dr.select(use, w * v, 0.0)
                    done |= dr.select(mine, 1 << c, 0)
                probe = dr.select(finished, 0, probe + 1)
                level_done = done == 0xFF
                done = dr.select(level_done, 0, done)
            else:
                in_range = dr.all((fl >= 0.0) & (fl < limit))
                qi = mi.Vector3u(dr.select(in_range, fl, 0.0))
                hit, level_done, blk = self._probe(qi >> self.log2_block, L, probe, in_range)
                v = dr.gather(mi.Float, self.values, blk * b3 + self._local(qi), hit)
                found |= hit & ~dr.isnan(v)
                sum_wv = dr.select(hit & ~dr.isnan(v), v, sum_wv)
                probe = dr.select(level_done, 0, probe + 1)
            remaining = dr.select(level_done, remaining & ~(mi.UInt32(1) << L), remaining)
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
