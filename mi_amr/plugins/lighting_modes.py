"""The lighting modes of ``amrvolpath``: what a real collision in a medium does.

``amrvolpath`` walks every path the same way in every mode (Russian
roulette, surfaces, free flights through the media's local majorants,
emitters hit, next-event estimation, the next direction); a mode is a
consumer of that one walk's events (docs/design.md section 6d):

* `EmissionAbsorption`: at a real collision, score the collision's albedo
  (the TF colour, already in the throughput) times ``brightness`` and stop
  the path, whatever the lights (self-lit colours, as ParaView, VisIt and
  yt render them);
* `SingleScattering`: one next-event estimate at the collision, weighted by
  the phase function alone (no phase sampling follows, so no MIS weight),
  then stop;
* `MultipleScattering`: volpath's estimator (NEE with MIS, then phase
  sampling on);
* `RayMarch`: no free flight at all: the ray marches through each amr
  medium (`AMRMedium.march`, deterministic steps of the one walk,
  docs/design.md section 14), collects its self-lit colour and leaves it
  with the transmittance as the throughput's factor; the same integral as
  `EmissionAbsorption` without its noise. Surfaces of smooth lobes are
  shaded locally (`local_surface_shading`), so the picture has no noise.

Each mode is a Python object of the kernel's shape (the mode is a Python
constant of the kernel): its methods add Dr.Jit operations at fixed places
of the walk, never a branch on Dr.Jit values.
"""

from __future__ import annotations

import drjit as dr

from ..device.marching import AMBIENT, DIFFUSE


def accumulate(L, where, contribution, adjoint):
    """``L`` with ``contribution`` added on lanes ``where`` (the primal), or
    taken away (a replay: ``L`` is the radiance still to come)."""
    if adjoint is None:
        return dr.select(where, L + contribution, L)
    return dr.select(where, L - contribution, L)


class MultipleScattering:
    """volpath's estimator: a collision scatters, its light sample is
    MIS-weighted against phase sampling, and the path goes on."""

    #: whether the path goes on from a medium collision after its light sample
    continues = True
    #: whether amr media are ray-marched rather than tracked (`RayMarch`)
    marches = False
    #: whether an isosurface is shaded locally (`local_surface_shading`) and
    #: ends the path, rather than lit as any surface (docs/design.md section 15)
    shades_iso_locally = False

    def collided(self, L, act_scatter, throughput, brightness, adjoint):
        """``(L, act_scatter)`` after the walk's real collisions
        ``act_scatter`` (their albedo already in ``throughput``)."""
        return L, act_scatter

    def medium_nee_weight(self, phase_val, phase_pdf, ds, mis_weight):
        """The weight of a medium vertex's light sample ``ds``."""
        return phase_val * mis_weight(ds.pdf, dr.select(ds.delta, 0.0, phase_pdf))


class SingleScattering(MultipleScattering):
    """One light sample per collision, then the path stops: the sample is
    the estimator's only way to the emitters (no MIS weight)."""

    continues = False

    def medium_nee_weight(self, phase_val, phase_pdf, ds, mis_weight):
        return phase_val


class EmissionAbsorption(MultipleScattering):
    """The collision scores its albedo times the brightness and the path
    stops there (no light sample, no scattering)."""

    shades_iso_locally = True

    def collided(self, L, act_scatter, throughput, brightness, adjoint):
        L = accumulate(L, act_scatter, throughput * brightness, adjoint)
        return L, act_scatter & False


def local_surface_shading(reflectance, normal, light, view):
    """A surface as the ray marcher shades it (docs/design.md section 14):
    its diffuse ``reflectance`` times ``AMBIENT + DIFFUSE max(n.l, 0)``,
    the normal turned towards the viewer (``view``: towards it; ``light``:
    towards the light), no shadow: the sci-vis shading of its samples on a
    flat gradient."""
    n = dr.select(dr.dot(normal, view) < 0.0, -normal, normal)
    return reflectance * (AMBIENT + DIFFUSE * dr.maximum(dr.dot(n, light), 0.0))


class RayMarch(EmissionAbsorption):
    """The sci-vis ray marcher: amr media are marched, never collided in
    (no collision reaches `collided`); the ray goes on through them with
    their transmittance."""

    marches = True


#: The modes by name (``mode``), the default last.
LIGHTING_MODES = {"ray_march": RayMarch(), "emission_absorption": EmissionAbsorption(),
                  "single": SingleScattering(), "multi": MultipleScattering()}
