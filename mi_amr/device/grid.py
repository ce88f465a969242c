"""The macrocell grid in Dr.Jit: value ranges, level masks and majorants.

Macrocell ``(i, j, k)`` of an ``(rx, ry, rz)`` grid spans
``[i/rx, (i+1)/rx] x ...`` of the medium's local unit cube.
"""

from __future__ import annotations

from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..structures.cost_model import refine_gain
from ..structures.footprint import thinning_bytes_per_macrocell
from ..structures.macrocell_grid import NO_LEVEL
from ..core.jit_struct import jit_struct


def finest_level(level_bits):
    """The finest level set in per-leaf level masks (bit L: a level-L cell
    reaches the leaf); `NO_LEVEL` where none is set."""
    return dr.minimum(dr.tzcnt(level_bits), NO_LEVEL)


#: Minorants are scaled by this: an interpolated TF alpha may round one ulp
#: below the smaller of its two table entries.
MINORANT_SHRINK = 1.0 - 1e-6


@jit_struct(res="Vector3i", vmin="Float", vmax="Float", level_bits="UInt32", majorant="Float",
            minorant="Float", mask_lo="UInt32", mask_hi="UInt32", bin_lo="Float", bin_hi="Float")
class DeviceMacrocellGrid:
    """A `MacrocellGrid` in Dr.Jit: ranges, level masks, value masks (when
    the grid has them: ``mask_lo``/``mask_hi`` the low and high 32 bits, and
    the value bins' edges), majorants and minorants (inverse world units)."""

    def __init__(self, grid):
        self.host = grid
        self.res = mi.Vector3i(*[int(r) for r in grid.res])
        self.vmin = mi.Float(grid.vmin)
        self.vmax = mi.Float(grid.vmax)
        self.level_bits = mi.UInt32(grid.level_bits)
        self.majorant = dr.zeros(mi.Float, grid.vmin.size)
        self.minorant = dr.zeros(mi.Float, grid.vmin.size)
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

    def update_majorants(self, tf, density_scale, minorants: bool = True):
        """Per-macrocell majorant ``density_scale * max alpha`` over the
        table entries covering the macrocell's value range and, with value
        masks, over the bins of its mask (the smaller of the two); minorant
        ``density_scale * min alpha`` over the same (the larger of the two),
        or 0 where ``minorants`` is false (data with holes, where a point
        may have no value)."""
        alpha = tf.range_max_alpha(self.vmin, self.vmax)
        if self.has_masks:
            alpha = dr.minimum(alpha, self._mask_alpha(tf, dr.maximum))
        self.majorant = density_scale * alpha
        if minorants:
            low = tf.range_min_alpha(self.vmin, self.vmax)
            if self.has_masks:
                low = dr.maximum(low, self._mask_alpha(tf, dr.minimum))
            self.minorant = (density_scale * MINORANT_SHRINK) * low
        else:
            self.minorant = dr.zeros(mi.Float, self.size)
        dr.make_opaque(self.majorant, self.minorant)

    def _mask_alpha(self, tf, op):
        """Max (``op = dr.maximum``) or min (``dr.minimum``) alpha over the
        set bins of each value mask: per-bin extremes (64 range look-ups),
        then one 256-entry table per mask byte (8 x 256 entries), then one
        table look-up per byte of each mask; 0 for an empty mask."""
        none = 0.0 if op is dr.maximum else float("inf")       # neutral: no bit set
        bin_range = tf.range_max_alpha if op is dr.maximum else tf.range_min_alpha
        bin_alpha = bin_range(self.bin_lo, self.bin_hi)
        dr.eval(bin_alpha)
        idx = dr.arange(mi.UInt32, 8 * 256)
        byte, j = idx & 255, idx >> 8
        table = mi.Float(none)
        for i in range(8):
            a = dr.gather(mi.Float, bin_alpha, 8 * j + i)
            table = dr.select(((byte >> i) & 1) != 0, op(table, a), table)
        dr.eval(table)
        m = mi.Float(none)
        for j in range(8):
            word = self.mask_lo if j < 4 else self.mask_hi
            b = (word >> (8 * (j % 4))) & 255
            m = op(m, dr.gather(mi.Float, table, 256 * j + b))
        return dr.select(m == float("inf"), 0.0, m)

    def cell_of(self, u: mi.Vector3f) -> mi.Vector3i:
        """Macrocell containing local point ``u`` (clamped to the grid)."""
        return dr.clip(mi.Vector3i(dr.floor(u * mi.Vector3f(self.res))), 0, self.res - 1)

    def flat(self, c: mi.Vector3i) -> mi.UInt32:
        return mi.UInt32(c.x + self.res.x * (c.y + self.res.y * c.z))

    def describe(self) -> str:
        return "grid " + "x".join(str(int(r)) for r in self.host.res)

    def effective_majorants(self) -> np.ndarray:
        """The majorant of each macrocell, [z, y, x]."""
        r = self.host.res
        return self.majorant.numpy().reshape(r[2], r[1], r[0])


class DeviceThinningGrid(DeviceMacrocellGrid):
    """The finer majorants that thin the walks' tentative collisions
    (docs/design.md section 5d): a uniform `MacrocellGrid`'s value ranges
    and masks on the device, and the majorants made from them on every TF
    change; no level masks, no minorants and no host copy (the walk and
    the look-ups read the walked grid's)."""

    def __init__(self, grid):
        super().__init__(grid)
        self.n = int(grid.vmin.size)
        self.host_res = tuple(int(r) for r in grid.res)
        self.level_bits = dr.zeros(mi.UInt32, 1)
        self.host = None
        dr.make_opaque(self.level_bits)

    @property
    def size(self) -> int:
        return self.n

    @property
    def nbytes(self) -> int:
        return thinning_bytes_per_macrocell(self.has_masks) * self.n

    def update_majorants(self, tf, density_scale, minorants: bool = False):
        """The majorants (as `DeviceMacrocellGrid`); no minorants."""
        super().update_majorants(tf, density_scale, False)
        self.minorant = dr.zeros(mi.Float, 1)
        dr.make_opaque(self.minorant)

    def majorant_at(self, u: mi.Vector3f, active=True) -> mi.Float:
        """The majorant (inverse world units) of the macrocell holding each
        local point ``u``."""
        return dr.gather(mi.Float, self.majorant, self.flat(self.cell_of(u)), active)

    def describe(self) -> str:
        return "thinning grid " + "x".join(str(r) for r in self.host_res)


#: The largest edge (coarse macrocells) of an empty cube in ``coarse_skip``:
#: larger edges saved no further steps on the benchmark data, and edges up
#: to 4 (``log2`` in two bits) let the eight octants share one 32-bit word
#: (docs/performance/frame-cost.md section 8).
MAX_SKIP_EDGE = 4
#: Bits per octant in ``coarse_skip`` (log2 of the edge; 8 octants in 32 bits).
SKIP_BITS = 2
assert MAX_SKIP_EDGE.bit_length() - 1 < 1 << SKIP_BITS


@jit_struct(res="Vector3i", coarse_res="Vector3i", fine=DeviceMacrocellGrid, coarse_mu="Float",
            coarse_min="Float", coarse_skip="UInt32", coarse_level="UInt32", coarse_vmin="Float",
            coarse_vmax="Float", fine_inside="Bool", n_fine="Float", keep_step="Float", refine_step="Float",
            world_scale="Float")
class DeviceTwoLevelGrid:
    """A two-level macrocell grid in Dr.Jit (docs/design.md section 4).

    The fine level is a `MacrocellGrid` of ``res`` macrocells; the coarse
    level groups them into blocks of ``f^3`` (``coarse_res = ceil(res /
    f)``, the last block along an axis may reach past the unit cube). The
    fine macrocells are stored block by block (``f^3`` consecutive entries
    per coarse macrocell, padded with empty ones), so that per-block maxima
    and sums are block reductions. On each TF change a coarse macrocell is
    *refined* (walked through its fine macrocells) where that lowers the
    expected look-ups plus steps per unit length inside it; ``coarse_mu``
    holds its majorant, the largest of its fine ones, or -1 where refined;
    ``coarse_min`` its minorant, the smallest of its fine ones.
    ``coarse_skip``: per coarse macrocell and octant of ray directions, the
    edge of an empty cube of coarse macrocells that stretches from it along
    the octant (`_skip_cubes`), so that a ray may cross that whole cube in
    one step (empty-space skipping). ``coarse_level``: the finest level
    that reaches each coarse macrocell (`Segment.level` of a coarse step);
    ``coarse_vmin``/``coarse_vmax``: the value range of each (of its fine
    ones, made with the majorants: `Segment.vmin` of a coarse step).
    """

    def __init__(self, grid, refinement: int, world_scale: float, step_costs):
        f = int(refinement)
        if f < 2 or f & (f - 1):
            raise ValueError(f"grid refinement must be a power of two >= 2, got {f}")
        self.host, self.refinement, self.log2f = grid, f, f.bit_length() - 1
        rf = np.asarray(grid.res, dtype=np.int64)
        rc = -(-rf // f)
        self.coarse_shape = rc                  # coarse_res on the host (x, y, z)
        self.res = mi.Vector3i(*[int(r) for r in rf])
        self.coarse_res = mi.Vector3i(*[int(r) for r in rc])
        self.n_coarse = int(np.prod(rc))

        blocked = self.blocked
        inside = blocked(np.ones(grid.vmin.size, np.float32), 0.0)
        view = SimpleNamespace(res=grid.res, vmin=blocked(grid.vmin, np.inf), vmax=blocked(grid.vmax, -np.inf),
                               level_bits=blocked(grid.level_bits, np.uint32(0)),
                               masks=None if grid.masks is None else blocked(grid.masks, np.uint64(0)),
                               bins=grid.bins)
        self.fine = DeviceMacrocellGrid(view)
        self.fine.host = grid
        self.fine_inside = mi.Bool(inside > 0)
        self.n_fine = dr.block_sum(mi.Float(inside), f ** 3)
        self.coarse_level = dr.block_reduce(dr.ReduceOp.Min, finest_level(self.fine.level_bits), f ** 3)
        self.coarse_mu = dr.zeros(mi.Float, self.n_coarse)
        self.coarse_min = dr.zeros(mi.Float, self.n_coarse)
        self.coarse_skip = dr.zeros(mi.UInt32, self.n_coarse)
        self.coarse_vmin = dr.zeros(mi.Float, self.n_coarse)
        self.coarse_vmax = dr.zeros(mi.Float, self.n_coarse)
        self.keep_step, self.refine_step = mi.Float(step_costs[0]), mi.Float(step_costs[1])
        self.world_scale = mi.Float(world_scale)
        dr.make_opaque(self.res, self.coarse_res, self.fine_inside, self.n_fine, self.coarse_level,
                       self.keep_step, self.refine_step, self.world_scale)

    def blocked(self, a, fill):
        """A per-fine-macrocell host array ([z, y, x] order, flat) in the
        device's block order, the padding filled with ``fill``."""
        f, rf, rc = self.refinement, np.asarray(self.host.res, np.int64), self.coarse_shape
        a = np.asarray(a).reshape(int(rf[2]), int(rf[1]), int(rf[0]))
        pad = [(0, int(rc[2] * f - rf[2])), (0, int(rc[1] * f - rf[1])), (0, int(rc[0] * f - rf[0]))]
        a = np.pad(a, pad, constant_values=fill)
        a = a.reshape(int(rc[2]), f, int(rc[1]), f, int(rc[0]), f).transpose(0, 2, 4, 1, 3, 5)
        return np.ascontiguousarray(a).reshape(-1)

    @property
    def size(self) -> int:
        return self.host.vmin.size

    @property
    def majorant(self) -> mi.Float:
        """Fine majorants (block order): each bounds the field in its macrocell."""
        return self.fine.majorant

    @property
    def minorant(self) -> mi.Float:
        """Fine minorants (block order)."""
        return self.fine.minorant

    @property
    def level_bits(self) -> mi.UInt32:
        return self.fine.level_bits

    def update_majorants(self, tf, density_scale, minorants: bool = True):
        """Fine majorants and minorants (as `DeviceMacrocellGrid`), coarse
        ones as their block maxima and minima, and which coarse macrocells
        to refine (`mi_amr.structures.cost_model.refine_gain` > 0); no host
        round trip."""
        self.fine.update_majorants(tf, density_scale, minorants)
        self.coarse_min = dr.block_reduce(dr.ReduceOp.Min, dr.select(self.fine_inside, self.fine.minorant,
                                                                     float("inf")), self.refinement ** 3)
        b = self.refinement ** 3
        mu = self.fine.majorant * self.world_scale          # inverse local length
        mu_c = dr.block_reduce(dr.ReduceOp.Max, mu, b)
        s1 = dr.block_sum(mu, b)
        gain = refine_gain(self.n_fine, s1, mu_c, self.keep_step, self.refine_step, dr.maximum)
        self.coarse_mu = dr.select(gain > 0.0, -1.0, mu_c * dr.rcp(self.world_scale))
        self.coarse_skip = self._skip_cubes(self.coarse_mu != 0.0)
        # the ranges too: new values (`Structures.revalue`) end here as well
        self.coarse_vmin = dr.block_reduce(dr.ReduceOp.Min, self.fine.vmin, b)
        self.coarse_vmax = dr.block_reduce(dr.ReduceOp.Max, self.fine.vmax, b)
        dr.make_opaque(self.coarse_mu, self.coarse_min, self.coarse_skip, self.coarse_vmin, self.coarse_vmax)

    def _skip_cubes(self, occupied: mi.Bool) -> mi.UInt32:
        """Per coarse macrocell ``c``, one word: its ``SKIP_BITS`` bits from
        bit ``SKIP_BITS * o`` on, for octant ``o`` (bit ``i`` of ``o`` set
        where rays run down axis ``i``), hold ``log2 k``: ``k`` is the edge,
        a power of two, of an empty cube of ``k^3`` coarse macrocells that
        has ``c`` as its corner and stretches from it along the octant
        (cells past the grid count as empty; ``k`` at most `MAX_SKIP_EDGE`);
        0 (``k = 1``, the macrocell itself) where ``c`` is ``occupied``. A
        ray in ``c`` that runs along the octant stays in that cube until it
        leaves through one of its three far faces, so it crosses the cube in
        one step (empty-space skipping).

        Tables ``F_m`` ("the cube of edge m with its lowest corner at q is
        empty", cut at the grid's upper faces) for m = 1, 2, 4, ... by
        doubling, each the AND of eight ``F_{m/2}`` at offsets 0 and m/2;
        then per entry the largest power of two m whose cube is empty (the
        largest edge of any size, found by bisection, saved a few more steps
        but no frame time, and made each TF change dearer:
        docs/performance/frame-cost.md section 8). A cube
        that reaches below the grid is looked up at its corner moved up to 0
        (a larger cube in the grid: conservative, so there ``k`` may fall
        short)."""
        n = self.n_coarse
        rc = self.coarse_res
        rmax = int(self.coarse_shape.max())

        def corner(i):
            return mi.Vector3i(i % rc.x, (i // rc.x) % rc.y, i // (rc.x * rc.y))

        def at(table, q):
            inside = dr.all(q < rc)
            hit = dr.gather(mi.UInt32, table, mi.UInt32(q.x + rc.x * (q.y + rc.y * q.z)), inside)
            return dr.select(inside, hit, 1)
        q = corner(dr.arange(mi.Int32, n))
        tables = [dr.select(occupied, 0, mi.UInt32(1))]
        m = 1
        while m < min(rmax, MAX_SKIP_EDGE):
            half, m = m, 2 * m
            wider = mi.UInt32(1)
            for k in range(8):
                wider &= at(tables[-1], q + mi.Vector3i(half if k & 1 else 0, half if k & 2 else 0,
                                                        half if k & 4 else 0))
            dr.eval(wider)
            tables.append(wider)
        packed = mi.UInt32(0)
        for octant in range(8):
            down = [(octant >> axis) & 1 for axis in range(3)]
            log2_edge = mi.UInt32(0)          # of the largest power of two that is empty
            for lv in range(1, len(tables)):
                m = 1 << lv
                corner_q = mi.Vector3i(*[dr.maximum(q[a] - (m - 1), 0) if down[a] else q[a] for a in range(3)])
                log2_edge = dr.select(at(tables[lv], corner_q) == 1, lv, log2_edge)
            packed |= log2_edge << (SKIP_BITS * octant)
        return packed

    def describe(self) -> str:
        return (f"two-level grid {'x'.join(str(int(r)) for r in self.coarse_shape)} refined {self.refinement}x "
                f"in {self.refined_fraction():.0%} of its macrocells")

    def refined_fraction(self) -> float:
        """Share of the coarse macrocells walked through their fine ones."""
        return float(dr.count(self.coarse_mu < 0.0)[0]) / self.n_coarse

    def cell_of(self, u: mi.Vector3f) -> mi.Vector3i:
        """Fine macrocell containing local point ``u`` (clamped to the grid)."""
        return dr.clip(mi.Vector3i(dr.floor(u * mi.Vector3f(self.res))), 0, self.res - 1)

    def flat(self, c: mi.Vector3i) -> mi.UInt32:
        """Storage index of fine macrocell ``c`` (block by block)."""
        cc = c >> self.log2f
        m = self.refinement - 1
        block = cc.x + self.coarse_res.x * (cc.y + self.coarse_res.y * cc.z)
        local = (c.x & m) + self.refinement * ((c.y & m) + self.refinement * (c.z & m))
        return mi.UInt32(block) * (self.refinement ** 3) + mi.UInt32(local)

    def grid_order(self, values) -> np.ndarray:
        """Per-fine-macrocell values in block order (f^3 per coarse
        macrocell) as a [z, y, x] array of the fine grid, padding dropped."""
        f, rf, rc = self.refinement, self.host.res, self.coarse_shape
        a = np.asarray(values).reshape(rc[2], rc[1], rc[0], f, f, f).transpose(0, 3, 1, 4, 2, 5)
        return a.reshape(rc[2] * f, rc[1] * f, rc[0] * f)[:rf[2], :rf[1], :rf[0]]

    def effective_majorants(self) -> np.ndarray:
        """The majorant the walk uses in each fine macrocell, [z, y, x]."""
        b = self.refinement ** 3
        coarse = np.repeat(self.coarse_mu.numpy(), b)
        return self.grid_order(np.where(coarse < 0, self.fine.majorant.numpy(), coarse))
