"""A per-lane random number stream for the symbolic loops.

Dr.Jit records a symbolic loop a second time when its state holds a
variable the body leaves unchanged, and every loop nested inside is then
recorded twice as well (docs/design.md section 6). A Mitsuba sampler's
state keeps such a variable (its stream increment), so a loop that carries
the sampler is always recorded twice. The tracking and shadow-ray loops
carry an `Rng` instead, and so does the path loop of ``amrvolpath`` when
the sampler is Mitsuba's ``independent`` one (which draws from PCG32 too).
An `Rng` is PCG32 (O'Neill 2014) on one fixed stream, with the 64-bit state
as its only variable, which every draw changes. Each stream is seeded from
two of the sampler's dimensions (or from a parent stream), so images stay a
function of the sampler's seed.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core.jit_struct import jit_struct

_MULT = 0x5851F42D4C957F2D       # PCG32's LCG multiplier
_INC = 0x14057B7EF767814F        # one fixed (odd) stream increment


def _mix64(z):
    """SplitMix64's finaliser: spreads a few seed bits over all 64."""
    z = (z ^ (z >> 30)) * mi.UInt64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> 27)) * mi.UInt64(0x94D049BB133111EB)
    return z ^ (z >> 31)


@jit_struct(state="UInt64")
class Rng:
    """PCG32 stream per lane; ``next_1d`` has the signature of
    ``mi.Sampler.next_1d``, so tracking code takes either."""

    def __init__(self, state=None):
        self.state = state

    @staticmethod
    def derive(source, active=True) -> "Rng":
        """A new stream seeded from ``source``: a Mitsuba sampler (two of
        its dimensions, 48 bits) or another `Rng` (one step of it)."""
        if isinstance(source, Rng):
            return Rng(_mix64(source.next_u64(active)))
        hi = mi.UInt64(mi.UInt32(source.next_1d(active) * 16777216.0))
        lo = mi.UInt64(mi.UInt32(source.next_1d(active) * 16777216.0))
        return Rng(_mix64((hi << 24) | lo))

    def mixed(self, bits) -> "Rng":
        """This stream's state mixed with 64 further ``bits`` per lane (a
        hash: lanes whose states agree but whose bits differ part)."""
        return Rng(_mix64(self.state ^ bits))

    def next_u32(self, active=True):
        """32 random bits; the state advances on active lanes."""
        old = self.state
        self.state = dr.select(active, old * mi.UInt64(_MULT) + mi.UInt64(_INC), old)
        xorshifted = mi.UInt32(((old >> 18) ^ old) >> 27)
        rot = mi.UInt32(old >> 59)
        return (xorshifted >> rot) | (xorshifted << ((0 - rot) & 31))

    def next_u64(self, active=True):
        hi = mi.UInt64(self.next_u32(active))
        return (hi << 32) | mi.UInt64(self.next_u32(active))

    def next_1d(self, active=True):
        """Uniform float in [0, 1) (23 random mantissa bits)."""
        bits = (self.next_u32(active) >> 9) | 0x3F800000
        return dr.reinterpret_array(mi.Float, bits) - 1.0

    def next_2d(self, active=True):
        """Uniform point in [0, 1)^2, as ``mi.Sampler.next_2d``."""
        x = self.next_1d(active)
        return mi.Point2f(x, self.next_1d(active))
