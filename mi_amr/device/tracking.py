"""Delta and ratio tracking through local-majorant segments
(docs/design.md section 5), in one Dr.Jit symbolic loop, optionally with the
segments' minorants as control extinction (section 5b).

Per segment ``[t0, t1]`` with majorant ``mu``: skip it if ``mu == 0`` (no
density look-up); otherwise ``t -= ln(1 - xi) / mu`` from ``max(t, t0)``;
past ``t1`` move on to the next segment; a tentative collision at ``t`` is
real with probability ``sigma_t / mu`` (delta tracking) or multiplies the
transmittance by ``1 - sigma_t / mu`` (ratio tracking, with Russian
roulette once the transmittance falls below `RATIO_RR_THRESHOLD`).

With a control extinction ``mu_c`` (the segment's minorant, ``0 <= mu_c <=
sigma_t``), only the residual ``sigma_t - mu_c`` is tracked, against
``mu - mu_c``:

* residual ratio tracking (Novak et al. 2014): the transmittance takes the
  factor ``exp(-mu_c * length)`` of each segment analytically, and each
  tentative collision (rate ``mu - mu_c``) multiplies it by ``1 - (sigma_t -
  mu_c) / (mu - mu_c)``;
* decomposition tracking (Kutz et al. 2017): two exponential clocks run,
  the control one (rate ``mu_c``) and the residual one (rate ``mu - mu_c``);
  if the control clock rings first the collision is real with probability
  one and needs no look-up, otherwise it is real with probability
  ``(sigma_t - mu_c) / (mu - mu_c)``. A real collision needs the albedo,
  which for a TF of several colours is itself a look-up: then the control
  clock would save nothing, and it runs only where the albedo is known
  without one (``known_albedo``: a TF of one colour; a per-lane flag, so a
  TF change never changes the kernel).

With ``mu_c = 0`` both take exactly the random numbers and steps of plain
delta and ratio tracking: the same image for the same seed.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .rng import Rng
from .structs import jit_struct

#: Ratio tracking plays Russian roulette once its transmittance falls below
#: this: a shadow ray that is mostly blocked stops early, unbiased (it goes
#: on with probability T / threshold, carrying the threshold). Efficiency
#: 1.01-1.12x on five 20k benchmark cases (docs/performance/frame-cost.md):
#: the variance it adds is lost in the rest of the path's.
RATIO_RR_THRESHOLD = 0.5


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
                   max_iterations, length_scale=1.0, control: bool = False, known_albedo=None):
    """Track along the local ray ``o + t d`` over ``[t_lo, t_hi]``.

    ``segments``: a segment walker (`mi_amr.device.segments`); ``sampler``:
    a Mitsuba sampler or an `Rng`, which seeds the loop's own stream;
    ``density = (lookup, albedo_of)``: ``lookup(u, active) -> (value,
    sigma_t)`` at local points, ``albedo_of(value, active) -> rgb`` (called
    once, after the loop, for the lanes that collided: a null collision needs
    no colour); majorants and sigma_t are
    per world length, and ``length_scale`` is local ``t`` per world length.
    ``control``: use the segments' minorants as control extinction
    (residual ratio tracking, decomposition tracking); ``known_albedo``: a
    per-lane flag, set where every value has the same colour (decomposition
    tracking runs its control clock only then, and ``albedo_of`` colours a
    control collision from any value). At a control collision the returned
    sigma_t is the minorant (no look-up is made).
    Returns ``(collided, t, albedo, sigma_t_or_T, counts)`` (``t`` local):
    for delta tracking the first real collision (``collided``, its ``t``,
    albedo and sigma_t); for ratio tracking ``T`` in the 4th slot. The loop
    stops after ``max_iterations`` iterations (counted in ``counts.capped``).
    """
    # The loop state holds only what the loop changes (docs/design.md
    # section 6): what a mode leaves unchanged is a Python constant there,
    # per-ray constants are excluded, and the random numbers come from a
    # stream of our own (`Rng`) rather than from the sampler.
    use_control = control and (ratio or known_albedo is not None)
    lookup, albedo_of = density
    state, fixed = segments.begin(o, d, t_lo, t_hi, active)
    rng = Rng.derive(sampler, active)
    t = mi.Float(t_lo)
    seg_end = mi.Float(t_lo)
    mu = mi.Float(0.0)
    mu_c = mi.Float(0.0) if use_control else 0.0
    collided = False if ratio else mi.Bool(False)
    value = 0.0 if ratio else mi.Float(0.0)     # the value at the real collision
    result = mi.Float(1.0 if ratio else 0.0)
    lookups = mi.UInt32(0)
    n_null = mi.UInt32(0)
    n_real = 0 if ratio else mi.UInt32(0)
    steps = mi.UInt32(0)
    it = mi.UInt32(0)
    alive = mi.Bool(active)
    while dr.hint(alive, label="amr_track",
                  exclude=[segments, lookup, albedo_of, fixed, o, d, t_hi, max_iterations, length_scale,
                           known_albedo]):
        # ---- Next segment once the current one is used up ----
        need = alive & (t >= seg_end)
        state, seg = segments.advance(o, d, state, fixed, t_hi, need)
        seg_end = dr.select(need, seg.t1, seg_end)
        mu = dr.select(need, seg.mu, mu)
        t = dr.select(need, dr.maximum(t, seg.t0), t)
        steps += dr.select(need & seg.valid, 1, 0)
        alive &= ~need | seg.valid
        if dr.hint(use_control, mode="scalar"):
            mu_c_new = dr.clip(seg.mu_min, 0.0, seg.mu)
            if dr.hint(not ratio, mode="scalar"):
                # no control clock without a known albedo: plain delta tracking
                mu_c_new = dr.select(known_albedo, mu_c_new, 0.0)
            mu_c = dr.select(need, mu_c_new, mu_c)
            if dr.hint(ratio, mode="scalar"):
                # the control part of this segment's transmittance, analytically
                enter = need & alive
                result = dr.select(enter, result * dr.exp(-mu_c * (seg_end - t) * dr.rcp(length_scale)), result)

        # ---- Tentative collision in the segment (none if mu == 0) ----
        residual = mu - mu_c
        go = alive & (residual > 0.0)
        xi = rng.next_1d(go)
        t_c = t - dr.log(1.0 - xi) * dr.rcp(dr.select(go, residual, 1.0)) * length_scale
        t_c = dr.select(go, t_c, float("inf"))
        by_control = mi.Bool(False)
        if dr.hint(control and not ratio and known_albedo is not None, mode="scalar"):
            # decomposition tracking: the control clock (rate mu_c) may ring first
            ctl = alive & (mu_c > 0.0)
            xi_c = rng.next_1d(ctl)
            t_ctl = t - dr.log(1.0 - xi_c) * dr.rcp(dr.select(ctl, mu_c, 1.0)) * length_scale
            by_control = ctl & (t_ctl < t_c)
            t_c = dr.select(by_control, t_ctl, t_c)
        inside = alive & (t_c < seg_end)
        by_control &= inside
        t = dr.select(inside, t_c, dr.select(alive, seg_end, t))
        look = inside & ~by_control
        v = mi.Float(0.0)
        sigma_t = mi.Float(0.0)
        x = o + d * t
        if dr.hint(look, exclude=[lookup, x]):
            # a symbolic conditional: a SIMD packet in which no lane looks
            # up the density (all stepping through segments) skips it
            v, sigma_t = lookup(x, look)
        lookups += dr.select(look, 1, 0)
        excess = sigma_t - mu_c
        inv_res = dr.rcp(dr.select(residual > 0.0, residual, 1.0))
        if dr.hint(ratio, mode="scalar"):
            # (Residual) ratio tracking: T *= 1 - (sigma_t - mu_c) / (mu - mu_c)
            result = dr.select(inside, result * dr.maximum(1.0 - excess * inv_res, 0.0), result)
            n_null += dr.select(inside, 1, 0)
            # Russian roulette below RATIO_RR_THRESHOLD: go on with probability
            # T / threshold and T = threshold, else stop with T = 0 (unbiased)
            low = inside & (result < RATIO_RR_THRESHOLD)
            survive = rng.next_1d(low) * RATIO_RR_THRESHOLD < result
            result = dr.select(low, dr.select(survive, RATIO_RR_THRESHOLD, 0.0), result)
            alive &= result > 0.0
        else:
            # Delta / decomposition tracking: real with probability
            # (sigma_t - mu_c) / (mu - mu_c), or 1 at a control collision
            accept = by_control | (look & (rng.next_1d(look) * residual < excess))
            collided |= accept
            if dr.hint(known_albedo is not None, mode="scalar"):
                sigma_t = dr.select(by_control, mu_c, sigma_t)
            value = dr.select(accept & ~by_control, v, value)
            result = dr.select(accept, sigma_t, result)
            n_null += dr.select(inside & ~accept, 1, 0)
            n_real += dr.select(accept, 1, 0)
            alive &= ~accept
        it += 1
        capped = alive & (it >= max_iterations)
        alive &= ~capped
    counts = TrackingCounts(lookups, n_null, mi.UInt32(n_real), steps, dr.select(it >= max_iterations, 1, 0))
    if dr.hint(ratio, mode="scalar"):
        return mi.Bool(collided), t, mi.Color3f(0.0), result, counts
    # a control collision happens only where the colour is known (one
    # colour for every value), so the value left there colours it too
    return collided, t, albedo_of(value, collided), result, counts


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
    state, fixed = segments.begin(o, d, t_lo, t_hi, active)
    found = mi.Bool(False)
    t_first = mi.Float(t_hi)
    t_last = mi.Float(t_lo)
    t_seen = mi.Float(t_lo)
    mu_max = mi.Float(0.0)
    it = mi.UInt32(0)
    capped = mi.Bool(False)
    alive = mi.Bool(active) & (t_lo < t_hi)
    while dr.hint(alive, label="amr_span_majorant", exclude=[segments, fixed, o, d, t_hi, max_steps, global_mu]):
        state, seg = segments.advance(o, d, state, fixed, t_hi, alive)
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
