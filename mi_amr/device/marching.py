"""The sci-vis ray marcher as a consumer of the one segment walk
(docs/design.md section 14).

`RayMarch` plugs into `mi_amr.device.tracking.walk_segments` like the
tracking estimators (the same hooks: ``begin``, ``enter``, ``clock``,
``passes``, ``collide_at``, ``result``), so it walks the same segments of
every traversal. What it does with a segment ``[t0, t1]`` of majorant
``mu`` and finest level ``L`` under it (`Segment.level`, width ``w = 2^L``
finest cells):

* ``mu == 0``: no sample, no look-up (the per-leaf value ranges that make
  the majorant 0 make the segment empty for any TF);
* otherwise steps ``[a, b]`` cover the segment front to back, each sampled
  once at ``x``: of length ``h = step_scale * w`` (along the ray, in finest
  cells) at ``a + jitter (b - a)``, one jitter per ray (``tent``); or, with
  ``exact`` (``nearest``: the field is constant per cell), each step lies
  in one cell, so the integral is exact up to rounding: where the sampler
  finds the leaf cell at a point (``cell_at``: the block hash), the step
  goes from where the last one ended to the far face of the cell found
  just past it, whose value it takes (one look-up per cell crossed);
  elsewhere it ends on the next face of the lattice of width ``w``, which
  holds every face of every cell under the segment (no cell there is
  finer than ``w`` and cells are aligned to their width), sampled at its
  midpoint;
* each step composites front to back with its exact absorption:
  ``alpha = 1 - exp(-sigma_t (b - a))``, ``L += T alpha E(x)``,
  ``T *= 1 - alpha``, with ``E = brightness * shading * rgb + (1 - rgb)
  L_e`` (the TF colour, the Blinn-Phong factor of `GradientShading` or 1,
  and a glowing medium's emission as `emission_absorption` adds it): Max's
  emission-absorption integral, the expectation of the
  ``emission_absorption`` mode;
* once ``T`` falls below `MARCH_RR_THRESHOLD` the ray plays Russian
  roulette (goes on with probability ``T / threshold`` carrying the
  threshold, else stops): unbiased in ``T``, and a nearly opaque ray stops.

The steps are the walk's moves (its tentative collisions), so the walk's
iteration bound bounds them too.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .rng import Rng
from .segments import direction_guard, progress_guard
from .tracking import TrackingCounts, WalkEnd, _Fields, _counted, _counter, _tally
from ..core.jit_struct import jit_struct
from ..structures.macrocell_grid import NO_LEVEL

#: Below this transmittance a marched ray plays Russian roulette.
MARCH_RR_THRESHOLD = 1e-3
#: Blinn-Phong constants of the sci-vis shading (`GradientShading`):
#: ambient and diffuse shares of the colour, specular weight and exponent.
AMBIENT, DIFFUSE, SPECULAR, SHININESS = 0.25, 0.75, 0.25, 32.0
#: A sample whose forward differences all stay within this share of its
#: value is flat (unshaded): below it they are float32 rounding.
FLAT_SHARE = 1e-5


def _ray_bits(ray):
    """64 bits of a local ray's origin and direction (a hash seed)."""
    def bits(v):
        return mi.UInt64(dr.reinterpret_array(mi.UInt32, v))
    return ((bits(ray.o.x) ^ (bits(ray.d.y) << 21) ^ (bits(ray.o.z) << 42))
            + ((bits(ray.d.x) << 11) ^ (bits(ray.o.y) << 32) ^ (bits(ray.d.z) << 53)))


def lattice_exit(ray, a, w, end, extent, offset, guard):
    """The next face of the lattice of width ``w`` (finest cells) after
    local ``t = a`` along the local ray, at most ``end``: ``extent`` and
    ``offset`` the data box in finest cells and its corner relative to the
    cells' alignment origin, ``guard`` the ray's `direction_guard`. Every
    cell of width ``>= w`` aligned to its width has its faces on it."""
    d_f = ray.d * extent
    step = progress_guard(a, guard)
    p_f = offset + extent * (ray.o + ray.d * (a + step))
    target = (dr.floor(p_f * dr.rcp(w)) + dr.select(d_f > 0.0, 1.0, 0.0)) * w
    p_a = offset + extent * (ray.o + ray.d * a)
    t_axis = dr.select(dr.abs(d_f) > 0.0, a + (target - p_a) * dr.rcp(dr.select(d_f != 0.0, d_f, 1.0)),
                       float("inf"))
    return dr.minimum(dr.maximum(dr.min(t_axis), a + step), end)


def absorbed_fraction(tau):
    """``1 - exp(-tau)`` for optical depths ``tau >= 0``, without the
    cancellation of float32 at small ``tau`` (its series there)."""
    small = tau < 1e-3
    return dr.select(small, tau * (1.0 - tau * (0.5 - tau * (1.0 / 6.0))), 1.0 - dr.exp(-tau))


@jit_struct(rng=Rng, mu="Float", a="Float", b="Float", w="Float", T="Float",
            L="UnpolarizedSpectrum", lookups="UInt32", steps="UInt32")
class MarchState(_Fields):
    """Loop state of `RayMarch`: the stream (Russian roulette), the
    segment's majorant, the current step ``[a, b]`` (local ``t``; in cell
    steps ``b`` holds the segment's end until the cell is found), the
    segment's lattice width ``w`` (finest cells), the transmittance and
    radiance so far, and the counts."""


@jit_struct(L="UnpolarizedSpectrum", T="Float", counts=TrackingCounts)
class Marched(_Fields):
    """Result of a march: the radiance ``L`` collected along the ray and
    the transmittance ``T`` past it (the background's weight); the counts'
    ``real`` is the number of steps sampled."""


class RayMarch:
    """The ray marcher (see the module docstring).

    ``lookup(u, active) -> (value, sigma_t)`` at local points (or ``(value,
    sigma_t, carried)`` with ``carries``); ``colour_of(value, active)``: the
    TF colour; ``emission_of(value, carried, active)``: ``L_e`` or None (the
    medium does not glow); ``shading(u, value, rgb, active)`` (a
    `GradientShading`: the shaded colour) or None (the TF colour as it
    is); ``cell_at(u, active) -> (value, sigma_t, level)``: the leaf cell
    containing ``u`` (its value, that value's sigma_t, its level), or
    None: with ``exact`` (``nearest``) the steps then go cell by cell;
    ``extent``, ``offset``: the data box in finest cells and its lower
    corner relative to the cells' alignment origin (the lattices);
    ``step_scale``: the step in cells of the segment's finest level
    (``tent``); ``brightness``: the colour's factor; ``sampler`` seeds the
    jitter and the roulette."""

    label = "amr_march"
    MOVING = ("mu", "a", "b", "w", "steps")

    def __init__(self, lookup, colour_of, sampler, extent, offset, step_scale, brightness, exact: bool,
                 emission_of=None, shading=None, carries: bool = False, count: bool = True, cell_at=None):
        self.lookup, self.colour_of, self.sampler = lookup, colour_of, sampler
        self.extent, self.offset = extent, offset
        self.step_scale, self.brightness, self.exact = step_scale, brightness, exact
        self.emission_of, self.shading, self.carries, self.count = emission_of, shading, carries, count
        self.cell_at = cell_at
        #: exact steps cell by cell: each from where the last ended to the
        #: far face of the cell found there (nearest, with `cell_at`)
        self.by_cell = exact and cell_at is not None

    def begin(self, ray, active):
        # the stream from the sampler and the ray itself: a sampler that
        # repeats its numbers over pixels (stratified without jitter: yt's
        # pixel-centre rays) still gives each ray its own jitter
        rng = Rng.derive(self.sampler, active).mixed(_ray_bits(ray))
        # per ray: the jitter of every step's sample, finest cells per local
        # t, and the progress guard of a point just past a face
        self.jitter = mi.Float(0.5) if self.exact else rng.next_1d(active)
        self.cells_per_t = dr.norm(ray.d * self.extent)
        self.guard = direction_guard(ray.d)
        n = self.count
        return MarchState(rng=rng, mu=mi.Float(0.0), a=mi.Float(0.0), b=mi.Float(0.0), w=mi.Float(1.0),
                          T=mi.Float(1.0), L=dr.zeros(mi.UnpolarizedSpectrum),
                          lookups=_counter(n), steps=_counter(n))

    def enter(self, state, ray, seg, entered, t, seg_end):
        """A new segment: its majorant and its lattice width ``2^level``."""
        w = mi.Float(mi.UInt32(1) << dr.minimum(seg.level, 30))
        state.mu = dr.select(entered, seg.mu, state.mu)
        state.w = dr.select(entered, w, state.w)
        state.a = dr.select(entered, t, state.a)
        state.b = dr.select(entered, t, state.b)
        state.steps = _tally(state.steps, dr.select(entered, 1, 0))
        return state

    def _lattice_exit(self, ray, a, w, end):
        """The next face of the lattice of width ``w`` after ``a`` (`lattice_exit`)."""
        return lattice_exit(ray, a, w, end, self.extent, self.offset, self.guard)

    def clock(self, state, ray, t, seg_end, moving):
        """The next step ``[a, b]`` of lanes ``moving`` and its sample
        ``t_c``; none in an empty segment or past its end. A cell step
        samples just past ``a`` and finds its end there (`collide_at`)."""
        go = moving & (state.mu > 0.0) & (state.a < seg_end)
        if self.by_cell:
            b = mi.Float(seg_end)
        elif self.exact:
            b = self._lattice_exit(ray, state.a, state.w, seg_end)
        else:
            b = dr.minimum(state.a + self.step_scale * state.w * dr.rcp(dr.maximum(self.cells_per_t, 1e-30)),
                           seg_end)
        state.b = dr.select(go, b, state.b)
        if self.by_cell:
            t_c = dr.minimum(state.a + progress_guard(state.a, self.guard), 0.5 * (state.a + state.b))
        else:
            t_c = state.a + self.jitter * (state.b - state.a)
        return state, t_c, go & (state.b > state.a)

    def passes(self, state, alive):
        return alive & (state.T > 0.0)

    @dr.syntax
    def collide_at(self, state, ray, t_c, inside, alive):
        """Sample the step of lanes ``inside`` at ``t_c`` and composite it."""
        found = (mi.Float(0.0), mi.Float(0.0)) + ((mi.Float(0.0),) if self.carries else ())
        lookup, cell_at = self.lookup, self.cell_at
        x = ray.o + ray.d * t_c
        cell = (mi.Float(0.0), mi.Float(0.0), mi.UInt32(NO_LEVEL))
        if dr.hint(self.by_cell, mode="scalar"):
            if dr.hint(inside, exclude=[cell_at, x]):
                cell = cell_at(x, inside)
            found, level = cell[:2], cell[2]
            # the step ends on the far face of the cell found (the segment's
            # lattice where none was: nothing absorbs there)
            w = dr.select(level < NO_LEVEL, mi.Float(mi.UInt32(1) << dr.minimum(level, 30)), state.w)
            state.b = dr.select(inside, self._lattice_exit(ray, state.a, w, state.b), state.b)
        elif dr.hint(inside, exclude=[lookup, x]):
            found = lookup(x, inside)
        value, sigma_t = found[0], found[1]
        state.lookups = _tally(state.lookups, dr.select(inside, 1, 0))
        # alpha = 1 - exp(-sigma_t dt), dt in world units
        dt = (state.b - state.a) * dr.rcp(ray.scale)
        alpha = absorbed_fraction(dr.maximum(sigma_t, 0.0) * dt)
        seen = inside & (alpha > 0.0)
        rgb = self.colour_of(value, seen)
        emitted = rgb * self.brightness
        if self.shading is not None:
            emitted = self.shading(x, value, rgb, seen) * self.brightness
        if self.emission_of is not None:
            emitted += dr.maximum(1.0 - rgb, 0.0) * self.emission_of(value, found[2] if self.carries else None,
                                                                    seen)
        state.L = dr.select(seen, state.L + state.T * alpha * emitted, state.L)
        state.T = dr.select(inside, state.T * (1.0 - alpha), state.T)
        state.a = dr.select(inside, state.b, state.a)
        # Russian roulette once T is small: on with T = threshold w.p. T / threshold
        low = inside & (state.T < MARCH_RR_THRESHOLD)
        survive = state.rng.next_1d(low) * MARCH_RR_THRESHOLD < state.T
        state.T = dr.select(low, dr.select(survive, MARCH_RR_THRESHOLD, 0.0), state.T)
        return state, alive & (state.T > 0.0)

    def result(self, state, ray, end: WalkEnd) -> Marched:
        counts = TrackingCounts(_counted(state.lookups), mi.UInt32(0), _counted(state.lookups),
                                _counted(state.steps), dr.select(end.exhausted, 1, 0))
        return Marched(L=state.L, T=state.T, counts=counts)


class GradientShading:
    """The sci-vis shading of a sample (docs/design.md section 14):
    Blinn-Phong with the normalised gradient of the reconstruction as the
    normal (forward differences of ``value_at`` over ``eps`` local units
    per axis from the sample's own value: three look-ups more, not six),
    turned to face the viewer, one light direction ``light(x) ->
    unit vector towards the light`` (world space), no shadow rays:
    ``rgb (AMBIENT + DIFFUSE max(n.l, 0)) + SPECULAR max(n.h, 0)^SHININESS``.
    Where the gradient vanishes (every difference within `FLAT_SHARE` of
    the value) the sample is unshaded: ``rgb (AMBIENT + DIFFUSE)``. ``normal_to_world(g)``: a local-space gradient as a world
    normal (the inverse transpose of the medium's ``to_world``);
    ``view``: the world direction of the ray."""

    def __init__(self, value_at, eps, normal_to_world, light, view):
        self.value_at, self.eps, self.normal_to_world = value_at, eps, normal_to_world
        self.light, self.view = light, view

    def differences(self, x, value, active):
        """The forward differences of the value along the local axes at
        ``x``, where the reconstruction is ``value`` (a `Vector3f`)."""
        e = self.eps
        return mi.Vector3f(*[self.value_at(x + mi.Vector3f(*[e if k == axis else 0.0 for k in range(3)]), active)
                             - value for axis in range(3)])

    def __call__(self, x, value, rgb, active):
        d = self.differences(x, value, active)
        # flat: no difference above float32's rounding of the value (whose
        # noise would otherwise point the normal anywhere)
        flat = dr.max(dr.abs(d)) <= FLAT_SHARE * dr.abs(value)
        g = self.normal_to_world(d * dr.rcp(self.eps))
        length = dr.norm(g)
        flat |= ~(length > 0.0)
        n = g * dr.rcp(dr.select(flat, 1.0, length))
        v = -self.view
        n = dr.select(dr.dot(n, v) < 0.0, -n, n)              # facing the viewer
        light = self.light(x, active)
        half = dr.normalize(light + v)
        diffuse = dr.select(flat, 1.0, dr.maximum(dr.dot(n, light), 0.0))
        specular = dr.select(flat, 0.0, dr.power(dr.maximum(dr.dot(n, half), 0.0), SHININESS))
        return rgb * (AMBIENT + DIFFUSE * diffuse) + SPECULAR * specular
