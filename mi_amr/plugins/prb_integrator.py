"""The ``amrprbvolpath`` integrator: ``amrvolpath`` made differentiable by
path replay backpropagation (Vicini et al. 2021), as Mitsuba's
``prbvolpath`` is for ``volpath`` (docs/design.md section 13b).

The primal pass is ``amrvolpath``'s estimator with plain delta and ratio
tracking through the local majorants, raised by a margin (`MajorantMargin`:
a majorant equal to sigma_t, or 0, would hide the derivative of sigma_t),
without the minorant estimators (whose control collisions would need
gradients of their own). The replay pass walks the
same paths with the same random numbers; ``L`` is then the radiance still
to come, and each factor that depends on an ``amr`` medium's parameters
(density scale, TF, emission, cell values) is differentiated with the
majorants held fixed:

* a null collision of a free flight scales what follows by ``sigma_n = mu -
  sigma_t``; the walk looks ``sigma_t`` up again with gradients there
  (`mi_amr.device.tracking.Replay`);
* a real collision scales what follows by ``sigma_s / sigma_t`` (the
  albedo; ``sigma_t`` is the sampling density's) and adds ``sigma_a /
  sigma_t * L_e`` for a glowing medium;
* a shadow ray's ratio-tracking factors ``1 - sigma_t / mu`` scale its own
  contribution, known once its first walk is done: the replay walks the
  shadow ray twice, the second time differentiating.

Gradients flow to the ``amr`` media's parameters only; other media, BSDFs,
emitters and the phase function are not differentiated (Mitsuba's
``prbvolpath`` for those).
"""

from __future__ import annotations

from types import SimpleNamespace

import drjit as dr
import mitsuba as mi

from ..device.tracking import GRADIENT_FLOOR, GRADIENT_MARGIN
from ..params import ParameterError, check_known, get_float
from .integrator import AMRVolpathIntegrator, MODES, absorbed_share
from .medium import require_jit_rgb_variant
from .variant_class import VariantPlugin

#: The parameters ``amrprbvolpath`` accepts.
#: The lighting modes path replay differentiates: every mode but the ray
#: marcher, which has no collision weights to replay.
REPLAYED_MODES = tuple(m for m in MODES if m != "ray_march")
KNOWN = {"max_depth", "rr_depth", "hide_emitters", "mode", "brightness", "majorant_margin", "majorant_floor"}


def _rb_base():
    """Mitsuba's base class of path-replay integrators, for the active variant
    (from ``mitsuba.python.ad``, which Mitsuba reloads on a variant change)."""
    from mitsuba.python.ad.integrators.common import RBIntegrator
    return RBIntegrator


class PathAdjoint:
    """The replay pass's state that is not per path vertex: the AD mode,
    the adjoint radiance ``δL`` (backward mode) and the primal radiance
    ``L`` the replay starts from."""

    def __init__(self, mode, dL, L):
        self.mode, self.dL, self.L = mode, dL, L

    @property
    def forward(self) -> bool:
        return self.mode == dr.ADMode.Forward

    def weight(self, radiance):
        """Per lane, the adjoint radiance times ``radiance`` summed over
        channels (backward mode; None in forward mode)."""
        return None if self.forward else dr.sum(self.dL * radiance)

    def collision(self, medium, p, real, flight, throughput, L, wavelengths=None):
        """The derivative of a real collision at world points ``p`` (lanes
        ``real``) of ``flight`` in ``medium``: ``throughput`` before the
        collision, ``L`` the radiance still to come after its emission.
        Backward mode sends it to the parameters and returns 0; forward mode
        returns the radiance's tangent."""
        with dr.resume_grad():
            albedo, sigma_t = medium.eval_world(p, real, wavelengths)
            primal = dr.detach(sigma_t)
            ok = real & (primal > 0.0)
            inv = dr.rcp(dr.select(ok, primal, 1.0))
            # sigma_s / sigma_t with the denominator fixed: the albedo in
            # value, d sigma_s / sigma_t in derivative; it scales what follows
            after = dr.select(ok & (flight.albedo > 0.0), L * dr.rcp(dr.select(flight.albedo > 0.0, flight.albedo,
                                                                                1.0)), 0.0)
            terms = albedo * sigma_t * inv * after
            if medium.glows:
                terms += (throughput * absorbed_share(albedo) * sigma_t * inv
                          * medium.emitted_radiance(p, ok, wavelengths))
            terms = dr.select(ok, terms, 0.0)
            if not dr.grad_enabled(terms):
                return mi.Spectrum(0.0)
            if self.forward:
                return dr.forward_to(terms)
            dr.backward_from(self.dL * terms)
        return mi.Spectrum(0.0)


class AMRPRBVolpathIntegrator(AMRVolpathIntegrator, metaclass=VariantPlugin, base=_rb_base):
    r"""
    Differentiable AMR volumetric path tracer (:monosp:`amrprbvolpath`)
    -------------------------------------------------------------------

    ``amrvolpath`` with path replay backpropagation: ``mi.render`` and
    ``dr.backward``/``dr.forward`` give gradients of an image with respect
    to the ``amr`` media's parameters (``density_scale``, ``tf_rgba``,
    ``emission_rgba``, ``emission_scale``, ``values``).

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
     * - mode
       - |string|
       - ``emission_absorption``, ``single`` or ``multi``, as in
         ``amrvolpath`` (not ``ray_march``, which has no collision weights to
         replay). Default: ``multi``.
     * - brightness
       - |float|
       - The constant on the TF colour of ``emission_absorption``, as in
         ``amrvolpath``. Default: 1.
     * - majorant_margin
       - |float|
       - Factor (> 1) on every leaf's majorant in the walks, so that a
         leaf whose majorant equals sigma_t still samples null collisions,
         which carry the derivative of sigma_t. Default: 1.5.
     * - majorant_floor
       - |float|
       - Added to every leaf's majorant, as a share (in (0, 1]) of the
         medium's global majorant, so that leaves of zero extinction are
         looked up too (an opacity of 0 has a derivative). Default: 0.05.
    """

    # the estimator is amrvolpath's (`_trace`, one code path; docs/design.md
    # section 13b), on Mitsuba's path-replay base class

    def __init__(self, props: mi.Properties):
        require_jit_rgb_variant("the 'amrprbvolpath' integrator")
        check_known(props, "amrprbvolpath", KNOWN)
        # validated before Mitsuba's base reads max_depth and rr_depth its way
        options = SimpleNamespace()
        AMRVolpathIntegrator._parse_path_options(options, props, "amrprbvolpath", REPLAYED_MODES)
        margin = get_float(props, "amrprbvolpath", "majorant_margin", GRADIENT_MARGIN)
        floor = get_float(props, "amrprbvolpath", "majorant_floor", GRADIENT_FLOOR)
        if not margin > 1.0 or not 0.0 < floor <= 1.0:
            raise ParameterError(f"amrprbvolpath: majorant_margin must be > 1 and majorant_floor in (0, 1], got "
                                 f"{margin} and {floor} (at 1 and 0 a leaf whose majorant equals sigma_t, or is 0, "
                                 f"hides the derivative of sigma_t there: docs/design.md section 13b)")
        type(self).__base__.__init__(self, props)
        for name, value in vars(options).items():
            setattr(self, name, value)
        self.majorant_factor, self.majorant_floor = margin, floor
        # plain delta and ratio tracking (module docstring); no counters
        self.residual = self.decomposition = False
        self.counters_enabled = False

    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        if mode == dr.ADMode.Primal:
            L, valid, _ = self._trace(scene, sampler, ray, None, active)
            return L, valid, [], L
        adjoint = PathAdjoint(mode, mi.Spectrum(0.0 if δL is None else δL), state_in)
        L, valid, dL = self._trace(scene, sampler, ray, None, active, adjoint)
        return (dL if adjoint.forward else mi.Spectrum(0.0)), valid, [], L

    def _margin(self, medium):
        return medium.majorant_margin(self.majorant_factor, self.majorant_floor)

    def aov_names(self):
        return []

    def to_string(self):
        return f"AMRPRBVolpathIntegrator[max_depth = {self.max_depth}, mode = {self.mode}]"


def prb_integrator_class():
    """The ``amrprbvolpath`` integrator class of the active variant."""
    return AMRPRBVolpathIntegrator.variant_class()
