"""Point location and reconstruction through bricks (Dr.Jit).

* ``abr`` sampling: find the active brick region (ABR) that contains the
  point (kd-tree descent) and visit its constant list of bricks.
* ``brick`` sampling: visit the bricks whose *extended domain* contains the
  point, found through a uniform grid of per-macrocell brick lists.

What a brick contributes at a point is the reconstruction method's
(`mi_amr.reconstruction`, docs/design.md section 3): ``tent`` is trilinear
interpolation over the 2x2x2 cells around the point with the weights of
cells outside the brick dropped, summed over the visited bricks and
normalised; ``nearest`` takes the finest brick whose bounds contain the
point, and its ABRs are built over the brick bounds, one brick per leaf.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..reconstruction import Reconstruction
from ..structures.brick_lists import BrickLists
from ..structures.bricks import Bricks
from .ray import in_unit_cube
from ..core.jit_struct import jit_struct
from ..data.device_values import CellValues, device_values


@jit_struct(lo="Vector3f", dims="Vector3i", width="Float", offset="UInt32", values="Float")
class DeviceBricks:
    """Bricks in Dr.Jit; positions in finest units relative to ``origin``.
    ``values`` is the volume's one device array (`device_values`): a brick's
    cell ``i`` is at ``offset + i.x + B (i.y + B i.z)``."""

    def __init__(self, bricks: Bricks, origin):
        self.host = bricks
        lo = (bricks.lo - np.asarray(origin)).astype(np.float32)
        self.lo = mi.Vector3f(lo.T.copy())
        self.dims = mi.Vector3i(bricks.dims.T.astype(np.int32).copy())
        self.width = mi.Float(bricks.width.astype(np.float32))
        self.offset = mi.UInt32(bricks.offset.astype(np.uint32))
        self.values = device_values(bricks.volume)
        self.block = int(bricks.stride[1])
        dr.make_opaque(self.lo, self.dims, self.width, self.offset)

    def cell_slot(self, off, i):
        """Index in ``values`` of cell ``i`` of the brick whose first cell is at ``off``."""
        return off + mi.UInt32(i.x + self.block * (i.y + self.block * i.z))

    def locate(self, b, x, active):
        """Brick ``b`` at point ``x``: ``(xb, dims, width, offset, inside)``
        with ``xb`` the point in the brick's cell units from its lower
        corner and ``inside`` whether the brick's bounds contain it."""
        lo = dr.gather(mi.Vector3f, self.lo, b, active)
        dims = dr.gather(mi.Vector3i, self.dims, b, active)
        w = dr.gather(mi.Float, self.width, b, active)
        off = dr.gather(mi.UInt32, self.offset, b, active)
        xb = (x - lo) * dr.rcp(w)
        inside = active & dr.all((xb >= 0.0) & (xb < mi.Vector3f(dims)))
        return xb, dims, w, off, inside


@jit_struct(res="Vector3i", count="UInt32", offset="UInt32", items="UInt32")
class DeviceBrickLists:
    """`BrickLists` in Dr.Jit: a uniform grid over the local unit cube."""

    def __init__(self, lists: BrickLists):
        self.host = lists
        self.res = mi.Vector3i(*[int(r) for r in lists.res])
        self.count = mi.UInt32(lists.count)
        self.offset = mi.UInt32(lists.offset)
        self.items = mi.UInt32(lists.items)
        dr.make_opaque(self.res, self.count, self.offset, self.items)

    def cell(self, u):
        """Flat index of the list cell containing local point ``u``."""
        c = dr.clip(mi.Vector3i(dr.floor(u * mi.Vector3f(self.res))), 0, self.res - 1)
        return mi.UInt32(c.x + self.res.x * (c.y + self.res.y * c.z))


class BrickSampler:
    """Reconstruction through bricks, with ABR (``abr_tree``) or brick-domain
    (``lists``) point location. A view over device structs: it owns no
    Dr.Jit arrays of its own."""

    def __init__(self, bricks: DeviceBricks, method: Reconstruction, offset, extent, abr_tree=None,
                 lists=None, over_bounds: bool = False, carried: mi.Float | None = None):
        """``over_bounds``: ``abr_tree`` was built over the brick bounds
        (where a cell's support is its box), so a leaf's list is the one
        brick that contains the whole leaf: its cell is taken even where
        float rounding puts the point a hair outside the brick.
        ``carried``: a further field reconstructed by the same look-up
        (`CellValues`)."""
        self.carried = carried
        self.bricks = bricks
        self.method = method
        self.over_bounds = over_bounds and abr_tree is not None
        self.offset, self.extent = offset, extent
        self.abr = abr_tree
        self.lists = lists

    def eval(self, u: mi.Vector3f, active=True):
        """``(value, found)`` at local points ``u``; nothing outside the unit
        cube. ``value``: a ``Vector2f`` (main, carried) when a field is carried."""
        active = mi.Bool(active) & in_unit_cube(u)
        return self.eval_at(self.offset + u * self.extent, u, active)

    @dr.syntax
    def eval_at(self, x: mi.Vector3f, u: mi.Vector3f, active=True):
        """Value and found mask at ``x`` (finest units rel. to the brick
        origin), ``u`` the same point in the unit cube: each brick of the
        list is folded in by the method (`Reconstruction.brick_step`)."""
        if dr.hint(self.abr is not None, mode="scalar"):
            leaf = self.abr.locate(u, mi.Vector3f(1.0), active)
            start = dr.gather(mi.UInt32, self.abr.list_offset, leaf, active)
            count = dr.gather(mi.UInt32, self.abr.list_count, leaf, active)
            items = self.abr.items
        else:
            cell = self.lists.cell(u)
            start = dr.gather(mi.UInt32, self.lists.offset, cell, active)
            count = dr.gather(mi.UInt32, self.lists.count, cell, active)
            items = self.lists.items
        count = dr.select(active, count, 0)
        in_domain = dr.all((u >= 0.0) & (u < 1.0))          # cells are half-open
        i = mi.UInt32(0)
        # loop state: only what this reconstruction changes (docs/design.md section 6)
        cells = CellValues(self.bricks.values, self.carried)
        state = self.method.brick_state(cells)
        # max_iterations=-1: sum-style reverse mode, as in the hash look-up
        # (at most one brick contains a point for nearest; tent sums)
        while dr.hint(i < count, label="amr_brick_list", exclude=[self, x, start, count, items, in_domain],
                      max_iterations=-1):
            b = dr.gather(mi.UInt32, items, start + i)
            state = self.method.brick_step(self.bricks, cells, b, x, i < count, state, self.over_bounds, in_domain)
            i += 1
        return self.method.brick_result(state)
