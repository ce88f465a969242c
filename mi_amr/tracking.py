"""Ray traversal of the macrocell grid (Dr.Jit).

Coordinates are the medium's *local* space: the AMR bounding box is the unit
cube ``[0, 1]^3``. Rays are given by origin ``o`` and (not necessarily unit)
direction ``d`` in that space, with the same ray parameter ``t`` as in world
space.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Direction components smaller than this are treated as this (same sign),
#: so that reciprocals stay finite in float32.
MIN_DIR = 1e-20


def safe_rcp(d: mi.Vector3f) -> mi.Vector3f:
    """Componentwise ``1 / d`` that stays finite for zero components."""
    tiny = dr.abs(d) < MIN_DIR
    d = dr.select(tiny, dr.select(d < 0, -MIN_DIR, MIN_DIR), d)
    return dr.rcp(d)


def intersect_unit_cube(o: mi.Vector3f, inv_d: mi.Vector3f):
    """Slab test against ``[0, 1]^3``: ``(hit, t0, t1)``."""
    ta = (0.0 - o) * inv_d
    tb = (1.0 - o) * inv_d
    t0 = dr.max(dr.minimum(ta, tb))
    t1 = dr.min(dr.maximum(ta, tb))
    return (t0 <= t1) & dr.isfinite(t0) & dr.isfinite(t1), t0, t1


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

    @dr.syntax
    def ray_majorant(self, o: mi.Vector3f, d: mi.Vector3f, t_start, t_end, active=True):
        """Walk the grid along ``o + t d`` over ``[t_start, t_end]`` (3D DDA,
        Amanatides-Woo) and return ``(found, t_first, t_last, mu_max)``: the
        span from the entry of the first to the exit of the last macrocell
        with a non-zero majorant, and the largest majorant met. At most
        ``rx + ry + rz + 3`` steps (a ray crosses at most ``rx + ry + rz - 2``)."""
        res_f = mi.Vector3f(self.res)
        dg = d * res_f                               # direction in grid units
        inv = safe_rcp(dg)
        p = (o + d * t_start) * res_f
        cell = dr.clip(mi.Vector3i(dr.floor(p)), 0, self.res - 1)
        step = dr.select(dg >= 0, 1, -1)
        edge = mi.Vector3f(cell) + dr.select(dg >= 0, 1.0, 0.0)
        t_next = t_start + (edge - p) * inv
        dt = dr.abs(inv)
        t_cell = mi.Float(t_start)
        found = mi.Bool(False)
        t_first = mi.Float(t_end)
        t_last = mi.Float(t_start)
        mu_max = mi.Float(0.0)
        i = mi.UInt32(0)
        n_max = mi.UInt32(self.res.x + self.res.y + self.res.z + 3)
        alive = mi.Bool(active) & (t_start < t_end)
        while dr.hint(alive, label="amr_ray_majorant"):
            t_exit = dr.minimum(dr.min(t_next), t_end)
            mu = dr.gather(mi.Float, self.majorant, self.flat(cell), alive)
            nonzero = mu > 0.0
            t_first = dr.select(nonzero & ~found, t_cell, t_first)
            t_last = dr.select(nonzero, t_exit, t_last)
            mu_max = dr.maximum(mu_max, mu)
            found |= nonzero
            # step along the axis whose boundary comes first
            ax_x = (t_next.x <= t_next.y) & (t_next.x <= t_next.z)
            ax_y = ~ax_x & (t_next.y <= t_next.z)
            ax_z = ~ax_x & ~ax_y
            cell.x = dr.select(ax_x, cell.x + step.x, cell.x)
            cell.y = dr.select(ax_y, cell.y + step.y, cell.y)
            cell.z = dr.select(ax_z, cell.z + step.z, cell.z)
            t_next.x = dr.select(ax_x, t_next.x + dt.x, t_next.x)
            t_next.y = dr.select(ax_y, t_next.y + dt.y, t_next.y)
            t_next.z = dr.select(ax_z, t_next.z + dt.z, t_next.z)
            t_cell = t_exit
            i += 1
            alive &= (t_exit < t_end) & dr.all((cell >= 0) & (cell < self.res)) & (i < n_max)
        return found, t_first, t_last, mu_max
