"""Point location and reconstruction through bricks (Dr.Jit).

* ``abr`` sampling: find the active brick region (ABR) that contains the
  point (kd-tree descent) and visit its constant list of bricks.
* ``brick`` sampling: visit the bricks whose *extended domain* contains the
  point, found through a uniform grid of per-macrocell brick lists.

Within a brick, ``tent`` is trilinear interpolation over the 2x2x2 cells
around the point with the weights of cells outside the brick dropped; the
weights of all visited bricks are summed and normalised (docs/design.md
section 3). ``nearest`` takes the finest brick whose bounds contain the point;
its ABRs are built over the brick bounds, one brick per leaf.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..structures.bricks import Bricks
from ..data.reconstruction import WEIGHT_EPS
from ..structures.brick_lists import BrickLists
from .ray import in_unit_cube
from .structs import jit_struct
from .values import device_values


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

    def _index(self, off, i):
        return off + mi.UInt32(i.x + self.block * (i.y + self.block * i.z))

    def contribution(self, b, x, tent: bool, active):
        """``(sum_w, sum_wv, inside)`` of brick ``b`` at point ``x``; for
        ``nearest``: ``(cell width, value of the brick's cell nearest x, inside)``."""
        lo = dr.gather(mi.Vector3f, self.lo, b, active)
        dims = dr.gather(mi.Vector3i, self.dims, b, active)
        w = dr.gather(mi.Float, self.width, b, active)
        off = dr.gather(mi.UInt32, self.offset, b, active)
        xb = (x - lo) * dr.rcp(w)
        inside = active & dr.all((xb >= 0.0) & (xb < mi.Vector3f(dims)))
        if not tent:
            # the nearest cell of the brick (clamped into it); ``inside`` says whether it contains x
            i = dr.clip(mi.Vector3i(dr.floor(xb)), 0, dims - 1)
            v = dr.gather(mi.Float, self.values, self._index(off, i), active)
            return w, v, inside
        xc = xb - 0.5
        base = mi.Vector3i(dr.floor(xc))
        sum_w = mi.Float(0.0)
        sum_wv = mi.Float(0.0)
        for c in range(8):
            i = base + mi.Vector3i(c & 1, (c >> 1) & 1, (c >> 2) & 1)
            ok = active & dr.all((i >= 0) & (i < dims))
            dd = dr.abs(xc - mi.Vector3f(i))
            wt = dr.maximum(0.0, 1.0 - dd.x) * dr.maximum(0.0, 1.0 - dd.y) * dr.maximum(0.0, 1.0 - dd.z)
            ok &= wt > 0.0
            v = dr.gather(mi.Float, self.values, self._index(off, i), ok)
            sum_w += dr.select(ok, wt, 0.0)
            sum_wv += dr.select(ok, wt * v, 0.0)
        return sum_w, sum_wv, inside


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

    def __init__(self, bricks: DeviceBricks, method: str, offset, extent, abr_tree=None, lists=None,
                 over_bounds: bool = False):
        """``over_bounds``: ``abr_tree`` was built over the brick bounds
        (``nearest``), so a leaf's list is the one brick that contains the
        whole leaf: its cell is taken even where float rounding puts the
        point a hair outside the brick."""
        self.bricks = bricks
        self.tent = method == "tent"
        self.over_bounds = over_bounds and abr_tree is not None and not self.tent
        self.offset, self.extent = offset, extent
        self.abr = abr_tree
        self.lists = lists

    def eval(self, u: mi.Vector3f, active=True):
        """``(value, found)`` at local points ``u``; nothing outside the unit cube."""
        active = mi.Bool(active) & in_unit_cube(u)
        return self.eval_at(self.offset + u * self.extent, u, active)

    @dr.syntax
    def eval_at(self, x: mi.Vector3f, u: mi.Vector3f, active=True):
        """Value and found mask at ``x`` (finest units rel. to the brick
        origin), ``u`` the same point in the unit cube."""
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
        sum_w = mi.Float(0.0) if self.tent else 0.0
        sum_wv = mi.Float(0.0)
        best_w = float("inf") if self.tent else mi.Float(dr.inf)
        while dr.hint(i < count, label="amr_brick_list", exclude=[self, x, start, count, items, in_domain]):
            b = dr.gather(mi.UInt32, items, start + i)
            w, wv, inside = self.bricks.contribution(b, x, self.tent, i < count)
            if dr.hint(self.tent, mode="scalar"):
                sum_w += w
                sum_wv += wv
            else:
                if dr.hint(self.over_bounds, mode="scalar"):      # the leaf lies in its brick
                    inside = (i < count) & in_domain
                finer = inside & (w < best_w)          # finest containing brick wins
                best_w = dr.select(finer, w, best_w)
                sum_wv = dr.select(finer, wv, sum_wv)
            i += 1
        if dr.hint(self.tent, mode="scalar"):
            found = sum_w > WEIGHT_EPS
            return dr.select(found, sum_wv / dr.maximum(sum_w, WEIGHT_EPS), 0.0), found
        found = best_w < dr.inf
        return dr.select(found, sum_wv, 0.0), found
