"""Estimators along local-majorant segments (docs/design.md sections 5 and
5b), as consumers of one segment walk.

`walk_segments` is the one walk (the shape of pbrt-v4's ``SampleT_maj``):
it takes the traversal's segments ``[t0, t1]`` front to back, moves ``t``
through each, counts its moves and stops at a bound; its inner loop moves
each lane through segments until a tentative collision falls inside one,
its outer loop takes the collisions (docs/design.md section 5c). What happens in a
segment is the consumer's: an estimator object built per call, whose
attributes are per-ray constants and whose changing values live in its own
typed loop state. It provides

* ``label``: the name of the Dr.Jit loop (``amr_track``, ``amr_span_majorant``);
* ``begin(ray, active) -> state``: the initial loop state;
* ``enter(state, ray, seg, entered, t, seg_end) -> state``: lanes
  ``entered`` have just taken the segment ``seg`` and stand at ``t`` in
  ``[seg.t0, seg_end]``;
* ``MOVING``: the names of the state's fields that ``enter``, ``clock``
  and ``passes`` change (the inner loop's state);
* ``clock(state, ray, t, seg_end, moving) -> (state, t_c, inside)``: lanes
  ``moving`` draw their next tentative collision ``t_c`` in the current
  segment, ``inside`` where it falls before ``seg_end``;
* ``passes(state, alive) -> alive``: what a lane that reached ``seg_end``
  without a collision keeps of ``alive`` (false ends the lane);
* ``collide_at(state, ray, t_c, inside, alive) -> (state, alive)``: the
  lanes ``inside`` collide at ``t_c``;
* ``result(state, ray, end) -> result``: a typed result from the last state
  and the walk's `WalkEnd`.

The consumers:

* `DeltaTracking` (free flights): per segment ``[t0, t1]`` with majorant
  ``mu``, skip it if ``mu == 0`` (no density look-up); otherwise ``t -=
  ln(1 - xi) / mu`` from ``max(t, t0)``; past ``t1`` move on to the next
  segment; a tentative collision at ``t`` is real with probability
  ``sigma_t / mu``. Result: `FreeFlight`.
* `RatioTracking` (shadow rays): the same steps, each multiplying the
  transmittance by ``1 - sigma_t / mu``, with Russian roulette once it falls
  below `RATIO_RR_THRESHOLD`. Result: `Transmittance`.
* `ResidualRatioTracking` (Novak et al. 2014): with the segment's minorant
  as control extinction ``mu_c`` (``0 <= mu_c <= sigma_t``), the
  transmittance takes the factor ``exp(-mu_c * length)`` of each segment
  analytically (then Russian roulette, as after a collision), and each
  tentative collision (rate ``mu - mu_c``) multiplies it by ``1 - (sigma_t -
  mu_c) / (mu - mu_c)``.
* `DecompositionTracking` (Kutz et al. 2017): two exponential clocks run,
  the control one (rate ``mu_c``) and the residual one (rate ``mu -
  mu_c``), drawn as one clock of rate ``mu`` that is the control one with
  probability ``mu_c / mu``; if the control clock rings first the collision is real with
  probability one and needs no look-up, otherwise it is real with
  probability ``(sigma_t - mu_c) / (mu - mu_c)``. A real collision needs the
  albedo, which for a TF of several colours is itself a look-up: then the
  control clock would save nothing, and it runs only where the albedo is
  known without one (``known_albedo``: a TF of one colour; a per-lane flag,
  so a TF change never changes the kernel).
* `SpanMajorant`: no collisions, one segment per iteration; the span of the
  segments with a non-zero majorant and the largest majorant met (the
  ray-wise majorant for Mitsuba's stock volpath, docs/design.md section 6).
  Result: `MajorantSpan`.

With ``mu_c = 0`` the minorant estimators take exactly the random numbers
and steps of plain delta and ratio tracking: the same image for the same
seed.

Every tracking estimator can *thin* (docs/design.md section 5d): given
``thin(u, active) -> mu_f``, a finer majorant at local points, its clock
keeps a tentative collision with probability ``(mu_f - mu_c) / (mu -
mu_c)`` and draws the next one where it drops it (`_Tracking._thinned`),
and the kept collision is weighed against ``mu_f`` (``mu_pt`` in the
state): the look-ups of the finer majorants on the walked segments. A
collision thinned away counts as a null one without a look-up.

Every loop state holds only what the loop changes (docs/design.md section
6): read-only names are excluded, per-ray constants are attributes of the
consumer or of the `LocalRay`, what a consumer never changes (``mu_c``
without minorants) is a Python constant, and the random numbers come from a
stream of the consumer's own (`Rng`) rather than from the sampler.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .rng import Rng
from .segments import Segment
from ..core.jit_struct import jit_struct

#: Ratio tracking plays Russian roulette once its transmittance falls below
#: this: a shadow ray that is mostly blocked stops early, unbiased (it goes
#: on with probability T / threshold, carrying the threshold). The variance
#: it adds is lost in the rest of the path's, and the work it saves is not;
#: measured in docs/performance/frame-cost.md section 5.
RATIO_RR_THRESHOLD = 0.5
#: A thinning lane (`_Tracking._thinned`) stops thinning after this many
#: collisions thinned away in a row in one segment, so that its loop ends
#: however far the finer majorant falls below the segment's.
THIN_MAX_DRAWS = 64


def _tally(counter, increment):
    """``counter + increment``, or None where the estimator does not count
    (a Python constant: no loop variable, no work per iteration)."""
    return None if counter is None else counter + increment


def _counted(counter):
    """A count for `TrackingCounts`: zeros where none was kept."""
    return mi.UInt32(0) if counter is None else counter


def _counter(count: bool):
    """The initial value of a count: 0, or None when not counting."""
    return mi.UInt32(0) if count else None


class _Fields:
    """Keyword construction for a `jit_struct`: every field defaults to
    None (Dr.Jit makes empty instances and fills them in)."""

    def __init__(self, **values):
        for name in self.JIT_FIELDS:
            setattr(self, name, values.pop(name, None))
        if values:
            raise TypeError(f"{type(self).__name__}: unknown fields {sorted(values)}")


@jit_struct(lookups="UInt32", null="UInt32", real="UInt32", steps="UInt32", capped="UInt32")
class TrackingCounts:
    """Per-lane event counts of one tracking call: density look-ups, null
    and real collisions, segments entered, and walks that used all their
    iterations (``capped``)."""

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


# ---- The walk -------------------------------------------------------------------
@jit_struct(o="Point3f", d="Vector3f", t_lo="Float", t_hi="Float", scale="Float")
class LocalRay(_Fields):
    """A ray ``o + t d`` in the medium's local space (the unit cube), walked
    over ``[t_lo, t_hi]``; ``scale``: local ``t`` per world ``t`` (the
    world ray's point at ``t`` is the local one at ``scale * t``). Majorants
    and sigma_t are per world length, and the estimators report world ``t``
    (`world_t`)."""

    def world_t(self, t):
        """The world ray's ``t`` of local ``t``."""
        return t * dr.rcp(dr.select(self.scale > 0.0, self.scale, 1.0))


@jit_struct(t="Float", exhausted="Bool", cut="Bool")
class WalkEnd(_Fields):
    """Where a walk ended: ``t`` (local), ``exhausted`` where it used all
    ``max_iterations`` iterations, and ``cut`` where it still had work left
    then (a walk that ends on its last iteration is exhausted, not cut)."""


@dr.syntax
def walk_segments(segments, ray: LocalRay, active, consumer, max_iterations):
    """Walk ``consumer`` through the segments of ``ray`` over ``[ray.t_lo,
    ray.t_hi]`` and return its result.

    ``segments``: a segment walker (`mi_amr.device.segments`); ``consumer``:
    an estimator (`DeltaTracking`, `DecompositionTracking`, `RatioTracking`,
    `ResidualRatioTracking`, `SpanMajorant`, or anything with their hooks,
    see the module docstring). A lane stops when the consumer ends it, when
    the segments run out, or after ``max_iterations`` moves (a move: to a
    tentative collision, or to the end of a segment).

    Two loops (docs/design.md section 5c): the inner one
    (`_segments_to_collision`) moves each lane through segments, drawing
    its clock in each, until a tentative collision falls inside one (or the
    lane ends); the outer one then takes those collisions, with their
    density look-ups. A SIMD packet thus looks up once per collision of its
    busiest lane, not once per move of its busiest lane. Each lane makes the
    same moves and draws the same random numbers in the same order as in one
    loop.
    """
    seg_state, fixed = segments.begin(ray.o, ray.d, ray.t_lo, ray.t_hi, active)
    state = consumer.begin(ray, active)
    t = mi.Float(ray.t_lo)
    seg_end = mi.Float(ray.t_lo)
    it = mi.UInt32(0)
    alive = mi.Bool(active) & (ray.t_lo < ray.t_hi)
    # the loop state: the walker's and the consumer's state, t, the current
    # segment's end, the move count and the live lanes
    while dr.hint(alive & (it < max_iterations), label=consumer.label,
                  exclude=[segments, ray, consumer, fixed, max_iterations]):
        state, seg_state, seg_end, t, alive, it = _segments_to_collision(
            segments, ray, consumer, fixed, max_iterations, state, seg_state, seg_end, t, alive, it)
        # ---- The tentative collisions found: every lane still alive and
        # within the bound stopped at one (`t`) ----
        inside = alive & (it < max_iterations)
        state, alive = consumer.collide_at(state, ray, t, inside, alive)
        it += dr.select(inside, 1, 0)
    # a lane still alive here was stopped by the bound
    return consumer.result(state, ray, WalkEnd(t=t, exhausted=it >= max_iterations, cut=alive))


@dr.syntax
def _segments_to_collision(segments, ray, consumer, fixed, max_iterations, state, seg_state, seg_end, t, alive,
                           it):
    """The inner loop of `walk_segments`: each live lane moves on through
    its segments until its clock puts a tentative collision inside one
    (then ``t`` is that collision; a control clock's is marked in the
    consumer's state) or the lane ends. Its state holds only the fields of
    the consumer's state that moving changes (``consumer.MOVING``), so that
    it too is recorded once (docs/design.md section 6). Returns ``(state,
    seg_state, seg_end, t, alive, it)``."""
    names = tuple(k for k in consumer.MOVING if getattr(state, k) is not None)
    part = tuple(getattr(state, k) for k in names)
    moving = alive & (it < max_iterations)
    while dr.hint(moving, label=consumer.label + "_segments",
                  exclude=[segments, ray, consumer, fixed, max_iterations, state, names]):
        moved = _with_fields(state, names, part)
        # ---- Next segment once the current one is used up ----
        need = moving & (t >= seg_end)
        seg = Segment(t0=mi.Float(0.0), t1=mi.Float(0.0), mu=mi.Float(0.0), mu_min=mi.Float(0.0),
                      valid=mi.Bool(False), level=mi.UInt32(0), vmin=mi.Float(0.0), vmax=mi.Float(0.0))
        if dr.hint(need, exclude=[segments, ray, fixed]):
            # a symbolic conditional: a packet whose lanes all go on in
            # their segments (after a null collision) skips the advance
            seg_state, seg = segments.advance(ray.o, ray.d, seg_state, fixed, ray.t_hi, need)
        seg_end = dr.select(need, seg.t1, seg_end)
        t = dr.select(need, dr.maximum(t, seg.t0), t)
        alive &= ~need | seg.valid
        moving &= alive
        moved = consumer.enter(moved, ray, seg, need & seg.valid, t, seg_end)
        # ---- The lane's clock in the segment: a collision inside, or on to its end ----
        moved, t_c, inside = consumer.clock(moved, ray, t, seg_end, moving)
        passing = moving & ~inside
        t = dr.select(inside, t_c, dr.select(passing, seg_end, t))
        # every walker's segments end at t_hi: a lane that got there has
        # no segment left, and stops now rather than at a failed advance
        alive = dr.select(passing, consumer.passes(moved, alive) & (t < ray.t_hi), alive)
        it += dr.select(passing, 1, 0)
        moving = passing & alive & (it < max_iterations)
        part = tuple(getattr(moved, k) for k in names)
    return _with_fields(state, names, part), seg_state, seg_end, t, alive, it


def _with_fields(state, names, values):
    """A copy of the loop state ``state`` (a `_Fields` struct) with the fields
    ``names`` set to ``values``."""
    return type(state)(**{**vars(state), **dict(zip(names, values))})


# ---- Tracking estimators ----------------------------------------------------------
@jit_struct(rng=Rng, null="UInt32")
class _Clock(_Fields):
    """What a clock draws from and counts into (`_Tracking.clocks` reads
    ``rng`` only): the loop state of thinning (`_Tracking._thinned`)."""


class TentativeCollision:
    """One move of a tracking estimator in its segment, as its collision
    hook sees it: ``inside`` where a tentative collision fell in the segment
    (elsewhere the lane reached the segment's end), ``by_control`` where the
    control clock rang first (no look-up), ``look`` where the density was
    looked up, the ``value`` and ``sigma_t`` found there, and the segment's
    control extinction ``mu_c`` and residual majorant ``residual = mu - mu_c``;
    ``carried``: a further field's value found by the same look-up (0
    unless the look-up carries one); ``x``: the local point."""

    __slots__ = ("inside", "by_control", "look", "value", "sigma_t", "mu_c", "residual", "carried", "x")

    def __init__(self, inside, by_control, look, value, sigma_t, mu_c, residual, carried, x):
        self.inside, self.by_control, self.look = inside, by_control, look
        self.value, self.sigma_t, self.mu_c, self.residual = value, sigma_t, mu_c, residual
        self.carried, self.x = carried, x


class Replay:
    """The adjoint of a tracking walk in a path-replay pass (docs/design.md
    section 13b): the walk takes the primal's random numbers again, and at
    each tentative collision whose factor enters the estimate (a null
    collision of delta tracking: ``sigma_n = mu - sigma_t``; every
    collision of ratio tracking: ``1 - (sigma_t - mu_c) / (mu - mu_c)``)
    it looks ``sigma_t`` up again with gradients (``lookup(u, active) ->
    (value, sigma_t)``) and differentiates the factor's logarithm, the
    majorants held fixed.

    Backward mode (``mode`` ``dr.ADMode.Backward``): ``weight`` is, per
    lane, the adjoint radiance times the radiance that the factor scales,
    summed over channels, and each collision sends ``weight * d log(factor)``
    to the parameters. Forward mode: the walk's result carries the sum of
    the factors' ``d log`` (``dlog``), which the integrator scales."""

    def __init__(self, mode, lookup, weight=None):
        self.mode, self.lookup, self.weight = mode, lookup, weight

    @property
    def forward(self) -> bool:
        return self.mode == dr.ADMode.Forward

    def begin(self):
        """The initial ``dlog`` of a walk's state: 0 in forward mode, None
        (no loop variable) in backward mode."""
        return mi.Float(0.0) if self.forward else None

    def collision(self, state, x, where, factor):
        """Differentiate ``log factor(sigma_t)`` at local points ``x`` on
        lanes ``where``; ``factor`` maps the attached sigma_t to the
        collision's factor. Returns the state (its ``dlog`` grown in forward
        mode)."""
        with dr.resume_grad():
            _, sigma_t = self.lookup(x, where)
            f = factor(sigma_t)
            f_primal = dr.detach(f)
            ok = where & (f_primal > 0.0)
            # f / f_primal: 1 in value, d log f in its derivative (a safe
            # denominator where the factor is 0: no inf times 0 in the adjoint)
            ratio = dr.select(ok, f * dr.rcp(dr.select(ok, f_primal, 1.0)), 0.0)
            if dr.grad_enabled(ratio):
                if self.forward:
                    state.dlog = state.dlog + dr.select(ok, dr.forward_to(ratio), 0.0)
                else:
                    dr.backward_from(self.weight * ratio)
        return state


#: A differentiable walk's majorants (`MajorantMargin`): this factor on each
#: leaf's and this share of the global majorant added (docs/design.md 13b).
GRADIENT_MARGIN = 1.5
GRADIENT_FLOOR = 0.05


class MajorantMargin:
    """Majorants raised for differentiable walks (docs/design.md section
    13b): ``mu' = factor * mu + floor`` (``floor`` in inverse world units,
    per lane). A leaf's majorant may equal sigma_t (a constant region, a
    value on a TF entry): then no null collision is ever sampled there,
    though ``d sigma_n = -d sigma_t`` is not 0, and a replay would miss
    that derivative; where the majorant is 0 the walk makes no look-up at
    all. With ``factor > 1`` and ``floor > 0`` every point of a segment
    with a positive ``sigma_t`` derivative has ``sigma_n >= (factor - 1) mu
    + floor > 0``. The primal and the replay must use the same margin (the
    same random numbers)."""

    def __init__(self, factor: float, floor):
        self.factor, self.floor = factor, floor

    def __call__(self, mu):
        return mu * self.factor + self.floor


class _Tracking:
    """What the tracking estimators share: a random stream of their own
    (seeded from ``sampler``: a Mitsuba sampler or a parent `Rng`), the
    segment's majorant in the loop state, and tentative collisions at the
    residual rate ``mu - mu_c`` with a density look-up at each.

    ``lookup(u, active) -> (value, sigma_t)`` at local points (sigma_t per
    world length), or ``(value, sigma_t, carried)`` when one look-up also
    reconstructs a further field (`AMRMedium.point_query`). Subclasses provide the initial state (`begin`), the
    collision hook (`collide`) and the result. ``count``: keep the event
    counts (look-ups, collisions, steps) in the loop state; without it they
    are Python constants (no loop variables) and the result's counts are 0
    but ``capped``."""

    label = "amr_track"
    #: the state fields that `enter`, `clock` and `passes` change (the inner
    #: loop's state, `walk_segments`); the others change only in `collide_at`
    MOVING = ("rng", "mu", "steps", "mu_pt", "null")

    def __init__(self, lookup, sampler, carries: bool = False, count: bool = True, replay: Replay | None = None,
                 margin: MajorantMargin | None = None, thin=None):
        if thin is not None and (replay is not None or margin is not None):
            raise ValueError("tracking: a differentiable walk does not thin its collisions")
        #: ``thin(u, active) -> mu_f``: a finer majorant at local points
        #: (inverse world units), or None (docs/design.md section 5d)
        self.thin = thin
        self.lookup = lookup
        self.sampler = sampler
        #: whether ``lookup`` returns a carried field's value too
        self.carries = carries
        self.count = count
        #: the adjoint of a path-replay pass (`Replay`), or None: the primal
        self.replay = replay
        #: raised majorants of a differentiable walk (`MajorantMargin`), or None
        self.margin = margin

    def _dlog(self):
        return None if self.replay is None else self.replay.begin()

    def _mu_pt(self):
        """The initial finer majorant at the pending collision: None (no
        loop variable) unless the walk thins."""
        return None if self.thin is None else mi.Float(0.0)

    def control(self, state):
        """The current segment's control extinction ``mu_c``: none here, a
        Python constant (no loop variable)."""
        return 0.0

    def enter(self, state, ray, seg, entered, t, seg_end):
        """The walk's hook: the new segment's majorant, one more step."""
        mu = seg.mu if self.margin is None else self.margin(seg.mu)
        state.mu = dr.select(entered, mu, state.mu)
        state.steps = _tally(state.steps, dr.select(entered, 1, 0))
        return state

    def clocks(self, state, ray, t, mu_c, residual, alive):
        """``(t_c, by_control)``: the next tentative collision (``inf``
        where there is none: ``residual == 0``) and where the control clock
        set it (never here)."""
        go = alive & (residual > 0.0)
        xi = state.rng.next_1d(go)
        # t -= ln(1 - xi) / (mu - mu_c), rates per world length, t local
        t_c = t - dr.log(1.0 - xi) * dr.rcp(dr.select(go, residual, 1.0)) * ray.scale
        return dr.select(go, t_c, float("inf")), mi.Bool(False)

    def clock(self, state, ray, t, seg_end, moving):
        """The walk's hook: the lanes ``moving`` draw their next tentative
        collision in the segment; ``(state, t_c, inside)``, ``inside``
        where it falls before ``seg_end`` (whether the control clock set it
        is kept in the state: `rang`)."""
        mu_c = self.control(state)
        t_c, by_control = self.clocks(state, ray, t, mu_c, state.mu - mu_c, moving)
        inside = moving & (t_c < seg_end)
        if self.thin is not None:
            state, t_c, by_control, inside = self._thinned(state, ray, t_c, by_control, inside, seg_end, mu_c)
        return self.mark(state, by_control & inside, moving), t_c, inside

    @dr.syntax
    def _thinned(self, state, ray, t_c, by_control, inside, seg_end, mu_c):
        """Thin the segment's tentative collisions by the finer majorant
        (docs/design.md section 5d): a collision of the residual clock at
        ``x`` stays with probability ``(mu_f(x) - mu_c) / (mu - mu_c)``,
        and the lane looks the density up there against ``mu_f(x)``
        (``state.mu_pt``); a collision thinned away is a null one without a
        look-up, and the lane draws its next one from there. The kept
        collisions are those of a clock of rate ``mu_f - mu_c``: the same
        law as tracking against the finer majorant, with the segment's
        steps. After `THIN_MAX_DRAWS` thinned collisions in a row a lane
        takes the next one against ``mu`` itself (no more thinning)."""
        mu = state.mu
        residual = mu - mu_c
        pending = inside & ~by_control
        mu_pt = mi.Float(mu)
        draws = mi.UInt32(0)
        # the loop state: what thinning changes (the stream, the count of
        # null collisions, the pending collision), not the whole state
        clock = _Clock(rng=state.rng, null=state.null)
        thin = self.thin
        while dr.hint(pending, label=self.label + "_thin", exclude=[thin, ray, seg_end, residual, mu, mu_c]):
            capped = draws >= THIN_MAX_DRAWS
            mu_f = dr.minimum(thin(ray.o + ray.d * t_c, pending & ~capped), mu)
            keep = pending & (capped | (clock.rng.next_1d(pending & ~capped) * residual < mu_f - mu_c))
            mu_pt = dr.select(keep, dr.select(capped, mu, mu_f), mu_pt)
            redraw = pending & ~keep
            clock.null = _tally(clock.null, dr.select(redraw, 1, 0))
            t_next, ctl = self.clocks(clock, ray, t_c, mu_c, residual, redraw)
            t_c = dr.select(redraw, t_next, t_c)
            by_control = dr.select(redraw, ctl, by_control)
            inside = dr.select(redraw, t_c < seg_end, inside)
            draws += 1
            pending = redraw & inside & ~by_control
        state.rng, state.null = clock.rng, clock.null
        state.mu_pt = mu_pt
        return state, t_c, by_control, inside

    def mark(self, state, by_control, moving):
        """Keep in the state where the control clock set the collision
        (nothing to keep without a control clock)."""
        return state

    def rang(self, state, inside):
        """Where the control clock set the collision of lanes ``inside``."""
        return mi.Bool(False)

    def passes(self, state, alive):
        """The walk's hook: what a lane that reached its segment's end
        without a collision keeps of ``alive`` (all of it here)."""
        return alive

    @dr.syntax
    def collide_at(self, state, ray, t_c, inside, alive):
        """The walk's hook: the tentative collisions of lanes ``inside`` at
        ``t_c``, the density there, then the estimator's `collide`."""
        by_control = self.rang(state, inside)
        mu_c = self.control(state)
        # against the finer majorant at the point where the collision was thinned
        residual = (state.mu if self.thin is None else state.mu_pt) - mu_c
        look = inside & ~by_control
        found = (mi.Float(0.0), mi.Float(0.0)) + ((mi.Float(0.0),) if self.carries else ())
        lookup = self.lookup
        x = ray.o + ray.d * t_c
        if dr.hint(look, exclude=[lookup, x]):
            # a symbolic conditional: a SIMD packet in which no lane looks
            # up the density skips it
            found = lookup(x, look)
        state.lookups = _tally(state.lookups, dr.select(look, 1, 0))
        carried = found[2] if self.carries else 0.0
        return self.collide(state, TentativeCollision(inside, by_control, look, found[0], found[1], mu_c,
                                                      residual, carried, x), alive)


@jit_struct(rng=Rng, mu="Float", mu_pt="Float", collided="Bool", value="Float", carried="Float", looked="Bool",
            sigma_t="Float", lookups="UInt32", null="UInt32", real="UInt32", steps="UInt32", dlog="Float")
class DeltaState(_Fields):
    """Loop state of `DeltaTracking`: the stream, the segment's majorant,
    the real collision so far (its value and carried field's value, whether
    they were looked up there, and sigma_t) and the counts. ``carried`` is
    None unless the look-up carries a field (no loop variable that never
    changes); ``dlog`` None unless a forward-mode `Replay` sums into it."""


@jit_struct(collided="Bool", t="Float", albedo="UnpolarizedSpectrum", sigma_t="Float", value="Float",
            carried="Float", looked="Bool", counts=TrackingCounts, dlog="Float")
class FreeFlight(_Fields):
    """Result of a free flight: ``collided`` where a real collision
    happened, at the world ray's ``t`` (`LocalRay.world_t`; where none
    happened, where the walk ended), with its ``albedo`` and ``sigma_t``,
    the reconstructed ``value`` there (and a ``carried`` field's, None when
    the look-up carried none) where ``looked`` (a control collision of
    decomposition tracking looks nothing up), and the counts; ``dlog``: the
    derivative of the log of its null collisions' factors (forward-mode
    `Replay`; None otherwise)."""


class DeltaTracking(_Tracking):
    """Delta tracking: the first real collision.

    ``albedo_of(value, active) -> rgb`` is called once, after the loop, for
    the lanes that collided (a null collision needs no colour)."""

    def __init__(self, lookup, albedo_of, sampler, carries: bool = False, count: bool = True,
                 replay: Replay | None = None, margin: MajorantMargin | None = None, thin=None):
        super().__init__(lookup, sampler, carries, count, replay, margin, thin)
        self.albedo_of = albedo_of

    def begin(self, ray, active):
        n = self.count
        return DeltaState(rng=Rng.derive(self.sampler, active), mu=mi.Float(0.0), mu_pt=self._mu_pt(),
                          collided=mi.Bool(False),
                          value=mi.Float(0.0), carried=mi.Float(0.0) if self.carries else None,
                          looked=mi.Bool(False), sigma_t=mi.Float(0.0), lookups=_counter(n),
                          null=_counter(n), real=_counter(n), steps=_counter(n), dlog=self._dlog())

    def real_sigma_t(self, c: TentativeCollision):
        """sigma_t reported at a real collision: the one looked up."""
        return c.sigma_t

    def collide(self, state, c: TentativeCollision, alive):
        # real with probability (sigma_t - mu_c) / (mu - mu_c), or 1 at a
        # control collision
        excess = c.sigma_t - c.mu_c
        accept = c.by_control | (c.look & (state.rng.next_1d(c.look) * c.residual < excess))
        state.collided |= accept
        state.value = dr.select(accept & ~c.by_control, c.value, state.value)
        if self.carries:
            state.carried = dr.select(accept & ~c.by_control, c.carried, state.carried)
        state.looked = dr.select(accept, ~c.by_control, state.looked)
        state.sigma_t = dr.select(accept, self.real_sigma_t(c), state.sigma_t)
        state.null = _tally(state.null, dr.select(c.inside & ~accept, 1, 0))
        state.real = _tally(state.real, dr.select(accept, 1, 0))
        if self.replay is not None:
            # a looked-up null collision scales the path by sigma_n = mu - sigma_t
            mu = c.mu_c + c.residual
            state = self.replay.collision(state, c.x, c.look & ~accept, lambda sigma_t: mu - sigma_t)
        return state, alive & ~accept

    def result(self, state, ray, end: WalkEnd) -> FreeFlight:
        counts = TrackingCounts(_counted(state.lookups), _counted(state.null), _counted(state.real),
                                _counted(state.steps), dr.select(end.exhausted, 1, 0))
        return FreeFlight(collided=state.collided, t=ray.world_t(end.t),
                          albedo=self.albedo_of(state.value, state.collided), sigma_t=state.sigma_t,
                          value=state.value, carried=state.carried, looked=state.collided & state.looked,
                          counts=counts, dlog=state.dlog)


@jit_struct(**DeltaState.JIT_FIELDS, mu_c="Float", by_control="Bool")
class DecompositionState(DeltaState):
    """Loop state of `DecompositionTracking`: `DeltaState`, the segment's
    control extinction and whether the control clock set the pending
    collision."""


class DecompositionTracking(DeltaTracking):
    """Decomposition tracking against the segments' minorants, where
    ``known_albedo`` (a per-lane flag) says every value has the same colour;
    plain delta tracking elsewhere. A control collision makes no look-up and
    reports ``mu_c`` as its sigma_t; the value left in the state colours it
    (any value has that one colour)."""

    MOVING = DeltaTracking.MOVING + ("mu_c", "by_control")

    def __init__(self, lookup, albedo_of, sampler, known_albedo, carries: bool = False, count: bool = True,
                 thin=None):
        super().__init__(lookup, albedo_of, sampler, carries, count, thin=thin)
        self.known_albedo = known_albedo

    def begin(self, ray, active):
        return DecompositionState(**vars(super().begin(ray, active)), mu_c=mi.Float(0.0),
                                  by_control=mi.Bool(False))

    def control(self, state):
        return state.mu_c

    def mark(self, state, by_control, moving):
        state.by_control = dr.select(moving, by_control, state.by_control)
        return state

    def rang(self, state, inside):
        return state.by_control & inside

    def enter(self, state, ray, seg, entered, t, seg_end):
        state = super().enter(state, ray, seg, entered, t, seg_end)
        # no control clock without a known albedo: plain delta tracking there
        mu_c = dr.select(self.known_albedo, dr.clip(seg.mu_min, 0.0, seg.mu), 0.0)
        state.mu_c = dr.select(entered, mu_c, state.mu_c)
        return state

    def clocks(self, state, ray, t, mu_c, residual, alive):
        # the earlier of the control clock (rate mu_c) and the residual one
        # (rate mu - mu_c) rings at rate mu, and it is the control clock with
        # probability mu_c / mu: one exponential and one uniform (drawn only
        # where mu_c > 0, so that with mu_c = 0 the random numbers are those
        # of delta tracking) instead of two exponentials
        mu = mu_c + residual
        go = alive & (mu > 0.0)
        xi = state.rng.next_1d(go)
        t_c = t - dr.log(1.0 - xi) * dr.rcp(dr.select(go, mu, 1.0)) * ray.scale
        ctl = go & (mu_c > 0.0)
        by_control = ctl & (state.rng.next_1d(ctl) * mu < mu_c)
        return dr.select(go, t_c, float("inf")), by_control

    def real_sigma_t(self, c: TentativeCollision):
        return dr.select(c.by_control, c.mu_c, c.sigma_t)


@jit_struct(rng=Rng, mu="Float", mu_pt="Float", T="Float", lookups="UInt32", null="UInt32", steps="UInt32",
            dlog="Float")
class RatioState(_Fields):
    """Loop state of `RatioTracking`: the stream, the segment's majorant,
    the transmittance so far and the counts (``dlog`` as in `DeltaState`)."""


@jit_struct(T="Float", counts=TrackingCounts, dlog="Float")
class Transmittance(_Fields):
    """Result of a transmittance estimate: ``T`` and the counts (``real``
    is 0: ratio tracking has no real collisions); ``dlog``: the derivative
    of ``log T`` (forward-mode `Replay`; None otherwise)."""


class RatioTracking(_Tracking):
    """Ratio tracking with Russian roulette below `RATIO_RR_THRESHOLD`."""

    def begin(self, ray, active):
        n = self.count
        return RatioState(rng=Rng.derive(self.sampler, active), mu=mi.Float(0.0), mu_pt=self._mu_pt(), T=mi.Float(1.0),
                          lookups=_counter(n), null=_counter(n), steps=_counter(n), dlog=self._dlog())

    def collide(self, state, c: TentativeCollision, alive):
        # T *= 1 - (sigma_t - mu_c) / (mu - mu_c) at every tentative collision
        excess = c.sigma_t - c.mu_c
        inv_res = dr.rcp(dr.select(c.residual > 0.0, c.residual, 1.0))
        state.T = dr.select(c.inside, state.T * dr.maximum(1.0 - excess * inv_res, 0.0), state.T)
        state.null = _tally(state.null, dr.select(c.inside, 1, 0))
        if self.replay is not None:
            mu_c = c.mu_c
            state = self.replay.collision(state, c.x, c.look,
                                          lambda sigma_t: dr.maximum(1.0 - (sigma_t - mu_c) * inv_res, 0.0))
        state = self.roulette(state, c.inside)
        return state, alive & (state.T > 0.0)

    def passes(self, state, alive):
        # a segment's analytic factor and its roulette (`ResidualRatioTracking.enter`) may end a lane
        return alive & (state.T > 0.0)

    @staticmethod
    def roulette(state, where):
        """Russian roulette below RATIO_RR_THRESHOLD: go on with probability
        T / threshold and T = threshold, else stop with T = 0 (unbiased)."""
        low = where & (state.T < RATIO_RR_THRESHOLD)
        survive = state.rng.next_1d(low) * RATIO_RR_THRESHOLD < state.T
        state.T = dr.select(low, dr.select(survive, RATIO_RR_THRESHOLD, 0.0), state.T)
        return state

    def result(self, state, ray, end: WalkEnd) -> Transmittance:
        counts = TrackingCounts(_counted(state.lookups), _counted(state.null), mi.UInt32(0),
                                _counted(state.steps), dr.select(end.exhausted, 1, 0))
        return Transmittance(T=state.T, counts=counts, dlog=state.dlog)


@jit_struct(**RatioState.JIT_FIELDS, mu_c="Float")
class ResidualRatioState(RatioState):
    """Loop state of `ResidualRatioTracking`: `RatioState` and the
    segment's control extinction."""


class ResidualRatioTracking(RatioTracking):
    """Residual ratio tracking against the segments' minorants."""

    MOVING = RatioTracking.MOVING + ("mu_c", "T")

    def begin(self, ray, active):
        return ResidualRatioState(**vars(super().begin(ray, active)), mu_c=mi.Float(0.0))

    def control(self, state):
        return state.mu_c

    def enter(self, state, ray, seg, entered, t, seg_end):
        state = super().enter(state, ray, seg, entered, t, seg_end)
        state.mu_c = dr.select(entered, dr.clip(seg.mu_min, 0.0, seg.mu), state.mu_c)
        # the control part of this segment's transmittance, analytically
        state.T = dr.select(entered, state.T * dr.exp(-state.mu_c * (seg_end - t) * dr.rcp(ray.scale)), state.T)
        # and the same Russian roulette as at a collision once it falls below
        # RATIO_RR_THRESHOLD: a ray the minorants mostly block stops here (the
        # step ends a lane with T = 0); with mu_c = 0, T never falls here and
        # no number is drawn (the random numbers of plain ratio tracking)
        return self.roulette(state, entered)


# ---- The ray-wise majorant ----------------------------------------------------------
@jit_struct(found="Bool", t_first="Float", t_last="Float", t_seen="Float", mu_max="Float")
class SpanState(_Fields):
    """Loop state of `SpanMajorant`: whether a non-zero majorant was met,
    from where to where, the end of the last segment seen and the largest
    majorant."""


@jit_struct(found="Bool", t_first="Float", t_last="Float", mu="Float", capped="Bool")
class MajorantSpan(_Fields):
    """Result of `SpanMajorant`: ``found`` where the span holds a non-zero
    majorant, the span ``[t_first, t_last]`` (the world ray's ``t``,
    `LocalRay.world_t`), its majorant ``mu``, and ``capped`` where the walk
    was cut short (then the span runs on to ``t_hi`` with at least the
    global majorant)."""


class SpanMajorant:
    """The span from the start of the first to the end of the last segment
    with a non-zero majorant, and the largest majorant met.

    The walk's bound (its ``max_iterations``: one segment per iteration) is
    a number of segments; a walk cut short there falls back to a
    conservative answer: the span runs on to ``t_hi`` with the global
    majorant ``global_mu``."""

    label = "amr_span_majorant"
    MOVING = ("found", "t_first", "t_last", "t_seen", "mu_max")

    def __init__(self, global_mu, stop_share=None):
        self.global_mu = global_mu
        #: stop the walk once the largest majorant met reaches this share of
        #: the global one and answer the global majorant up to ``t_hi``
        #: (None: walk to the end)
        self.stop_share = stop_share

    def begin(self, ray, active):
        return SpanState(found=mi.Bool(False), t_first=mi.Float(ray.t_hi), t_last=mi.Float(ray.t_lo),
                         t_seen=mi.Float(ray.t_lo), mu_max=mi.Float(0.0))

    def enter(self, state, ray, seg, entered, t, seg_end):
        nonzero = entered & (seg.mu > 0.0)
        state.t_first = dr.select(nonzero & ~state.found, seg.t0, state.t_first)
        state.t_last = dr.select(nonzero, seg.t1, state.t_last)
        state.t_seen = dr.select(entered, seg.t1, state.t_seen)
        state.mu_max = dr.select(entered, dr.maximum(state.mu_max, seg.mu), state.mu_max)
        state.found |= nonzero
        return state

    def clock(self, state, ray, t, seg_end, moving):
        # no collisions: on to the segment's end (the last one ends at t_hi)
        return state, t, mi.Bool(False)

    def passes(self, state, alive):
        if self.stop_share is not None:
            return alive & (state.mu_max < self.stop_share * self.global_mu)
        return alive

    def collide_at(self, state, ray, t_c, inside, alive):
        return state, alive

    def result(self, state, ray, end: WalkEnd) -> MajorantSpan:
        cut = end.cut
        if self.stop_share is not None:
            # stopped at a majorant near the global one: the global one to t_hi
            cut |= state.found & (state.mu_max >= self.stop_share * self.global_mu)
        return MajorantSpan(found=state.found | (cut & (self.global_mu > 0.0)),
                            t_first=ray.world_t(dr.select(cut & ~state.found, state.t_seen, state.t_first)),
                            t_last=ray.world_t(dr.select(cut, ray.t_hi, state.t_last)),
                            mu=dr.select(cut, dr.maximum(state.mu_max, self.global_mu), state.mu_max),
                            capped=cut)
