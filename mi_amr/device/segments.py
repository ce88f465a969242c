"""Ray traversal in Dr.Jit: segments ``[t0, t1]`` with a majorant each.

All structures live in the medium's local space (the data bounds are the
unit cube). A *segment iterator* has two methods used inside symbolic loops:

* ``begin(o, d, t_lo, t_hi, active) -> (state, fixed)``: ``state``, a tuple
  of the Dr.Jit arrays that every step changes (the loop state), and
  ``fixed``, per-ray constants of the walk (kept out of the loop state: a
  loop carrying an unchanged variable is recorded twice, docs/design.md
  section 6)
* ``advance(o, d, state, fixed, t_hi, active) -> (state, Segment)``: the
  next segment along ``o + t d`` after the previous one; its ``valid`` is
  false once the ray has left ``[t_lo, t_hi]``.

A walker made with ``levels=True`` also reports the finest level under
each segment (``Segment.level``: the finest level whose cells' supports
reach the leaf, from the leaf's level mask or its own record; the step of
the ray marcher, docs/design.md section 14); without it ``level`` is 0 and
costs no gather. One made with ``ranges=True`` reports the range of values
the reconstruction takes in each segment's leaf (``Segment.vmin``,
``vmax``: the isosurface search skips a leaf whose range holds no iso
value, docs/design.md section 15), and walks every leaf one by one (no
empty-space cubes: a leaf empty under the TF may hold a surface);
without it both are 0.

`GridSegments` walks the macrocell grid with a 3D DDA (Amanatides-Woo);
`TwoLevelGridSegments` walks a two-level grid by locating the macrocell at
the current point (the fine one where its coarse one is refined, the cube
of empty coarse ones ahead of an empty one);
`TreeSegments` walks the leaves of a kd-tree front to back by re-descending
from the root at the current point ("kd-restart": no stack, exact ties).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
from .grid import SKIP_BITS, finest_level
from .ray import safe_rcp
from ..core.jit_struct import jit_struct
from .tree import DeviceTree


@jit_struct(t0="Float", t1="Float", mu="Float", mu_min="Float", valid="Bool", level="UInt32", vmin="Float",
            vmax="Float")
class Segment:
    """One piece ``[t0, t1]`` (local ray parameter) of a ray with majorant
    ``mu`` and minorant ``mu_min`` (inverse world units); ``valid`` is false
    past the ray's end; ``level``: the finest level under it (walkers made
    with ``levels=True``; 0 otherwise); ``vmin``, ``vmax``: the value range
    of its leaf (walkers made with ``ranges=True``; 0 otherwise)."""

    def __init__(self, t0=None, t1=None, mu=None, mu_min=None, valid=None, level=None, vmin=None, vmax=None):
        self.t0, self.t1, self.mu, self.mu_min, self.valid = t0, t1, mu, mu_min, valid
        self.level = mi.UInt32(0) if level is None else level
        self.vmin = mi.Float(0.0) if vmin is None else vmin
        self.vmax = mi.Float(0.0) if vmax is None else vmax


class GridSegments:
    """Front-to-back macrocells of a `DeviceMacrocellGrid`."""

    def __init__(self, grid, levels: bool = False, ranges: bool = False):
        self.grid = grid
        #: report each segment's finest level (`Segment.level`)
        self.levels = levels
        #: report each segment's value range (`Segment.vmin`, ``vmax``)
        self.ranges = ranges

    def leaf_bounds(self):
        """``(minorant, majorant, volume)`` per leaf on the host (numpy):
        the fine macrocells, all of one volume."""
        hi = self.grid.majorant.numpy()
        return self.grid.minorant.numpy(), hi, np.ones(len(hi))

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
        # per ray: t per macrocell along each axis, and the step direction
        return (cell, t_next, mi.Float(t_lo)), (dr.abs(inv), dr.select(dg >= 0, 1, -1))

    def advance(self, o, d, state, fixed, t_hi, active):
        g = self.grid
        cell, t_next, t_cell = state
        dt, step = fixed
        inside = dr.all((cell >= 0) & (cell < g.res))
        valid = active & inside & (t_cell < t_hi)
        t0 = t_cell
        t1 = dr.minimum(dr.min(t_next), t_hi)
        flat = g.flat(dr.clip(cell, 0, g.res - 1))
        mu = dr.gather(mi.Float, g.majorant, flat, valid)
        mu_min = dr.gather(mi.Float, g.minorant, flat, valid)
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
        level = finest_level(dr.gather(mi.UInt32, g.level_bits, flat, valid)) if self.levels else None
        vmin = vmax = None
        if self.ranges:
            vmin, vmax = dr.gather(mi.Float, g.vmin, flat, valid), dr.gather(mi.Float, g.vmax, flat, valid)
        return (cell, t_next, t_cell), Segment(t0, t1, mu, mu_min, valid, level, vmin, vmax)


def direction_guard(d):
    """The direction-only part of `progress_guard` (a per-ray constant):
    1e-7 of the time to cross the unit cube along ``d``."""
    return 1e-7 * dr.rcp(dr.max(dr.abs(d)))


def progress_guard(t, guard):
    """Smallest step along ``o + t d`` for walks that re-locate the point at
    each step: a few ulps of ``t``, or ``guard = direction_guard(d)``. A
    point rounded back onto the face it just left still moves on."""
    return dr.maximum(dr.abs(t) * 5e-7, guard)


class TwoLevelGridSegments(GridSegments):
    """Front-to-back macrocells of a `DeviceTwoLevelGrid`: at each step the
    fine macrocell just past the current point is located; where its coarse
    macrocell is refined, the segment is the fine macrocell, otherwise the
    whole coarse one, or, where that is empty, the cube of empty coarse
    macrocells that stretches from it along the ray's octant
    (``coarse_skip``). The exit is measured from the
    located point, so every step moves forward. Its leaves are the fine
    macrocells, as `GridSegments`' (``leaf_bounds``)."""

    def max_steps(self):
        g = self.grid
        return g.res.x + g.res.y + g.res.z + g.coarse_res.x + g.coarse_res.y + g.coarse_res.z + 3

    def begin(self, o, d, t_lo, t_hi, active):
        res_f = mi.Vector3f(self.grid.res)
        # per ray: t per fine macrocell width along each axis, the
        # direction-only part of the progress guard, and where the ray's
        # octant sits in a ``coarse_skip`` word
        octant = dr.select(d.x < 0.0, 1, 0) | dr.select(d.y < 0.0, 2, 0) | dr.select(d.z < 0.0, 4, 0)
        return (mi.Float(t_lo),), (safe_rcp(d * res_f), direction_guard(d), mi.UInt32(octant) * SKIP_BITS)

    def advance(self, o, d, state, fixed, t_hi, active):
        (t_cell,) = state
        inv, guard, octant_shift = fixed
        g = self.grid
        valid = mi.Bool(active) & (t_cell < t_hi)
        res_f = mi.Vector3f(g.res)
        t_at = t_cell + progress_guard(t_cell, guard)
        p = (o + d * t_at) * res_f                          # fine macrocell units
        cell = dr.clip(mi.Vector3i(dr.floor(p)), 0, g.res - 1)
        coarse = cell >> g.log2f
        cflat = coarse.x + g.coarse_res.x * (coarse.y + g.coarse_res.y * coarse.z)
        mu_c = dr.gather(mi.Float, g.coarse_mu, mi.UInt32(cflat), valid)
        refined = valid & (mu_c < 0.0)
        fflat = g.flat(cell)
        mu_f = dr.gather(mi.Float, g.fine.majorant, fflat, refined)
        mu_min = dr.select(refined, dr.gather(mi.Float, g.fine.minorant, fflat, refined),
                           dr.gather(mi.Float, g.coarse_min, mi.UInt32(cflat), valid & ~refined))
        # an empty coarse macrocell: the empty cube of edge k that stretches
        # from it along the ray's octant (k = 1: the macrocell itself)
        if self.ranges:
            k = mi.Int32(1)          # every coarse macrocell on its own: its range counts, not the TF
        else:
            word = dr.gather(mi.UInt32, g.coarse_skip, mi.UInt32(cflat), valid & ~refined)
            k = mi.Int32(1) << mi.Int32((word >> octant_shift) & ((1 << SKIP_BITS) - 1))
        lo = dr.select(refined, cell, (coarse + 1 - k) << g.log2f)
        hi = dr.select(refined, cell + 1, (coarse + k) << g.log2f)
        far = mi.Vector3f(dr.select(d >= 0, hi, lo))
        # >= t_at: a point rounded past the grid's last face (clamped) moves on too
        t_exit = t_at + dr.maximum(dr.min((far - p) * inv), 0.0)
        t1 = dr.minimum(t_exit, t_hi)
        t0 = t_cell
        t_cell = dr.select(valid, t1, t_cell)
        level = None
        if self.levels:
            level = dr.select(refined, finest_level(dr.gather(mi.UInt32, g.fine.level_bits, fflat, refined)),
                              dr.gather(mi.UInt32, g.coarse_level, mi.UInt32(cflat), valid & ~refined))
        vmin = vmax = None
        if self.ranges:
            coarse_only = valid & ~refined
            vmin = dr.select(refined, dr.gather(mi.Float, g.fine.vmin, fflat, refined),
                             dr.gather(mi.Float, g.coarse_vmin, mi.UInt32(cflat), coarse_only))
            vmax = dr.select(refined, dr.gather(mi.Float, g.fine.vmax, fflat, refined),
                             dr.gather(mi.Float, g.coarse_vmax, mi.UInt32(cflat), coarse_only))
        return (t_cell,), Segment(t0, t1, dr.select(refined, mu_f, mu_c), mu_min, valid, level, vmin, vmax)


class TreeSegments:
    """Front-to-back leaves of a `DeviceTree` (kd-restart)."""

    def __init__(self, tree: DeviceTree, levels: bool = False, ranges: bool = False):
        self.tree = tree
        #: report each segment's finest level (`Segment.level`)
        self.levels = levels
        #: report each segment's value range (`Segment.vmin`, ``vmax``)
        self.ranges = ranges

    def leaf_bounds(self):
        """``(minorant, majorant, volume)`` per leaf on the host (numpy;
        volumes in the tree's host units)."""
        t = self.tree
        return t.minorant.numpy(), t.majorant.numpy(), np.prod(t.host.leaf_hi - t.host.leaf_lo, axis=1)

    def max_steps(self):
        return mi.UInt32(self.tree.n_leaves + 2)

    def begin(self, o, d, t_lo, t_hi, active):
        # per ray: 1/d, and the direction-only part of the progress guard
        return (mi.Float(t_lo),), (safe_rcp(d), direction_guard(d))

    def advance(self, o, d, state, fixed, t_hi, active):
        (t_cell,) = state
        inv, guard = fixed
        tree = self.tree
        valid = mi.Bool(active) & (t_cell < t_hi)
        p = o + d * t_cell
        leaf = tree.locate(p, d, valid)
        lo = dr.gather(mi.Vector3f, tree.leaf_lo, leaf, valid)
        hi = dr.gather(mi.Vector3f, tree.leaf_hi, leaf, valid)
        far = dr.select(d >= 0, hi, lo)
        t_exit = dr.min((far - o) * inv)
        # progress guard: p rounded to before the plane re-finds the same leaf
        t_min = t_cell + progress_guard(t_cell, guard)
        t1 = dr.minimum(dr.maximum(t_exit, t_min), t_hi)
        mu = dr.gather(mi.Float, tree.majorant, leaf, valid)
        mu_min = dr.gather(mi.Float, tree.minorant, leaf, valid)
        t0 = t_cell
        t_cell = dr.select(valid, t1, t_cell)
        level = dr.gather(mi.UInt32, tree.finest_level, leaf, valid) if self.levels else None
        vmin = vmax = None
        if self.ranges:
            vmin, vmax = dr.gather(mi.Float, tree.vmin, leaf, valid), dr.gather(mi.Float, tree.vmax, leaf, valid)
        return (t_cell,), Segment(t0, t1, mu, mu_min, valid, level, vmin, vmax)
