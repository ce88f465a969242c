"""The isosurface search as a consumer of the one segment walk
(docs/design.md section 15).

`IsoSearch` plugs into `mi_amr.device.tracking.walk_segments` like the
tracking estimators and the ray marcher (hooks ``begin``, ``enter``,
``clock``, ``passes``, ``collide_at``, ``result``), over a walker made with
``levels=True, ranges=True``: each segment carries its leaf's value range
``[vmin, vmax]`` and the finest level under it. What it does with a
segment ``[t0, t1]`` (local ``t``):

* no iso value in ``[vmin, vmax]`` (widened by the value tolerance): the
  reconstruction takes no iso value there, so the surface is not there;
  no look-up, on to the next segment (the analogue of a zero majorant).
  Its values all lie on one side of every iso value, so ``vmin`` stands
  for them in the sign tests, as the last sample up to its end: a jump
  across an iso value at the face between two such leaves (the surface of
  a piecewise-constant field lies on faces) makes the next leaf walked;
* otherwise the field is sampled front to back at step ends at most
  `ISO_STEP_CELLS` cells of the segment's finest level apart (for a
  field constant per cell, ``exact``: steps from face to face of the
  lattice of the segment's finest cells, each in one cell, sampled at its
  midpoint, and a crossing is the face between two samples, found
  exactly without bisection; the step
  ends on ``t1``, so that a run of candidate segments shares its samples;
  a ray's first walked leaf samples its own start first); between two samples whose values lie on both sides of an iso
  value (``(f_a - iso) (f_b - iso) <= 0``) the surface is bracketed: of
  several iso values crossed, the one nearest ``f_a`` (the first crossed
  where ``f`` is monotone in the step);
* the bracket is refined by bisection until ``|f - iso|`` is within the
  value tolerance or `ISO_BISECTIONS` halvings, and the hit is the secant
  (linear) root of the last bracket; the lane stops there, unless the
  root lies within `ISO_SELF_CELLS` of the ray's start: that is the surface
  a ray leaves (a path's next ray, a shadow ray), and the search goes on.

Iso values are the slots of one opaque array of `MAX_ISO_VALUES` floats;
unused slots hold NaN, which no comparison accepts, so the number of
values changes no kernel. A point with no value (a hole in the data) is
NaN too: no bracket reaches across it. The tent reconstruction is
continuous across level boundaries, so the surface found has no cracks
there; nearest reconstruction is piecewise constant, and its "surface" is
made of cell faces (the bracket closes on the face where the value
jumps across the iso value).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .marching import lattice_exit
from .segments import direction_guard
from .tracking import TrackingCounts, WalkEnd, _Fields, _counted, _counter, _tally
from ..core.jit_struct import jit_struct

#: Iso values a medium holds at once (slots of one opaque array).
MAX_ISO_VALUES = 4
#: The search's step, in cells of the finest level under the segment.
ISO_STEP_CELLS = 0.5
#: Most bisections of one bracket (each halves it: 2^-20 of a step).
ISO_BISECTIONS = 20
#: The value tolerance of a hit, as a share of the data's value range.
ISO_VALUE_TOLERANCE = 1e-5
#: A root closer than this to the ray's start (finest cells) is the surface
#: the ray leaves (a path's next ray, a shadow ray from the surface): not a hit.
ISO_SELF_CELLS = 1e-3


@jit_struct(a="Float", fa="Float", e="Float", b="Float", w="Float", candidate="Bool", fresh="Bool",
            t_hit="Float", slot="UInt32", hit="Bool", lookups="UInt32", steps="UInt32")
class IsoState(_Fields):
    """Loop state of `IsoSearch`: the last sample's local ``t`` (``a``) and
    value (``fa``, NaN where unknown), where the last step ended (``e``)
    and where the current one ends (``b``; cell steps), the segment's
    lattice width ``w`` (finest cells), whether the segment is walked
    (``candidate``) and whether its first sample is still to take
    (``fresh``); the hit found (``t_hit`` local, the iso slot); counts."""


@jit_struct(t="Float", found="Bool", slot="UInt32", counts=TrackingCounts)
class IsoFound(_Fields):
    """The first isosurface crossing along a local ray: ``t`` (local; inf
    where none was ``found``), the slot of its iso value, and the counts
    (``lookups``: field look-ups, ``steps``: segments entered)."""


class IsoSearch:
    """The isosurface search (see the module docstring). ``value_at(u,
    active) -> value`` at local points (NaN where there is none);
    ``iso``: the `MAX_ISO_VALUES` slots (opaque ``Float``, NaN unused);
    ``tolerance``: the value tolerance (opaque ``Float``, value units);
    ``extent``: the data box in finest cells (the lattice); ``exact``:
    the field is constant per cell (``nearest``), stepped face to face."""

    label = "amr_iso"
    MOVING = ("a", "fa", "e", "b", "w", "candidate", "fresh", "steps")

    def __init__(self, value_at, iso, tolerance, extent, count: bool = True, exact: bool = False, offset=None):
        self.value_at, self.iso, self.tolerance, self.extent = value_at, iso, tolerance, extent
        self.count = count
        #: piecewise-constant field (``nearest``): steps from face to face of
        #: the segment's lattice, each sampled at its midpoint (one cell each);
        #: a crossing is the face between two samples ("offset": the data
        #: box's corner relative to the cells' alignment origin)
        self.exact, self.offset = exact, offset
        self.slots = [dr.gather(mi.Float, iso, mi.UInt32(k)) for k in range(MAX_ISO_VALUES)]

    def begin(self, ray, active):
        # per ray: finest cells per local t, and the smallest step
        self.cells_per_t = dr.norm(ray.d * self.extent)
        self.guard = direction_guard(ray.d)
        n = self.count
        return IsoState(a=mi.Float(ray.t_lo), fa=mi.Float(dr.nan), e=mi.Float(ray.t_lo), b=mi.Float(ray.t_lo),
                        w=mi.Float(1.0), candidate=mi.Bool(False),
                        fresh=mi.Bool(True), t_hit=mi.Float(dr.inf), slot=mi.UInt32(0), hit=mi.Bool(False),
                        lookups=_counter(n), steps=_counter(n))

    def holds_iso(self, vmin, vmax):
        """Whether some iso value lies in ``[vmin, vmax]`` (widened by the tolerance)."""
        inside = mi.Bool(False)
        for iso in self.slots:
            inside |= (iso >= vmin - self.tolerance) & (iso <= vmax + self.tolerance)
        return inside

    def enter(self, state, ray, seg, entered, t, seg_end):
        """A new segment: is it walked with look-ups, and what is known at its start?

        A leaf whose range holds no iso value has all its values on one
        side of every iso value, so any of them (``vmin``) stands for all of
        them in the sign tests: it becomes the last "sample" up to the
        leaf's end, without a look-up. A leaf is walked where its range
        holds an iso value, or where that stand-in and the last sample lie
        on both sides of one (a jump across the iso value at the face
        between two leaves: a piecewise-constant field's surface lies on
        faces)."""
        candidate = self.holds_iso(seg.vmin, seg.vmax)
        known = ~state.fresh & (state.e == t)            # the last sample (or stand-in) reaches this start
        stand_in = dr.select(seg.vmin <= seg.vmax, seg.vmin, dr.nan)      # NaN: a leaf with no cells
        jumped = self._crossing(state.fa, stand_in)[0] & known
        walked = candidate | jumped
        skipped = entered & ~walked
        state.fresh = dr.select(entered, dr.select(walked, ~known, dr.isnan(stand_in)), state.fresh)
        state.fa = dr.select(skipped, stand_in, state.fa)
        state.candidate = dr.select(entered, walked, state.candidate)
        state.a = dr.select(skipped, seg_end, state.a)
        state.e = dr.select(entered, dr.select(walked, t, seg_end), state.e)
        state.w = dr.select(entered, mi.Float(mi.UInt32(1) << dr.minimum(seg.level, 30)), state.w)
        state.steps = _tally(state.steps, dr.select(entered, 1, 0))
        return state

    def clock(self, state, ray, t, seg_end, moving):
        """The next sample of lanes ``moving`` in a walked segment: its
        start first (``fresh``), then step ends up to ``seg_end``; cell
        steps (``exact``) are sampled at their midpoints."""
        go = moving & state.candidate & (state.e < seg_end)
        if self.exact:
            b = lattice_exit(ray, state.e, state.w, seg_end, self.extent, self.offset, self.guard)
            state.b = dr.select(go, b, state.b)
            return state, 0.5 * (state.e + b), go
        step = dr.maximum(ISO_STEP_CELLS * state.w * dr.rcp(dr.maximum(self.cells_per_t, 1e-30)), self.guard)
        b = dr.select(state.fresh, state.e, dr.minimum(state.e + step, seg_end))
        return state, b, go

    def passes(self, state, alive):
        return alive

    def _crossing(self, fa, fb):
        """``(crossed, slot, iso)``: an iso value between ``fa`` and
        ``fb`` (of several, the one nearest ``fa``)."""
        crossed, slot, iso, gap = mi.Bool(False), mi.UInt32(0), mi.Float(0.0), mi.Float(dr.inf)
        for k, value in enumerate(self.slots):
            here = ((fa - value) * (fb - value) <= 0.0) & (dr.abs(fa - value) < gap)
            crossed |= here
            slot = dr.select(here, k, slot)
            iso = dr.select(here, value, iso)
            gap = dr.select(here, dr.abs(fa - value), gap)
        return crossed, slot, iso

    @dr.syntax
    def collide_at(self, state, ray, t_b, inside, alive):
        """Sample lanes ``inside`` at ``t_b``; where the iso value is crossed
        since the last sample, refine the bracket and stop the lane there."""
        value_at = self.value_at
        fb = mi.Float(dr.nan)
        if dr.hint(inside, exclude=[value_at]):
            fb = value_at(ray.o + ray.d * t_b, inside)
        state.lookups = _tally(state.lookups, dr.select(inside, 1, 0))
        crossed, slot, iso = self._crossing(state.fa, fb)
        crossed &= inside & (self.exact | ~state.fresh)
        if dr.hint(self.exact, mode="scalar"):
            # a cell step lies in one cell: the value jumps on the face where it began
            return self._found(state, ray, t_b, inside, alive, fb, crossed, slot, state.e)
        # ---- bisection of [lo, hi], g = f - iso on both sides ----
        lo, hi = mi.Float(state.a), mi.Float(t_b)
        g_lo, g_hi = state.fa - iso, fb - iso
        k = mi.UInt32(0)
        refining = crossed & (dr.abs(g_hi) > self.tolerance) & (dr.abs(g_lo) > self.tolerance)
        while dr.hint(refining, exclude=[value_at]):
            mid = 0.5 * (lo + hi)
            g_mid = value_at(ray.o + ray.d * mid, refining) - iso
            left = g_lo * g_mid <= 0.0                       # the root lies in [lo, mid]
            hi = dr.select(left, mid, hi)
            g_hi = dr.select(left, g_mid, g_hi)
            lo = dr.select(left, lo, mid)
            g_lo = dr.select(left, g_lo, g_mid)
            k += 1
            refining &= (k < ISO_BISECTIONS) & (dr.abs(g_mid) > self.tolerance)
        state.lookups = _tally(state.lookups, k)
        # the secant root of the last bracket (an end that meets the tolerance is it)
        share = dr.select(g_lo != g_hi, g_lo * dr.rcp(g_lo - g_hi), 0.5)
        t_root = lo + dr.clip(share, 0.0, 1.0) * (hi - lo)
        t_root = dr.select(dr.abs(g_lo) <= self.tolerance, lo, dr.select(dr.abs(g_hi) <= self.tolerance, hi, t_root))
        return self._found(state, ray, t_b, inside, alive, fb, crossed, slot, t_root)

    def _found(self, state, ray, t_b, inside, alive, fb, crossed, slot, t_root):
        """Lanes ``crossed`` end at ``t_root`` (but for the surface a ray
        starts on, which is no hit: its search goes on); the others take
        the sample ``fb`` at ``t_b`` as the last one."""
        crossed &= t_root > ray.t_lo + ISO_SELF_CELLS * dr.rcp(dr.maximum(self.cells_per_t, 1e-30))
        state.t_hit = dr.select(crossed, t_root, state.t_hit)
        state.slot = dr.select(crossed, slot, state.slot)
        state.hit |= crossed
        state.fa = dr.select(inside, fb, state.fa)
        state.a = dr.select(inside, t_b, state.a)
        state.e = dr.select(inside, state.b if self.exact else t_b, state.e)
        state.fresh &= ~inside
        return state, alive & ~crossed

    def result(self, state, ray, end: WalkEnd) -> IsoFound:
        counts = TrackingCounts(_counted(state.lookups), mi.UInt32(0), mi.UInt32(dr.select(state.hit, 1, 0)),
                                _counted(state.steps), dr.select(end.exhausted, 1, 0))
        return IsoFound(t=dr.select(state.hit, state.t_hit, dr.inf), found=mi.Bool(state.hit), slot=state.slot,
                        counts=counts)


@jit_struct(t="Float", found="Bool", p="Point3f", n="Vector3f", slot="UInt32", counts=TrackingCounts)
class IsoHit(_Fields):
    """An isosurface hit in world space (`AMRMedium.iso_hit`): the ray's
    ``t`` (inf where none was ``found``), the point, the unit normal (the
    reconstruction's gradient, turned towards lower values), the iso slot
    and the search's counts."""


def central_gradient(value_at, u, eps, active):
    """The gradient of ``value_at`` at local points ``u`` by central
    differences over ``eps`` local units per axis (six look-ups); NaN
    where a look-up found no value."""
    g = []
    for axis in range(3):
        e = mi.Vector3f(*[eps if k == axis else 0.0 for k in range(3)])
        g.append((value_at(u + e, active) - value_at(u - e, active)) * dr.rcp(2.0 * eps))
    return mi.Vector3f(*g)
