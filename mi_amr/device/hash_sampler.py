"""Point location and reconstruction through a hash of blocks (Dr.Jit).

The data live in a `BlockVolume`: aligned B^3 blocks of same-level cells.
One hash table per level maps a block coordinate to its block; a cell's
value is then one gather (docs/design.md sections 3 and 9). The look-up
loop is shared; the reconstruction method (`mi_amr.reconstruction`) picks
the order of the levels and supplies the body for one level. ``nearest``
probes coarsest first and stops at the first cell present: leaf cells do
not overlap, so any order finds the same cell, and look-ups fall uniformly
in the volume of a macrocell, most of which coarse cells fill, so fewer
levels are probed than finest first (docs/performance/frame-cost.md
section 7). ``tent`` visits the 2x2x2 stencil of every contributing level,
probing once per distinct block the stencil touches (usually one).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..data.blocks import BlockVolume
from ..reconstruction import Reconstruction
from ..structures.level_hash import SLOT_BYTES, LevelHash, hash_u32, pack_key
from .ray import in_unit_cube
from ..structures.macrocell_grid import NO_LEVEL
from ..core.jit_struct import jit_struct
from ..data.device_values import CellValues, device_values, shares_host_values


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
    """Reconstruction at points, in Dr.Jit, from the blocks of a `BlockVolume`.

    ``keys``: with narrow keys, each slot's key and payload interleaved
    (``keys[2 s]``, ``keys[2 s + 1]``; ``payload`` unused); with wide keys
    the keys alone, ``keys_z`` and ``payload`` beside them."""

    def __init__(self, volume: BlockVolume, method: Reconstruction):
        self.method = method
        self.volume = volume
        if self.method.needs_ghosts:        # ghost blocks and neighbours: one probe per stencil
            ghost_coord, ghost_level, neighbours = volume.stencil_index()
            self.hash = BlockHash(volume, (ghost_coord, ghost_level))
        else:
            self.hash, neighbours = BlockHash(volume), np.zeros(1, np.uint32)
        self.n_blocks = mi.UInt32(len(volume.level))
        self.origin = volume.origin
        self.block = volume.block
        self.log2_block = volume.log2_block
        self.wide = self.hash.wide
        self.n_slots = len(self.hash.keys)
        if self.wide:
            self.keys = mi.UInt64(self.hash.keys)
            self.payload = mi.UInt32(self.hash.payload)
        else:
            # a slot's key and payload side by side in one cache line: a
            # probe that hits reads its payload without a second miss
            slots = np.empty(2 * self.n_slots, np.uint64)
            slots[0::2], slots[1::2] = self.hash.keys, self.hash.payload
            self.keys = mi.UInt64(slots)
            self.payload = dr.zeros(mi.UInt32, 1)
        self.keys_z = mi.UInt32(self.hash.keys_z)
        self.offset = mi.UInt32(self.hash.offset)
        self.mask = mi.UInt32(self.hash.mask)
        self.max_probe = mi.UInt32(self.hash.max_probe)
        self.values = device_values(volume)    # shared with every structure on the data
        self.neighbours = mi.UInt32(neighbours.ravel())
        dr.make_opaque(self.keys, self.keys_z, self.payload, self.offset, self.mask, self.max_probe,
                       self.neighbours, self.n_blocks)
        self.shares_values = shares_host_values(self.values)

    @property
    def nbytes(self) -> int:
        """Bytes of the hash as the look-ups read it (`SLOT_BYTES` a slot),
        plus the device values unless they are the volume's own (CPU
        backend: counted once, in `BlockVolume.nbytes`)."""
        return (SLOT_BYTES * self.n_slots + 4 * dr.width(self.neighbours)
                + (0 if self.shares_values else 4 * dr.width(self.values)))

    def probe_block(self, qb: mi.Vector3u, L, probe, active):
        """One linear-probing step for block ``qb`` of level ``L``:
        ``(hit, finished, block index)``."""
        key = pack_key(mi.UInt64(qb.x), mi.UInt64(qb.y), mi.UInt64(qb.z), self.wide)
        h = hash_u32(qb.x, qb.y, qb.z)
        slot = dr.gather(mi.UInt32, self.offset, L, active) + \
            ((h + probe) & dr.gather(mi.UInt32, self.mask, L, active))
        if dr.hint(self.wide, mode="scalar"):
            k = dr.gather(mi.UInt64, self.keys, slot, active)
            hit = active & (k == key) & (dr.gather(mi.UInt32, self.keys_z, slot, active & (k == key)) == qb.z)
            block = dr.gather(mi.UInt32, self.payload, slot, hit)
        else:
            k = dr.gather(mi.UInt64, self.keys, 2 * slot, active)
            hit = active & (k == key)
            block = mi.UInt32(dr.gather(mi.UInt64, self.keys, 2 * slot + 1, hit))
        finished = hit | ~active | (k == 0xFFFFFFFFFFFFFFFF) | (probe + 1 >= self.max_probe)
        return hit, finished, block

    @dr.syntax
    def cell_at(self, x: mi.Vector3f, level_bits: mi.UInt32, active=True):
        """The leaf cell that contains ``x`` (finest units relative to
        ``origin``) whatever the reconstruction: ``(value, found, level)``,
        probing the levels of ``level_bits`` coarsest first up to the first
        present cell (leaf cells do not overlap; a ghost block holds none).
        ``level`` is `NO_LEVEL` where none is found."""
        limit = float(min(self.hash.coord_limit << self.log2_block, 1 << 31))
        remaining = dr.select(active, level_bits, 0)
        st = _CellSearch(found=mi.Bool(False), value=mi.Float(0.0), level=mi.UInt32(NO_LEVEL), probe=mi.UInt32(0))
        while dr.hint(remaining != 0, label="amr_cell_at", exclude=[self, x]):
            L = 31 - dr.lzcnt(remaining)
            fl = dr.floor(x * dr.rcp(mi.Float(mi.UInt32(1) << L)))
            in_range = dr.all((fl >= 0.0) & (fl < limit))
            qi = mi.Vector3u(dr.select(in_range, fl, 0.0))
            hit, level_done, blk = self.probe_block(qi >> self.log2_block, L, st.probe, in_range)
            hit &= blk < self.n_blocks
            v = dr.gather(mi.Float, self.values, blk * self.block ** 3 + self.cell_slot(qi), hit)
            present = hit & ~dr.isnan(v)
            st.value = dr.select(present, v, st.value)
            st.level = dr.select(present, L, st.level)
            st.found |= present
            st.probe = dr.select(level_done, 0, st.probe + 1)
            remaining = dr.select(level_done, remaining & ~(mi.UInt32(1) << L), remaining)
            remaining = dr.select(st.found, 0, remaining)
        return st.value, st.found, st.level

    def cell_slot(self, q: mi.Vector3u):
        """Index of cell ``q`` (level coordinates) inside its block."""
        m = self.block - 1
        return (q.x & m) + self.block * ((q.y & m) + self.block * (q.z & m))

    @dr.syntax
    def eval(self, x: mi.Vector3f, level_bits: mi.UInt32, active=True, carried: mi.Float | None = None):
        """Reconstruct at ``x`` (finest units relative to ``origin``).

        ``level_bits``: the levels that may contribute at ``x`` (from the
        macrocell grid). Returns ``(value, found)``; with a ``carried``
        field (same layout as the values) ``value`` is a ``Vector2f`` of
        both fields, reconstructed from the same cells and weights. Each loop iteration does
        one probe, at the level the method picks, and runs the method's body
        for that level (`Reconstruction.hash_step`); a level takes at most
        ``max_probe`` probes per block it visits.
        """
        limit = float(min(self.hash.coord_limit << self.log2_block, 1 << 31))
        remaining = dr.select(active, level_bits, 0)
        probe = mi.UInt32(0)
        # loop state: only what this reconstruction changes (docs/design.md section 6)
        cells = CellValues(self.values, carried)
        state = self.method.hash_state(cells)
        # max_iterations=-1: Dr.Jit's sum-style reverse mode (docs/design.md
        # section 13): a value enters the state once (nearest) or is summed
        # (tent), so the loop's adjoint is the loop again
        while dr.hint(remaining != 0, label="amr_reconstruct", exclude=[self, x], max_iterations=-1):
            L = self.method.hash_level(remaining)
            # x / 2^L is exact; fractions stay small numbers so that no
            # sub-cell offset is rounded away near 2^24 (float32 spacing 1)
            xl = x * dr.rcp(mi.Float(mi.UInt32(1) << L))
            fl = dr.floor(xl)
            level_done, probe, state = self.method.hash_step(self, cells, L, xl, fl, limit, probe, state)
            remaining = dr.select(level_done, remaining & ~(mi.UInt32(1) << L), remaining)
            remaining = self.method.hash_stop(remaining, state)
        return self.method.hash_result(state)


@jit_struct(found="Bool", value="Float", level="UInt32", probe="UInt32")
class _CellSearch:
    """Loop state of `DeviceReconstruction.cell_at`."""

    def __init__(self, found=None, value=None, level=None, probe=None):
        self.found, self.value, self.level, self.probe = found, value, level, probe


class HashSampler:
    """Point sampler over a `DeviceReconstruction`: the macrocell grid's level
    masks limit the levels probed. A view over device structs; ``carried``:
    a further field reconstructed by the same look-up (`CellValues`)."""

    def __init__(self, table: DeviceReconstruction, grid, offset, extent, carried: mi.Float | None = None):
        self.table, self.grid = table, grid
        self.offset, self.extent = offset, extent
        self.carried = carried

    def eval(self, u: mi.Vector3f, active=True):
        """``(value, found)`` at local points ``u``; nothing outside the unit
        cube. ``value``: a ``Vector2f`` (main, carried) when a field is carried."""
        active = mi.Bool(active) & in_unit_cube(u)
        g = self.grid
        level_bits = dr.gather(mi.UInt32, g.level_bits, g.flat(g.cell_of(u)), active)
        return self.table.eval(self.offset + u * self.extent, level_bits, active, self.carried)

    def cell_at(self, u: mi.Vector3f, active=True):
        """``(value, found, level)`` of the leaf cell that contains the local
        point ``u`` (`DeviceReconstruction.cell_at`): the level the ray
        marcher steps by, and the value of ``nearest`` there."""
        active = mi.Bool(active) & in_unit_cube(u)
        g = self.grid
        level_bits = dr.gather(mi.UInt32, g.level_bits, g.flat(g.cell_of(u)), active)
        return self.table.cell_at(self.offset + u * self.extent, level_bits, active)
