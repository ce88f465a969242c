"""The ``amrvolpath`` integrator: Mitsuba's volpath with local majorants.

Same estimator as Mitsuba's ``volpath`` (unidirectional volumetric path
tracing, next-event estimation with ratio-tracked shadow rays, which here
play Russian roulette once their transmittance is small, MIS between
emitter and BSDF/phase sampling for emitters hit by chance, Russian
roulette, nested media and index-matched boundaries). For ``amr`` media,
free flights (delta tracking) and shadow rays (ratio tracking) run segment
by segment through the medium's traversal structure, each segment with its
own majorant, without restarting at null collisions. Every other medium goes
through ``Medium.sample_interaction`` exactly as in volpath.

``amr`` media that glow (an ``emission`` TF) add their emission ``sigma_a
L_e`` along every path segment through them, estimated at the segment's
real collision; stock volpath has no medium emission.

``mode`` chooses what a real collision in a medium does (the sci-vis
lighting modes of Zellmann et al.'s ExaBricks-style renderer):
``emission_absorption`` scores the TF colour (albedo) times a constant
``brightness`` and stops, whatever the lights (self-lit, as ParaView, VisIt
and yt render),
``single`` scores one next-event estimate and stops, ``multi`` (the default)
is volpath's estimator. The mode is a Python constant of the kernel.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..device.rng import Rng
from ..core.jit_struct import jit_struct
from ..device.tracking import TrackingCounts
from ..params import ParameterError, check_known, get_bool, get_float, get_int, get_string
from ..transfer.spectra import variant_kind
from .lighting_modes import LIGHTING_MODES, accumulate, local_surface_shading
from .medium import AMRMedium, require_jit_rgb_variant, scene_media
from .variant_class import VariantPlugin

#: Bound on the surfaces and media one shadow ray crosses (blocked beyond).
MAX_SHADOW_CROSSINGS = 4096
#: Free-flight look-ups, null and real collisions, traversal steps, loops
#: stopped by the iteration bound; then for shadow rays: look-ups, steps,
#: stopped loops and crossings of an amr medium (transmittance estimates).
COUNTER_NAMES = ("lookups", "null", "real", "steps", "capped",
                 "shadow_lookups", "shadow_steps", "shadow_capped", "shadow_crossings")
#: The parameters ``amrvolpath`` accepts (docs/manual/integrator.md's table and the
#: docstring's are tested against this set: tests/test_docs.py).
KNOWN = {"max_depth", "rr_depth", "hide_emitters", "counters",
         "residual_ratio_tracking", "decomposition_tracking", "mode", "brightness", "step_scale", "shading"}
#: The ray marcher's shadings (``shading``): the TF colour as it is, or
#: Blinn-Phong on the reconstruction's gradient (docs/design.md section 14).
SHADINGS = ("flat", "gradient")
#: The ray marcher's default step, in finest cells under each segment.
DEFAULT_STEP_SCALE = 0.5
#: The lighting modes (``mode``; docs/design.md section 6d), the default last:
#: what a real collision in a medium does.
MODES = tuple(LIGHTING_MODES)


def _mitsuba_helpers():
    """Mitsuba's power-heuristic MIS weight and RGB channel indexing (the
    ones its own Python volume integrators use), for the active variant:
    imported under ``mitsuba.python.ad``, the modules Mitsuba reloads on a
    variant change (``mitsuba.ad.*`` keeps the first variant's classes)."""
    from mitsuba.python.ad.integrators.common import mis_weight
    from mitsuba.python.ad.integrators.prbvolpath import index_spectrum
    return mis_weight, index_spectrum


@jit_struct(o="Point3f", d="Vector3f", max_dist="Float", time="Float", wavelengths="Color0f",
            medium="MediumPtr", rng=Rng, active="Bool")
class ShadowStart:
    """Where a shadow ray starts (world space): origin, unit direction,
    distance to the emitter sample, time, wavelengths, medium, its random
    stream (None without media) and live lanes."""

    def __init__(self, o=None, d=None, max_dist=None, time=None, wavelengths=None, medium=None, rng=None,
                 active=None):
        self.o, self.d, self.max_dist, self.time, self.wavelengths = o, d, max_dist, time, wavelengths
        self.medium, self.rng, self.active = medium, rng, active


def absorbed_share(albedo):
    """``1 - albedo``, the share of extinction that absorbs (and emits);
    clamped at 0 in spectral variants, where Mitsuba's upsampling of a
    colour (``gridvolume``'s, which the albedo follows) can exceed 1 at
    some wavelengths."""
    share = 1.0 - albedo
    return dr.maximum(share, 0.0) if variant_kind() == "spectral" else share


class AMRVolpathIntegrator(metaclass=VariantPlugin, base="SamplingIntegrator"):
    r"""
    AMR volumetric path tracer (:monosp:`amrvolpath`)
    -------------------------------------------------

    A drop-in replacement for ``volpath`` that tracks through the local
    majorants of ``amr`` media.

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: infinite). Default: -1.
     * - rr_depth
       - |int|
       - Depth from which Russian roulette starts. Default: 5.
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. Default: false.
     * - counters
       - |bool|
       - Count density look-ups, null and real collisions and traversal
         steps per render (see `counters()`). Default: false (no cost).
     * - residual_ratio_tracking
       - |bool|
       - Shadow rays track only the residual above each segment's
         minorant; the minorant's part of the transmittance is exact.
         Default: per medium, on where its minorants carry at least half of
         its majorants at load (``minorants_pay``), where it pays; off
         elsewhere, where each segment's minorant costs more frame time than
         it saves (docs/performance/minorants.md). With zero minorants it is
         plain ratio tracking.
     * - decomposition_tracking
       - |bool|
       - Free flights sample collisions with the minorant analytically
         (real with probability one) and track only the residual. Default:
         per medium, as ``residual_ratio_tracking``. With zero minorants it
         is plain delta tracking.
     * - mode
       - |string|
       - What a real collision in a medium does (the lighting modes of
         sci-vis volume renderers). ``emission_absorption``: the path stops
         there and scores the collision's albedo (the TF colour) times
         ``brightness``, whatever the lights, the environment and the view
         direction: the expectation is the emission-absorption integral
         with emission sigma_t times the colour and absorption sigma_t, as
         ParaView, VisIt and yt render it (self-lit colours).
         ``single``: one shadow ray towards one emitter chosen at random
         (Mitsuba's emitter sampling, ratio-tracked transmittance), the
         phase function's value times its light with no MIS weight, then
         the path stops (single scattering). ``multi``: multiple scattering,
         volpath's estimator (NEE with MIS, phase sampling, Russian
         roulette). In every mode free flights use the same segments and
         majorants (delta tracking), a glowing medium adds its emission at
         the collision, a ray that leaves the media sees the emitters and
         the background as usual, and surfaces are lit as in ``multi``.
         Default: ``multi``.
         ``ray_march``: the sci-vis ray marcher (ExaBricks' renderer): each
         amr medium is marched front to back in steps of ``step_scale``
         times the finest cell under each traversal leaf (empty leaves
         skipped; with ``nearest`` reconstruction the steps end on cell
         faces and the integral is exact), compositing the TF colour times
         ``brightness`` with each step's exact absorption: the integral
         ``emission_absorption`` estimates, without its noise; the ray then
         goes on with the medium's transmittance.
     * - brightness
       - |float|
       - The constant that multiplies the TF colour of ``emission_absorption``
         and ``ray_march`` (>= 0; other modes ignore it). Default: 1.
     * - step_scale
       - |float|
       - ``ray_march``: the step, in cells of the finest level under each
         traversal leaf (> 0; smaller is more accurate and slower; one
         jittered offset per ray). Default: 0.5.
     * - shading
       - |string|
       - ``ray_march``: ``flat`` (the TF colour) or ``gradient`` (the
         sci-vis style: Blinn-Phong with the normalised gradient of the
         reconstruction, lit by the scene's first directional or point
         light, or a headlight when it has none; no shadow rays).
         Default: ``flat``.
    """

    def __init__(self, props: mi.Properties):
        require_jit_rgb_variant("the 'amrvolpath' integrator")
        type(self).__base__.__init__(self, props)
        check_known(props, "amrvolpath", KNOWN)
        self._parse_path_options(props, "amrvolpath")
        self.counters_enabled = get_bool(props, "amrvolpath", "counters", False)
        # None: decided per medium (`AMRMedium.minorants_pay`)
        self.residual = get_bool(props, "amrvolpath", "residual_ratio_tracking", None)
        self.decomposition = get_bool(props, "amrvolpath", "decomposition_tracking", None)
        self._counter_array = dr.zeros(mi.UInt64, len(COUNTER_NAMES))

    def _parse_path_options(self, props, plugin: str, modes: tuple = MODES):
        """``max_depth``, ``rr_depth``, ``hide_emitters``, ``mode`` (one of
        ``modes``) and the ray marcher's ``step_scale`` and ``shading``."""
        md = get_int(props, plugin, "max_depth", -1)
        if md < -1:
            raise ParameterError(f"{plugin}: max_depth must be -1 (infinite) or >= 0, got {md}")
        self.max_depth = 0xFFFFFFFF if md == -1 else md
        self.rr_depth = get_int(props, plugin, "rr_depth", 5, minimum=1)
        self.hide_emitters = get_bool(props, plugin, "hide_emitters", False)
        # a Python constant: it shapes the kernel (docs/design.md section 6d)
        self.mode = get_string(props, plugin, "mode", "multi", choices=modes)
        # opaque: another brightness or step compiles nothing
        self.brightness = dr.opaque(mi.Float, get_float(props, plugin, "brightness", 1.0, minimum=0.0))
        step = get_float(props, plugin, "step_scale", DEFAULT_STEP_SCALE)
        if not step > 0.0:
            raise ParameterError(f"{plugin}: step_scale must be > 0, got {step}")
        self.step_scale = dr.opaque(mi.Float, step)
        self.shading = get_string(props, plugin, "shading", "flat", choices=SHADINGS)

    # ---- Counters ------------------------------------------------------------
    def reset_counters(self):
        self._counter_array = dr.zeros(mi.UInt64, len(COUNTER_NAMES))

    def counters(self) -> dict:
        """Totals since the last `reset_counters` (or construction), with
        ``lookups_per_collision`` = free-flight look-ups / real collisions,
        ``null_per_collision`` = free-flight null collisions / real collisions
        and ``lookups_per_shadow_ray`` = shadow look-ups / crossings of an amr
        medium by shadow rays."""
        vals = self._counter_array.numpy()
        out = {k: int(v) for k, v in zip(COUNTER_NAMES, vals)}
        out["lookups_per_collision"] = out["lookups"] / out["real"] if out["real"] else float("nan")
        out["null_per_collision"] = out["null"] / out["real"] if out["real"] else float("nan")
        out["lookups_per_shadow_ray"] = (out["shadow_lookups"] / out["shadow_crossings"]
                                         if out["shadow_crossings"] else float("nan"))
        return out

    def _count(self, free: TrackingCounts, shadow: TrackingCounts):
        if not self.counters_enabled:
            return
        values = (free.lookups, free.null, free.real, free.steps, free.capped,
                  shadow.lookups, shadow.steps, shadow.capped, shadow.real)
        for i, v in enumerate(values):
            dr.scatter_reduce(dr.ReduceOp.Add, self._counter_array, mi.UInt64(v), mi.UInt32(i))

    def _margin(self, medium):
        """Raised majorants for the walks through ``medium``: none here
        (the differentiable form's, `AMRPRBVolpathIntegrator`)."""
        return None

    @staticmethod
    def _uses_minorants(option, medium) -> bool:
        """An estimator option as given, or the medium's own choice."""
        return medium.minorants_pay if option is None else option

    # ---- Scene analysis ---------------------------------------------------------
    @staticmethod
    def _media(scene):
        """(amr media, whether any other medium exists) in the scene."""
        media = scene_media(scene)
        return ([m for m in media if isinstance(m, AMRMedium)],
                any(not isinstance(m, AMRMedium) for m in media))

    # ---- Radiance ------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        self._refuse_gradients(scene)
        L, valid_ray, _ = self._trace(scene, sampler, ray, medium, active)
        return L, valid_ray, []

    def _refuse_gradients(self, scene):
        """A `ParameterError` when this primal estimator is differentiated
        (an ``amr`` medium's density scale, TF table or cell values carry
        gradients while it traces: ``dr.backward``/``dr.forward`` through
        ``mi.render``). Its free flights use detached majorants and no
        replay, so automatic differentiation through it gives a wrong
        gradient (7x too small on the test field), never a right one:
        ``amrprbvolpath`` differentiates these media (docs/design.md
        section 13b). A primal render (Mitsuba suspends gradients) passes."""
        media, _ = self._media(scene)
        for m in media:
            c = m.classification
            if any(dr.grad_enabled(v) for v in (c.scale, c.tf_rgba, m._values)):
                raise ParameterError(
                    "amrvolpath: an amr medium's parameters carry gradients, and this integrator does not "
                    "differentiate them (its gradient would be wrong): use the 'amrprbvolpath' integrator")

    @dr.syntax
    def _trace(self, scene, sampler, ray, medium=None, active=True, adjoint=None):
        """The path estimator: ``(L, valid_ray, dL)``. ``adjoint`` (a
        `PathAdjoint`, or None for the primal) makes it the replay pass of
        path-replay backpropagation (docs/design.md section 13b): the same
        random numbers and paths, ``L`` starts at the primal's radiance and
        loses each contribution as the path passes it (the radiance still to
        come), and every factor of an amr medium's parameters sends its
        derivative on (backward mode) or adds its tangent to ``dL``
        (forward mode; None otherwise)."""
        mis_weight, index_spectrum = _mitsuba_helpers()
        # what a real collision does: the mode consumes the walk's events
        # at three places (`mi_amr.plugins.lighting_modes`)
        lighting = LIGHTING_MODES[self.mode]
        amr_media, has_other = self._media(scene)
        amr_ptrs = [mi.MediumPtr(m) for m in amr_media]
        # whether any amr medium has isosurfaces (a Python constant of the kernel:
        # scenes without them trace no surface search, docs/design.md section 15)
        any_iso = any(m.has_iso for m in amr_media)

        ray = mi.Ray3f(ray)
        L = mi.Spectrum(0.0) if adjoint is None else mi.Spectrum(adjoint.L)
        # forward mode: the tangent of the radiance, summed along the path
        dL = mi.Spectrum(0.0) if (adjoint is not None and adjoint.forward) else None
        throughput = mi.Spectrum(1.0)
        eta = mi.Float(1.0)
        depth = mi.UInt32(0)
        active = mi.Bool(active)
        valid_ray = mi.Bool(False)
        specular_chain = mi.Bool(True)
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        last_event = dr.zeros(mi.Interaction3f)
        last_pdf = mi.Float(1.0)
        medium = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        n_channels = dr.size_v(mi.UnpolarizedSpectrum)          # 3 in rgb, 4 in spectral, 1 in mono
        channel = mi.UInt32(dr.minimum(float(n_channels) * sampler.next_1d(active), n_channels - 1.0))
        # Random numbers of the path: with Mitsuba's independent sampler, a
        # stream of our own with the same distribution (PCG32, seeded from
        # the sampler), so that no loop state holds an unchanged variable
        # and the path loop is recorded once (docs/design.md section 6);
        # any other sampler (stratified, low-discrepancy) is used as it is.
        rng = Rng.derive(sampler, active) if sampler.class_name() == "IndependentSampler" else sampler
        # the event counts, None (Python constants, no loop variables) unless counted
        counts = TrackingCounts() if self.counters_enabled else None
        shadow_counts = TrackingCounts() if self.counters_enabled else None

        # read-only names stay out of the loop state (docs/design.md section
        # 6); a sampler other than the independent one is carried as `rng`,
        # and its unchanged stream increment makes Dr.Jit record the loop twice
        while dr.hint(active, label="amrvolpath",
                      exclude=[self, scene, sampler, amr_media, amr_ptrs, has_other, channel, mis_weight,
                               index_spectrum, adjoint, lighting, any_iso]):
            # ---- Russian roulette (as in volpath) ----
            q = dr.minimum(dr.max(throughput) * dr.square(eta), 0.95)
            perform_rr = depth > self.rr_depth
            active &= (rng.next_1d(active) < q) | ~perform_rr
            throughput = dr.select(perform_rr, throughput * dr.rcp(q), throughput)
            active &= dr.any(throughput != 0.0)

            # ---- Surface along the ray (bounds the medium segment) ----
            intersect = active & needs_intersection
            si[intersect] = scene.ray_intersect(ray, intersect)
            needs_intersection &= ~intersect

            active_medium = active & (medium != None)  # noqa: E711
            act_scatter = mi.Bool(False)
            act_null = mi.Bool(False)
            mei = dr.zeros(mi.MediumInteraction3f)

            # ---- isosurfaces of amr media (docs/design.md section 15): the
            # first one ahead is the surface that ends the medium segment ----
            iso_at = mi.Bool(False)
            iso_bsdf = dr.zeros(mi.BSDFPtr)
            for k in range(len(amr_media) if any_iso else 0):
                if dr.hint(amr_media[k].has_iso, mode="scalar"):
                    is_k = active_medium & (medium == amr_ptrs[k])
                    hit = amr_media[k].iso_hit(ray, si.t, is_k)
                    closer = is_k & hit.found & (hit.t < si.t)
                    si[closer] = self._iso_interaction(ray, hit)
                    iso_bsdf[closer] = amr_media[k].iso_bsdf(hit.slot, closer)
                    iso_at |= closer

            # ---- amr media: the ray marcher's steps (docs/design.md section 14) ----
            if dr.hint(lighting.marches, mode="scalar"):
                light = self._march_light(scene, ray)
                for k in range(len(amr_media)):
                    is_k = active_medium & (medium == amr_ptrs[k])
                    marched = amr_media[k].march(ray, si.t, rng, is_k, self.step_scale, self.brightness, light,
                                                 self.counters_enabled)
                    if dr.hint(self.counters_enabled, mode="scalar"):
                        counts = counts + marched.counts
                    L = accumulate(L, is_k, throughput * marched.L, adjoint)
                    throughput[is_k] *= marched.T

            # ---- amr media: delta tracking through local majorants ----
            for k in range(len(amr_media) if not lighting.marches else 0):
                is_k = active_medium & (medium == amr_ptrs[k])
                control = self._uses_minorants(self.decomposition, amr_media[k])
                replay = None
                if dr.hint(adjoint is not None, mode="scalar"):
                    # the flight's null collisions scale all radiance still to come
                    replay = amr_media[k].replay(adjoint.mode, adjoint.weight(L))
                flight = amr_media[k].free_flight(ray, si.t, rng, is_k, control, self.counters_enabled, replay,
                                                  self._margin(amr_media[k]))
                if dr.hint(dL is not None, mode="scalar"):
                    dL[is_k] += L * flight.dlog
                if dr.hint(self.counters_enabled, mode="scalar"):
                    counts = counts + flight.counts
                real = is_k & flight.collided
                mei[real] = self._medium_interaction(ray, flight, amr_ptrs[k])
                if dr.hint(amr_media[k].glows, mode="scalar"):
                    # emission, collision estimator: a real collision falls at
                    # t with density T(t) sigma_t(t), so adding sigma_a/sigma_t
                    # L_e = (1 - albedo) L_e there estimates the integral of
                    # T sigma_a L_e along the segment (docs/design.md section 12)
                    L = accumulate(L, real, throughput * absorbed_share(flight.albedo)
                                   * amr_media[k].emitted_radiance_at(flight, mei.p, real, ray.wavelengths), adjoint)
                if dr.hint(adjoint is not None, mode="scalar"):
                    tangent = adjoint.collision(amr_media[k], mei.p, real, flight, throughput, L, ray.wavelengths)
                    if dr.hint(dL is not None, mode="scalar"):
                        dL += tangent
                throughput[real] *= flight.albedo        # sigma_s / sigma_t
                act_scatter |= real

            # ---- other media: Mitsuba's sample_interaction, as in volpath ----
            if dr.hint(has_other, mode="scalar"):
                is_other = active_medium
                for p in amr_ptrs:
                    is_other &= medium != p
                m_other = medium.sample_interaction(ray, rng.next_1d(is_other), channel, is_other)
                m_other.t[is_other & (si.t < m_other.t)] = dr.inf
                tr, ff_pdf = medium.transmittance_eval_pdf(m_other, si, is_other)
                tr_pdf = index_spectrum(ff_pdf, channel)
                throughput[is_other] *= dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)
                valid_o = is_other & m_other.is_valid()
                p_real = index_spectrum(m_other.sigma_t, channel) / index_spectrum(m_other.combined_extinction, channel)
                null_o = valid_o & (rng.next_1d(valid_o) >= p_real)
                real_o = valid_o & ~null_o
                throughput[null_o] *= m_other.sigma_n / (1.0 - p_real)
                throughput[real_o] *= m_other.sigma_s / p_real
                mei[valid_o] = m_other
                act_scatter |= real_o
                act_null |= null_o
                # continue from the null collision: keep the surface hit
                ray.o[null_o] = m_other.p
                si.t[null_o] = si.t - m_other.t

            escaped_medium = active_medium & ~act_scatter & ~act_null
            depth[act_scatter] += 1
            last_event[act_scatter] = mei
            active &= depth < self.max_depth
            act_scatter &= active

            # ---- Lighting mode, at the collisions (docs/design.md section 6d) ----
            L, act_scatter = lighting.collided(L, act_scatter, throughput, self.brightness, adjoint)

            # ---- Medium scattering: the phase function (NEE below) ----
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            phase[~act_scatter] = dr.zeros(mi.PhaseFunctionPtr)
            sample_emitters = mei.medium.use_emitter_sampling()
            specular_chain &= ~act_scatter
            specular_chain |= act_scatter & ~sample_emitters
            nee_m = act_scatter & sample_emitters

            # ---- Surfaces (and rays that left their medium): emitters hit ----
            active_surface = (active & ~active_medium) | (escaped_medium & active)
            emitter = si.emitter(scene)
            active_e = active_surface & (emitter != None)  # noqa: E711
            if dr.hint(self.hide_emitters, mode="scalar"):
                active_e &= ~(depth == 0)
            ds_hit = mi.DirectionSample3f(scene, si, last_event)
            em_pdf = scene.pdf_emitter_direction(last_event, ds_hit, active_e & ~specular_chain)
            count_direct = (depth == 0) | specular_chain
            mis = dr.select(count_direct, 1.0, mis_weight(last_pdf, em_pdf))
            L = accumulate(L, active_e, throughput * emitter.eval(si, active_e) * mis, adjoint)

            active_surface &= si.is_valid()
            ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)
            iso_surface = active_surface & iso_at
            if dr.hint(any_iso, mode="scalar"):
                bsdf[iso_surface] = iso_bsdf
            nee_s = active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < self.max_depth)
            if dr.hint(lighting.marches or (lighting.shades_iso_locally and any_iso), mode="scalar"):
                # the ray marcher shades a surface of smooth lobes locally, as
                # its samples (no light sample, no bounce): a deterministic
                # picture; null, delta and emitting surfaces are as ever.
                # emission_absorption shades its isosurfaces so (self-lit
                # colours of the sci-vis modes) and lights other surfaces as multi
                local = nee_s if lighting.marches else nee_s & iso_surface
                light = self._march_light(scene, ray, local=True)
                L = accumulate(L, local, throughput * self.brightness * local_surface_shading(
                    bsdf.eval_diffuse_reflectance(si, local), si.sh_frame.n, light(si.p, local), -ray.d), adjoint)
                active_surface &= ~local
                nee_s &= ~local

            # ---- NEE, one call for medium and surface vertices ----
            # (a lane is one or the other: one shadow loop in the kernel and
            # in the trace, which runs for both kinds of lane together)
            if dr.hint(len(scene.emitters()) > 0, mode="scalar"):
                ref = dr.select(nee_m, mi.Interaction3f(mei), mi.Interaction3f(si))
                emitted, ds, c, shadow = self._sample_emitter(ref, scene, rng, medium, channel,
                                                              nee_m | nee_s, amr_media, amr_ptrs, has_other)
                if dr.hint(self.counters_enabled, mode="scalar"):
                    shadow_counts = shadow_counts + c
                phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, nee_m)
                nee_weight_m = lighting.medium_nee_weight(phase_val, phase_pdf, ds, mis_weight)
                bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), nee_s)
                nee_weight_s = bsdf_val * mis_weight(ds.pdf, dr.select(ds.delta, 0.0, bsdf_pdf))
                L = accumulate(L, nee_m, throughput * nee_weight_m * emitted, adjoint)
                L = accumulate(L, nee_s, throughput * nee_weight_s * emitted, adjoint)
                if dr.hint(adjoint is not None, mode="scalar"):
                    # the shadow ray's factors scale its own contribution: its
                    # walks again, from the same random numbers
                    nee = dr.select(nee_m, throughput * nee_weight_m * emitted,
                                    dr.select(nee_s, throughput * nee_weight_s * emitted, 0.0))
                    dlog = self._shadow(scene, ds, shadow, channel, amr_media, amr_ptrs, has_other,
                                        adjoint, adjoint.weight(nee))[2]
                    if dr.hint(dL is not None, mode="scalar"):
                        dL += nee * dlog

            if dr.hint(not lighting.continues, mode="scalar"):
                act_scatter &= False                     # the mode stops the path after the light sample

            # ---- Next direction: phase sampling in media, BSDF sampling at surfaces ----
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, rng.next_1d(act_scatter),
                                                       rng.next_2d(act_scatter), act_scatter)
            act_scatter &= phase_pdf > 0.0
            throughput[act_scatter] *= phase_weight
            ray[act_scatter] = mei.spawn_ray(wo)
            needs_intersection |= act_scatter
            last_pdf[act_scatter] = phase_pdf
            valid_ray |= act_scatter

            bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_1d(active_surface),
                                          rng.next_2d(active_surface), active_surface)
            active_surface &= bs.pdf > 0.0
            throughput[active_surface] *= bsdf_weight
            eta[active_surface] *= bs.eta
            ray[active_surface] = si.spawn_ray(si.to_world(bs.wo))
            needs_intersection |= active_surface
            non_null = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[non_null] += 1
            last_event[non_null] = si
            last_pdf[non_null] = bs.pdf
            valid_ray |= non_null
            specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            transition = active_surface & si.is_medium_transition()
            medium[transition] = si.target_medium(ray.d)
            active &= active_surface | act_scatter | act_null

        self._count(counts, shadow_counts)
        return L, valid_ray, dL

    def _march_light(self, scene, ray, local: bool = False):
        """The light of the ray marcher's local shading: ``light(p, active)
        -> unit direction towards it`` from world points, for the scene's
        first directional or point emitter (its delta sample), else a
        headlight along ``-ray.d``. None for the samples of flat shading
        (unless ``local``: the light of the surfaces it shades)."""
        if self.shading != "gradient" and not local:
            return None
        delta = mi.EmitterFlags.DeltaDirection | mi.EmitterFlags.DeltaPosition
        emitter = next((e for e in scene.emitters() if mi.has_flag(e.flags(), delta)), None)
        if emitter is None:
            head = -dr.normalize(ray.d)
            return lambda p, active: head

        def light(p, active):
            it = dr.zeros(mi.Interaction3f)
            it.p = p
            ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), active)
            return ds.d
        return light

    @staticmethod
    def _iso_interaction(ray, hit):
        """The surface interaction at an isosurface hit (`IsoHit`): no shape
        (no emitter, no medium transition: the path stays in its medium),
        the shading frame on the surface's normal."""
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.t = hit.t
        si.p = hit.p
        si.n = mi.Normal3f(hit.n)
        si.sh_frame = mi.Frame3f(si.n)
        si.dp_du, si.dp_dv = si.sh_frame.s, si.sh_frame.t
        si.wi = si.to_local(-ray.d)
        si.time = ray.time
        si.wavelengths = ray.wavelengths
        return si

    @staticmethod
    def _medium_interaction(ray, flight, ptr):
        """The interaction at a free flight's real collision (`FreeFlight`)."""
        mei = dr.zeros(mi.MediumInteraction3f)
        mei.t = flight.t
        mei.p = ray(flight.t)
        mei.wi = -ray.d
        mei.sh_frame = mi.Frame3f(mei.wi)
        mei.time = ray.time
        mei.wavelengths = ray.wavelengths
        mei.medium = ptr
        mei.sigma_t = mi.UnpolarizedSpectrum(flight.sigma_t)
        mei.sigma_s = flight.albedo * flight.sigma_t
        mei.combined_extinction = mi.UnpolarizedSpectrum(flight.sigma_t)
        return mei

    @dr.syntax
    def _sample_emitter(self, ref, scene, source, medium, channel, active,
                        amr_media, amr_ptrs, has_other):
        """Next-event estimation: an emitter sample and its transmittance
        through media (ratio tracking) and index-matched surfaces:
        ``(emitted, ds, counts, shadow)``, ``shadow`` the shadow ray's start
        (`ShadowStart`) for a replay of its walk. ``source``: the path's
        random numbers (an `Rng` or the Mitsuba sampler)."""
        active = mi.Bool(active)
        ds, emitter_val = scene.sample_emitter_direction(ref, source.next_2d(active), False, active)
        active &= ds.pdf != 0.0
        first = ref.spawn_ray_to(ds.p)
        # the loop state holds only what the loop changes (docs/design.md
        # section 6): the ray's origin and direction, not its time, and a
        # random stream of our own rather than the sampler
        rng = Rng.derive(source, active) if (amr_media or has_other) else None
        shadow = ShadowStart(o=mi.Point3f(first.o), d=mi.Vector3f(first.d), max_dist=mi.Float(first.maxt),
                             time=first.time, wavelengths=first.wavelengths, medium=mi.MediumPtr(medium),
                             rng=rng, active=active)
        T, counts, _ = self._shadow(scene, ds, shadow, channel, amr_media, amr_ptrs, has_other)
        return emitter_val * T, ds, counts, shadow

    @dr.syntax
    def _shadow(self, scene, ds, start, channel, amr_media, amr_ptrs, has_other, adjoint=None, weight=None):
        """The shadow ray's walk from ``start`` to ``ds.p``: ``(T, counts,
        dlog)``. With ``adjoint`` (a replay from the same start and random
        numbers) each amr medium's ratio tracking differentiates its factors,
        backward with ``weight`` (the adjoint radiance times the
        contribution, per lane) or forward into ``dlog`` (None otherwise)."""
        _, index_spectrum = _mitsuba_helpers()
        ray_o, ray_d, max_dist = mi.Point3f(start.o), mi.Vector3f(start.d), start.max_dist
        time, wavelengths = start.time, start.wavelengths
        rng = None if start.rng is None else Rng(mi.UInt64(start.rng.state))
        active = mi.Bool(start.active)
        total = mi.Float(0.0)
        T = mi.Spectrum(1.0)
        medium = mi.MediumPtr(start.medium)
        counts = TrackingCounts() if self.counters_enabled else None
        dlog = mi.Float(0.0) if (adjoint is not None and adjoint.forward) else None
        it = mi.UInt32(0)
        while dr.hint(active, label="amrvolpath_shadow",
                      exclude=[self, scene, ds, max_dist, time, wavelengths, amr_media, amr_ptrs, has_other,
                               channel, index_spectrum, adjoint, weight]):
            remaining = max_dist - total
            ray = mi.Ray3f(ray_o, ray_d, remaining, time, wavelengths)
            active &= remaining > 0.0
            si = scene.ray_intersect(ray, active)
            seg = dr.minimum(si.t, remaining)
            in_medium = active & (medium != None)  # noqa: E711
            moved = mi.Bool(False)
            for k in range(len(amr_media)):
                is_k = in_medium & (medium == amr_ptrs[k])
                if dr.hint(amr_media[k].has_iso, mode="scalar"):
                    # an isosurface is opaque: it blocks the light behind it
                    blocked = is_k & amr_media[k].iso_hit(ray, seg, is_k).found
                    T[blocked] = 0.0
                    is_k &= ~blocked
                control = self._uses_minorants(self.residual, amr_media[k])
                replay = None if adjoint is None else amr_media[k].replay(adjoint.mode, weight)
                estimate = amr_media[k].transmittance(ray, seg, rng, is_k, control, self.counters_enabled, replay,
                                                      self._margin(amr_media[k]))
                if dr.hint(self.counters_enabled, mode="scalar"):
                    c = estimate.counts
                    c.real = mi.UInt32(dr.select(is_k, 1, 0))      # shadow counts: crossings
                    counts = counts + c
                if dr.hint(dlog is not None, mode="scalar"):
                    dlog[is_k] += estimate.dlog
                T[is_k] *= estimate.T
            if dr.hint(has_other, mode="scalar"):
                is_other = in_medium
                for p in amr_ptrs:
                    is_other &= medium != p
                ray_m = mi.Ray3f(ray)
                ray_m.maxt = seg
                m_o = medium.sample_interaction(ray_m, rng.next_1d(is_other), channel, is_other)
                hit_o = is_other & m_o.is_valid() & (m_o.t < seg)
                # spectral media: analytic transmittance up to the next event
                spectral = is_other & medium.has_spectral_extinction()
                t_end = dr.select(hit_o, m_o.t, seg)
                tr = dr.exp(-(t_end - dr.maximum(m_o.mint, 0.0)) * m_o.combined_extinction)
                tr_pdf = dr.select(hit_o, index_spectrum(tr * m_o.combined_extinction, channel), index_spectrum(tr, channel))
                T[spectral & (dr.isfinite(m_o.mint))] *= dr.select(tr_pdf > 0.0, tr / tr_pdf, 0.0)
                T[hit_o] *= dr.select(spectral, m_o.sigma_n, m_o.sigma_n / m_o.combined_extinction)
                ray_o[hit_o] = m_o.p
                total[hit_o] += m_o.t
                moved |= hit_o
            # ---- the surface (or the emitter) at the end of the segment ----
            at_surface = active & ~moved & si.is_valid() & (si.t < remaining)
            bsdf = si.bsdf(ray)
            T[at_surface] *= bsdf.eval_null_transmission(si, at_surface)
            total[at_surface] += si.t
            onward = si.spawn_ray_to(ds.p)
            ray_o[at_surface] = onward.o
            ray_d[at_surface] = onward.d
            medium[at_surface & si.is_medium_transition()] = si.target_medium(onward.d)
            active &= (at_surface | moved) & dr.any(T != 0.0)
            it += 1
            # bound on the surfaces and media crossed: a shadow ray cut short
            # there counts as blocked (never leaks light) and is reported
            cut = active & (it >= MAX_SHADOW_CROSSINGS)
            T[cut] = 0.0
            if dr.hint(self.counters_enabled, mode="scalar"):
                counts.capped += dr.select(cut, 1, 0)
            active &= ~cut
        return T, counts, dlog


def integrator_class():
    """The ``amrvolpath`` integrator class of the active variant."""
    return AMRVolpathIntegrator.variant_class()
