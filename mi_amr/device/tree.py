"""kd-trees (region trees and the SAH kd-tree) in Dr.Jit, in local coordinates."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .grid import MINORANT_SHRINK
from ..core.jit_struct import jit_struct


@jit_struct(axis="UInt32", split="Float", child="UInt32", leaf_lo="Vector3f", leaf_hi="Vector3f",
            vmin="Float", vmax="Float", list_offset="UInt32", list_count="UInt32", items="UInt32",
            depth="UInt32", majorant="Float", minorant="Float", finest_level="UInt32")
class DeviceTree:
    """A `RegionTree` (or SAH kd-tree) in Dr.Jit, in local coordinates.

    ``to_local(x) = (x - lo) * scale`` maps the tree's host units to the unit
    cube. Leaves carry value ranges (``vmin``/``vmax``), majorants and
    minorants, and the finest level whose cells reach them
    (``finest_level``: the ray marcher's step, docs/design.md section 14;
    0, the finest possible, where the builder gave none).
    """

    def __init__(self, tree, lo, scale, vmin, vmax, majorant=None, finest_level=None):
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
        self.minorant = dr.zeros(mi.Float, tree.n_leaves)
        self.finest_level = mi.UInt32(np.zeros(tree.n_leaves, np.uint32) if finest_level is None
                                      else np.asarray(finest_level, dtype=np.uint32))
        dr.make_opaque(self.axis, self.split, self.child, self.leaf_lo, self.leaf_hi,
                       self.vmin, self.vmax, self.list_offset, self.list_count, self.items,
                       self.depth, self.majorant, self.minorant, self.finest_level)

    @property
    def n_leaves(self) -> int:
        return self.host.n_leaves

    def update_majorants(self, tf, density_scale, minorants: bool = True):
        """Leaf majorants and minorants from the value ranges (minorants 0
        unless ``minorants``; see `DeviceMacrocellGrid.update_majorants`)."""
        self.majorant = density_scale * tf.range_max_alpha(self.vmin, self.vmax)
        self.minorant = ((density_scale * MINORANT_SHRINK) * tf.range_min_alpha(self.vmin, self.vmax)
                         if minorants else dr.zeros(mi.Float, self.n_leaves))
        dr.make_opaque(self.majorant, self.minorant)

    @dr.syntax
    def locate(self, p: mi.Vector3f, d: mi.Vector3f, active=True):
        """Leaf containing ``p``; on a split plane, the side ``d`` points to
        (the upper side when ``d`` lies in the plane, as cells are half-open
        ``[lo, hi)`` and the point look-up takes that side too)."""
        node = mi.UInt32(0)
        axis = dr.gather(mi.UInt32, self.axis, node, active)
        i = mi.UInt32(0)
        while dr.hint(mi.Bool(active) & (axis < 3) & (i < self.depth), label="amr_kd_locate",
                      exclude=[self, p, d, active]):
            s = dr.gather(mi.Float, self.split, node)
            pa = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
            da = dr.select(axis == 0, d.x, dr.select(axis == 1, d.y, d.z))
            right = (pa > s) | ((pa == s) & (da >= 0))
            node = dr.gather(mi.UInt32, self.child, node) + dr.select(right, 1, 0)
            axis = dr.gather(mi.UInt32, self.axis, node)
            i += 1
        return dr.gather(mi.UInt32, self.child, node, active)
