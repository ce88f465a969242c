"""Ray traversal in Dr.Jit: segments ``[t0, t1]`` with a majorant each.

All structures live in the medium's local space (the data bounds are the
unit cube). A *segment iterator* has two methods used inside symbolic loops:

* ``begin(o, d, t_lo, t_hi, active) -> state`` (a tuple of Dr.Jit arrays)
* ``advance(o, d, state, t_hi, active) -> (state, t0, t1, mu, valid)``: the
  next segment along ``o + t d`` after the previous one; ``valid`` is false
  once the ray has left ``[t_lo, t_hi]``.

`GridSegments` walks the macrocell grid with a 3D DDA (Amanatides-Woo);
`TreeSegments` walks the leaves of a kd-tree front to back by re-descending
from the root at the current point ("kd-restart": no stack, exact ties).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .tracking import safe_rcp


class GridSegments:
    """Front-to-back macrocells of a `DeviceMacrocellGrid`."""

    def __init__(self, grid):
        self.grid = grid

    def max_steps(self):
        return self.grid.res.x + self.grid.res.y + self.grid.res.z + 3

    def begin(self, o, d, t_lo, t_hi, active):
        g = self.grid
        res_f = mi.Vector3f(g.res)
        dg = d * res_f
        inv = safe_rcp(dg)
        p = (o + d * t_lo) * res_f
        cell = dr.clip(mi.Vector3i(dr.floor(p)), 0, g.res - 1)
        edge = mi.Vector3f(cell) + dr.select(dg >= 0, 1.0, 0.0)
        t_next = t_lo + (edge - p) * inv
        return (cell, t_next, mi.Float(t_lo))

    def advance(self, o, d, state, t_hi, active):
        g = self.grid
        cell, t_next, t_cell = state
        dg = d * mi.Vector3f(g.res)
        dt = dr.abs(safe_rcp(dg))
        step = dr.select(dg >= 0, 1, -1)
        inside = dr.all((cell >= 0) & (cell < g.res))
        valid = active & inside & (t_cell < t_hi)
        t0 = t_cell
        t1 = dr.minimum(dr.min(t_next), t_hi)
        mu = dr.gather(mi.Float, g.majorant, g.flat(dr.clip(cell, 0, g.res - 1)), valid)
        ax_x = (t_next.x <= t_next.y) & (t_next.x <= t_next.z)
        ax_y = ~ax_x & (t_next.y <= t_next.z)
        ax_z = ~ax_x & ~ax_y
        mv = valid
        cell = mi.Vector3i(dr.select(mv & ax_x, cell.x + step.x, cell.x),
                           dr.select(mv & ax_y, cell.y + step.y, cell.y),
                           dr.select(mv & ax_z, cell.z + step.z, cell.z))
        t_next = mi.Vector3f(dr.select(mv & ax_x, t_next.x + dt.x, t_next.x),
                             dr.select(mv & ax_y, t_next.y + dt.y, t_next.y),
                             dr.select(mv & ax_z, t_next.z + dt.z, t_next.z))
        t_cell = dr.select(mv, t1, t_cell)
        return (cell, t_next, t_cell), t0, t1, mu, valid


class DeviceTree:
    """A `RegionTree` (or SAH kd-tree) in Dr.Jit, in local coordinates.

    ``to_local(x) = (x - lo) * scale`` maps the tree's host units to the unit
    cube. Leaves carry value ranges (``vmin``/``vmax``) and majorants.
    """

    def __init__(self, tree, lo, scale, vmin, vmax, majorant=None):
        lo = np.asarray(lo, dtype=np.float64)
        scale = np.asarray(scale, dtype=np.float64)
        self.host = tree
        ax = tree.axis.astype(np.int64)
        inner = ax < 3
        split_local = np.zeros(len(ax))
        split_local[inner] = (tree.split[inner] - lo[ax[inner]]) * scale[ax[inner]]
        self.axis = mi.UInt32(tree.axis)
        self.split = mi.Float(split_local.astype(np.float32))
        self.child = mi.UInt32(tree.child)
        llo = ((tree.leaf_lo - lo) * scale).astype(np.float32)
        lhi = ((tree.leaf_hi - lo) * scale).astype(np.float32)
        self.leaf_lo = mi.Vector3f(llo.T.copy())
        self.leaf_hi = mi.Vector3f(lhi.T.copy())
        self.vmin = mi.Float(np.asarray(vmin, dtype=np.float32))
        self.vmax = mi.Float(np.asarray(vmax, dtype=np.float32))
        self.list_offset = mi.UInt32(tree.list_offset)
        self.list_count = mi.UInt32(tree.list_count)
        self.items = mi.UInt32(tree.items if len(tree.items) else np.zeros(1, np.uint32))
        self.depth = mi.UInt32(tree.depth + 1)
        self.majorant = mi.Float(np.zeros(tree.n_leaves, np.float32) if majorant is None
                                 else np.asarray(majorant, dtype=np.float32))
        dr.make_opaque(self.axis, self.split, self.child, self.leaf_lo, self.leaf_hi,
                       self.vmin, self.vmax, self.list_offset, self.list_count, self.items,
                       self.depth, self.majorant)

    @property
    def n_leaves(self) -> int:
        return self.host.n_leaves

    def update_majorants(self, tf, density_scale):
        self.majorant = density_scale * tf.range_max_alpha(self.vmin, self.vmax)
        dr.make_opaque(self.majorant)

    @dr.syntax
    def locate(self, p: mi.Vector3f, d: mi.Vector3f, active=True):
        """Leaf containing ``p``; on a split plane, the side ``d`` points to
        (the upper side when ``d`` lies in the plane, as cells are half-open
        ``[lo, hi)`` and the point look-up takes that side too)."""
        node = mi.UInt32(0)
        axis = dr.gather(mi.UInt32, self.axis, node, active)
        i = mi.UInt32(0)
        while dr.hint(mi.Bool(active) & (axis < 3) & (i < self.depth), label="amr_kd_locate"):
            s = dr.gather(mi.Float, self.split, node)
            pa = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
            da = dr.select(axis == 0, d.x, dr.select(axis == 1, d.y, d.z))
            right = (pa > s) | ((pa == s) & (da >= 0))
            node = dr.gather(mi.UInt32, self.child, node) + dr.select(right, 1, 0)
            axis = dr.gather(mi.UInt32, self.axis, node)
            i += 1
        return dr.gather(mi.UInt32, self.child, node, active)


class TreeSegments:
    """Front-to-back leaves of a `DeviceTree` (kd-restart)."""

    def __init__(self, tree: DeviceTree):
        self.tree = tree

    def max_steps(self):
        return mi.UInt32(self.tree.n_leaves + 2)

    def begin(self, o, d, t_lo, t_hi, active):
        return (mi.Float(t_lo),)

    def advance(self, o, d, state, t_hi, active):
        (t_cell,) = state
        tree = self.tree
        valid = mi.Bool(active) & (t_cell < t_hi)
        p = o + d * t_cell
        leaf = tree.locate(p, d, valid)
        lo = dr.gather(mi.Vector3f, tree.leaf_lo, leaf, valid)
        hi = dr.gather(mi.Vector3f, tree.leaf_hi, leaf, valid)
        far = dr.select(d >= 0, hi, lo)
        t_exit = dr.min((far - o) * safe_rcp(d))
        # progress guard: p rounded to before the plane re-finds the same
        # leaf; step a few ulps of t, or 1e-7 of the time to cross the cube
        t_min = t_cell + dr.maximum(dr.abs(t_cell) * 5e-7, 1e-7 * dr.rcp(dr.max(dr.abs(d))))
        t1 = dr.minimum(dr.maximum(t_exit, t_min), t_hi)
        mu = dr.gather(mi.Float, tree.majorant, leaf, valid)
        t0 = t_cell
        t_cell = dr.select(valid, t1, t_cell)
        return (t_cell,), t0, t1, mu, valid
