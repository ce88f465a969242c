"""Ray helpers in Dr.Jit: safe reciprocals, tiny-component flushing, unit-cube slab test.

Coordinates are the medium's *local* space: the AMR bounding box is the unit
cube ``[0, 1]^3``. Rays are given by origin ``o`` and (not necessarily unit)
direction ``d`` in that space, with the same ray parameter ``t`` as in world
space. The grid walk itself is `mi_amr.device.segments.GridSegments`.
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


#: Direction components below this fraction of the largest one are flushed to 0.
FLUSH_REL = 1e-12


def flush_tiny(d: mi.Vector3f) -> mi.Vector3f:
    """``d`` with components below `FLUSH_REL` times its largest one set to
    exactly 0.

    Such a component moves the point by less than 1e-12 of the unit cube
    while the ray crosses it, which float32 cannot resolve away from 0: the
    look-ups would stay on a face the traversal has already left. Treated
    as parallel, the ray's traversal, majorants and density look-ups agree
    on which side of a face it runs (the upper one, as cells are ``[lo, hi)``).
    """
    return dr.select(dr.abs(d) < FLUSH_REL * dr.max(dr.abs(d)), 0.0, d)


def intersect_unit_cube(o: mi.Vector3f, inv_d: mi.Vector3f):
    """Slab test against ``[0, 1]^3``: ``(hit, t0, t1)``."""
    ta = (0.0 - o) * inv_d
    tb = (1.0 - o) * inv_d
    t0 = dr.max(dr.minimum(ta, tb))
    t1 = dr.min(dr.maximum(ta, tb))
    return (t0 <= t1) & dr.isfinite(t0) & dr.isfinite(t1), t0, t1


def clip_to_half_space(o: mi.Vector3f, d: mi.Vector3f, t_lo, t_hi, normal: mi.Vector3f, offset):
    """``(t_lo, t_hi)`` of the ray ``o + t d`` kept where ``normal . x <=
    offset`` (a half-space, local coordinates): the interval narrowed to
    the plane's side, empty (``t_hi < t_lo``) where the ray lies wholly
    outside. ``normal = 0``, ``offset >= 0`` keeps everything."""
    nd, no = dr.dot(normal, d), dr.dot(normal, o)
    t_plane = (offset - no) * dr.rcp(dr.select(nd == 0.0, 1.0, nd))
    t_lo = dr.select(nd < 0.0, dr.maximum(t_lo, t_plane), t_lo)
    t_hi = dr.select(nd > 0.0, dr.minimum(t_hi, t_plane), t_hi)
    return t_lo, dr.select((nd == 0.0) & (no > offset), -dr.inf, t_hi)


def in_unit_cube(u: mi.Vector3f) -> mi.Bool:
    """Whether local points ``u`` lie in the closed unit cube (the data bounds)."""
    return dr.all((u >= 0.0) & (u <= 1.0))
