"""Delta and ratio tracking through local-majorant segments
(docs/design.md section 5), in one Dr.Jit symbolic loop.

Per segment ``[t0, t1]`` with majorant ``mu``: skip it if ``mu == 0`` (no
density look-up); otherwise ``t -= ln(1 - xi) / mu`` from ``max(t, t0)``;
past ``t1`` move on to the next segment; a tentative collision at ``t`` is
real with probability ``sigma_t / mu`` (delta tracking) or multiplies the
transmittance by ``1 - sigma_t / mu`` (ratio tracking).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .structs import jit_struct


@jit_struct(lookups="UInt32", null="UInt32", real="UInt32", steps="UInt32", capped="UInt32")
class TrackingCounts:
    """Per-lane event counts of one tracking call."""

    def __init__(self, lookups=None, null=None, real=None, steps=None, capped=None):
        self.lookups = mi.UInt32(0) if lookups is None else lookups
        self.null = mi.UInt32(0) if null is None else null
        self.real = mi.UInt32(0) if real is None else real
        self.steps = mi.UInt32(0) if steps is None else steps
        self.capped = mi.UInt32(0) if capped is None else capped

    def __add__(self, other):
        return TrackingCounts(self.lookups + other.lookups, self.null + other.null,
                              self.real + other.real, self.steps + other.steps,
                              self.capped + other.capped)


@dr.syntax
def track_segments(segments, density, o, d, t_lo, t_hi, sampler, active, ratio: bool,
                   max_iterations, length_scale=1.0):
    """Track along the local ray ``o + t d`` over ``[t_lo, t_hi]``.

    ``segments``: a segment walker (`mi_amr.device.segments`);
    ``density(u, active) -> (albedo, sigma_t)``; majorants and sigma_t are
    per world length, and ``length_scale`` is local ``t`` per world length.
    Returns ``(collided, t, albedo, sigma_t_or_T, counts)`` (``t`` local):
    for delta tracking the first real collision (``collided``, its ``t``,
    albedo and sigma_t); for ratio tracking ``T`` in the 4th slot. The loop
    stops after ``max_iterations`` iterations (counted in ``counts.capped``).
    """
    state = segments.begin(o, d, t_lo, t_hi, active)
    t = mi.Float(t_lo)
    seg_end = mi.Float(t_lo)
    mu = mi.Float(0.0)
    collided = mi.Bool(False)
    albedo = mi.Color3f(0.0)
    result = mi.Float(1.0 if ratio else 0.0)
    lookups = mi.UInt32(0)
    n_null = mi.UInt32(0)
    n_real = mi.UInt32(0)
    steps = mi.UInt32(0)
    it = mi.UInt32(0)
    alive = mi.Bool(active)
    while dr.hint(alive, label="amr_track"):
        # ---- Next segment once the current one is used up ----
        need = alive & (t >= seg_end)
        state, seg = segments.advance(o, d, state, t_hi, need)
        seg_end = dr.select(need, seg.t1, seg_end)
        mu = dr.select(need, seg.mu, mu)
        t = dr.select(need, dr.maximum(t, seg.t0), t)
        steps += dr.select(need & seg.valid, 1, 0)
        alive &= ~need | seg.valid

        # ---- Tentative collision in the segment (none if mu == 0) ----
        go = alive & (mu > 0.0)
        xi = sampler.next_1d(go)
        t_c = t - dr.log(1.0 - xi) * dr.rcp(dr.select(go, mu, 1.0)) * length_scale
        inside = go & (t_c < seg_end)
        t = dr.select(inside, t_c, dr.select(alive, seg_end, t))
        rgb, sigma_t = density(o + d * t, inside)
        lookups += dr.select(inside, 1, 0)
        if dr.hint(ratio, mode="scalar"):
            # Ratio tracking: T *= 1 - sigma_t / mu
            result = dr.select(inside, result * dr.maximum(1.0 - sigma_t * dr.rcp(mu), 0.0), result)
            n_null += dr.select(inside, 1, 0)
            alive &= result > 0.0
        else:
            # Delta tracking: real collision with probability sigma_t / mu
            accept = inside & (sampler.next_1d(inside) * mu < sigma_t)
            collided |= accept
            albedo = dr.select(accept, rgb, albedo)
            result = dr.select(accept, sigma_t, result)
            n_null += dr.select(inside & ~accept, 1, 0)
            n_real += dr.select(accept, 1, 0)
            alive &= ~accept
        it += 1
        capped = alive & (it >= max_iterations)
        alive &= ~capped
    counts = TrackingCounts(lookups, n_null, n_real, steps, dr.select(it >= max_iterations, 1, 0))
    return collided, t, albedo, result, counts


@dr.syntax
def span_majorant(segments, o, d, t_lo, t_hi, active, max_steps, global_mu):
    """Walk all segments over ``[t_lo, t_hi]`` and return ``(found, t_first,
    t_last, mu_max, capped)``: the span from the start of the first to the
    end of the last segment with a non-zero majorant, and the largest
    majorant met (the "ray-wise" majorant for Mitsuba's stock volpath,
    docs/design.md section 6).

    At most ``max_steps`` segments are visited. A walk cut short there
    (``capped``) falls back to a conservative answer: the span runs on to
    ``t_hi`` with the global majorant ``global_mu``.
    """
    state = segments.begin(o, d, t_lo, t_hi, active)
    found = mi.Bool(False)
    t_first = mi.Float(t_hi)
    t_last = mi.Float(t_lo)
    t_seen = mi.Float(t_lo)
    mu_max = mi.Float(0.0)
    it = mi.UInt32(0)
    capped = mi.Bool(False)
    alive = mi.Bool(active) & (t_lo < t_hi)
    while dr.hint(alive, label="amr_span_majorant"):
        state, seg = segments.advance(o, d, state, t_hi, alive)
        nonzero = seg.valid & (seg.mu > 0.0)
        t_first = dr.select(nonzero & ~found, seg.t0, t_first)
        t_last = dr.select(nonzero, seg.t1, t_last)
        t_seen = dr.select(seg.valid, seg.t1, t_seen)
        mu_max = dr.select(seg.valid, dr.maximum(mu_max, seg.mu), mu_max)
        found |= nonzero
        it += 1
        alive &= seg.valid & (seg.t1 < t_hi)
        capped |= alive & (it >= max_steps)
        alive &= ~capped
    t_first = dr.select(capped & ~found, t_seen, t_first)
    t_last = dr.select(capped, t_hi, t_last)
    mu_max = dr.select(capped, dr.maximum(mu_max, global_mu), mu_max)
    found |= capped & (global_mu > 0.0)
    return found, t_first, t_last, mu_max, capped
