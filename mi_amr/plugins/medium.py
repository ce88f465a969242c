"""The ``amr`` medium: cell-centric AMR data as a Mitsuba participating medium.

A thin plugin: `parse_medium_options` validates the properties once,
`Structures` builds what the chosen traversal and sampling need, and the
tracking kernels of `mi_amr.device` do the per-ray work. The class is
built for the Mitsuba variant that is active when it is instantiated
(`mi_amr.plugins.variant_class`).
"""

from __future__ import annotations

import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device.grid import DeviceTwoLevelGrid
from ..device.isosurface import IsoHit, IsoSearch, central_gradient
from ..device.marching import GradientShading, Marched, RayMarch
from ..device.ray import clip_to_half_space, flush_tiny, intersect_unit_cube, safe_rcp
from ..device.tracking import (GRADIENT_FLOOR, GRADIENT_MARGIN, DecompositionTracking, DeltaTracking,
                               FreeFlight, LocalRay, MajorantMargin, RatioTracking, Replay, ResidualRatioTracking,
                               SpanMajorant, Transmittance, walk_segments)
from ..data.device_values import commit_values, device_values
from ..params import ParameterError
from ..building import Structures
from ..transfer.classification import Classification
from ..transfer.function import TransferFunction
from ..transfer.spectra import require_supported_variant
from .iso_surfaces import IsoSurfaces
from .options import parse_medium_options
from .variant_class import VariantPlugin
import gc
from ..structures.cost_model import volpath_speedup


def scene_media(scene) -> list:
    """Every medium of a scene (shape interiors and exteriors, sensors), each
    once as far as object identity tells."""
    found = []
    candidates = [m for shape in scene.shapes() for m in (shape.interior_medium(), shape.exterior_medium())]
    candidates += [s.medium() for s in scene.sensors() if hasattr(s, "medium")]
    for m in candidates:
        if m is not None and all(m is not f for f in found):
            found.append(m)
    return found


def amr_media(scene_or_medium) -> list:
    """The ``amr`` media of a scene (or the medium itself, in a list)."""
    if isinstance(scene_or_medium, AMRMedium):
        return [scene_or_medium]
    return [m for m in scene_media(scene_or_medium) if isinstance(m, AMRMedium)]


def require_jit_rgb_variant(what: str = "mi_amr"):
    """Raise a one-line error unless the active Mitsuba variant is a JIT
    rgb, spectral or mono one (`mi_amr.transfer.spectra.refusal` says why
    the others are refused; the name is kept from when only rgb worked)."""
    require_supported_variant(what)


class _RayMajorant:
    """The ray-wise majorant of the ray last passed to ``intersect_aabb``.

    A plain object on purpose: it holds variables of the kernel being
    traced, which ``dr.freeze`` must not see as inputs. ``key`` holds the
    variables of ``-ray.d``; Mitsuba's ``sample_interaction`` sets
    ``mei.wi = -ray.d`` before it calls ``intersect_aabb``, so (Dr.Jit
    reuses identical expressions) only an interaction of that very ray has
    ``wi`` made of the same variables.
    """

    def __init__(self):
        self.key, self.mu = None, None

    def key_of(self, ray):
        """The variables of ``-ray.d``; call before any symbolic loop (a loop
        opens a new scope, and Dr.Jit reuses expressions only within one)."""
        wi = -ray.d
        return (wi.x, wi.y, wi.z)

    def store(self, key, mu):
        self.key, self.mu = key, mu

    def lookup(self, mei):
        """The stored majorant if ``mei`` belongs to the stored ray, else None."""
        if self.key is None:
            return None
        if any(a.index != b.index or a.index == 0 for a, b in zip(self.key, (mei.wi.x, mei.wi.y, mei.wi.z))):
            return None
        return self.mu

    def clear(self):
        self.key, self.mu = None, None


#: Every live `AMRMedium` (weak references): Dr.Jit dispatches over all live
#: instances, so timings need to know that no other scene is alive.
_LIVE = weakref.WeakSet()


def live_media() -> int:
    """Number of `AMRMedium` instances alive (after a garbage collection)."""
    gc.collect()
    return len(_LIVE)


#: ``amrvolpath`` uses residual ratio and decomposition tracking on a medium
#: (unless told otherwise) when its minorants carry at least this share of
#: its majorants at load (volume-weighted). Every segment pays for its
#: minorant (a gather and an exponential), and what that buys, look-ups and
#: variance, grows with the minorants' share: they pay where it is large and
#: cost frame time where it is small (timings: docs/performance/minorants.md,
#: "2026-12-01: timed pass by pass, and the per-medium default").
MINORANTS_PAY_FRACTION = 0.5

#: Stock volpath restarts its ray at every null collision and asks
#: `intersect_aabb` for the majorant of the rest of the ray each time. On a
#: two-level grid (long walks) that walk stops once it has met this share of
#: the global majorant and answers the global majorant up to the cube's exit:
#: at most 1/0.9 more null collisions on those rays, for walks of a few
#: macrocells instead of all of them (docs/performance/protocol.md, "Stock
#: volpath"). On uniform grids the walk is short and its trailing trim pays.
SPAN_STOP_SHARE = 0.9

#: Settings that cannot be made as efficient as Mitsuba's own heterogeneous
#: medium, and why; the medium warns once per process when one is chosen.
#: The measured efficiencies are in docs/performance/settings.md, which the
#: warnings cite rather than copy.
SLOW_SETTINGS = {
    ("majorant", "global"): (
        "majorant='global' tracks with one majorant, as Mitsuba's heterogeneous medium does, so it "
        "makes as many density look-ups, and an AMR look-up (a hash probe per level) costs more than "
        "a dense texture fetch: it is at best as efficient as that medium. majorant='ray' (the "
        "default) skips empty space and is faster (figures: docs/performance/settings.md)"),
    ("traversal", "kdtree"): (
        "traversal='kdtree' re-descends the SAH kd-tree from its root at every segment (about 12 "
        "levels for 4096 leaves), which costs more than the look-ups its leaves save on most data; "
        "traversal='grid' (the default) is faster on every benchmark data set (figures: "
        "docs/performance/settings.md)"),
}
_WARNED: set = set()


def _warn_slow_settings(options):
    for (name, value), why in SLOW_SETTINGS.items():
        chosen = options.majorant if name == "majorant" else options.structures.traversal
        if chosen == value and (name, value) not in _WARNED:
            _WARNED.add((name, value))
            mi.Log(mi.LogLevel.Warn, f"amr: {why}")


def _warn_if_volpath_is_slower(medium):
    """Once per process: warn, naming ``amrvolpath``, when stock ``volpath``
    (or another integrator that calls ``sample_interaction``) renders a
    medium whose majorants predict that it will be less efficient than
    Mitsuba's own ``heterogeneous`` medium on the same field
    (`volpath_speedup`: where a shell or a fog keeps the majorant of most
    rays near the global one). Runs when a kernel is traced, not per ray.
    The prediction reads the macrocell grid's majorants: a medium whose
    traversal and sampling built no grid (``abr``, ``brick`` or ``kdtree``
    with an ``abr`` or ``brick`` sampling) is not predicted, and nothing
    is built for the warning."""
    if "volpath" in _WARNED or medium.majorant_mode != "ray" or medium._volpath_checked:
        return
    medium._volpath_checked = True               # with the TF of its first trace
    if "grid" not in medium.structures.built:
        return
    speedup = volpath_speedup(medium.majorant_grid)
    if speedup < 1.0:
        _WARNED.add("volpath")
        mi.Log(mi.LogLevel.Warn,
               f"amr: with this TF most rays keep a majorant near the global one, so stock volpath is "
               f"predicted to reach only {speedup:.2f}x the efficiency of Mitsuba's heterogeneous medium "
               f"on the same field; the 'amrvolpath' integrator tracks through local majorants and is "
               f"faster (<integrator type=\"amrvolpath\"/>; figures: docs/performance/protocol.md)")


def _warn_if_iso_is_ignored(medium):
    """Once per process: stock ``volpath`` (any integrator that calls
    ``sample_interaction``) cannot see isosurfaces; say so, naming
    ``amrvolpath``."""
    if "iso" in _WARNED or not medium.iso_values:
        return
    _WARNED.add("iso")
    mi.Log(mi.LogLevel.Warn,
           "amr: this medium has isosurfaces (iso values), which Mitsuba's stock volpath cannot see: it renders "
           "the volume alone; the 'amrvolpath' and 'amrprbvolpath' integrators draw them")


def _warn_if_emission_is_ignored(medium):
    """Once per process: stock ``volpath`` (any integrator that calls
    ``sample_interaction``) has no medium emission, so a medium that glows
    renders dark there; say so, naming ``amrvolpath``."""
    if "emission" in _WARNED or not medium.glows:
        return
    _WARNED.add("emission")
    mi.Log(mi.LogLevel.Warn,
           "amr: this medium emits light (an 'emission' TF), but Mitsuba's stock volpath has no medium "
           "emission and renders it as if it did not glow; the 'amrvolpath' integrator adds the emission "
           "(<integrator type=\"amrvolpath\"/>)")


class AMRMedium(metaclass=VariantPlugin, base="Medium"):
    r"""
    AMR medium (:monosp:`amr`)
    --------------------------

    Cell-centric adaptive-mesh-refinement data, coloured by an RGBA transfer
    function: ``sigma_t(x) = density_scale * alpha(f(x))`` (inverse world
    units) and albedo ``rgb(f(x))``. The AMR bounding box fills the unit cube
    and ``to_world`` places it, as with ``gridvolume``. Enclose it in a shape
    (usually a ``cube`` with the same ``to_world``) whose ``interior`` is this
    medium.

    .. pluginparameters::

     * - filename
       - |string|
       - ExaBricks ``.cells`` file (or ``.npz``, ``.amrb``); the scalars are
         the sibling ``.scalars`` file unless ``scalars`` names another. Or
         any output yt loads, with ``field``.
     * - field
       - |string|
       - The field yt reads from ``filename``; for a ``.cells`` file, its
         ``NAME-FIELD.scalars``.
     * - data_checksum
       - |string|
       - The checksum the data of ``filename`` and ``field`` must have
         (`mi_amr.data.opening.volume_checksum`); other data are refused.
     * - clip_normal
       - |vector|
       - A clip plane's normal (world space): the medium is kept where
         ``clip_normal . x <= clip_offset``, empty beyond, in every
         integrator and mode (`set_clip_plane` moves it).
     * - clip_offset
       - |float|
       - The clip plane's offset, world units. Default: 0.
     * - iso
       - |string|
       - Up to 4 iso values in the medium's value units (after
         ``value_transform``), as ``"0.3 0.5"``: isosurfaces of the
         reconstruction, drawn by ``amrvolpath`` and ``amrprbvolpath``
         (docs/design.md section 15); nested BSDFs, in order, are their
         BSDFs (default: two-sided diffuse in the TF's colour at the
         value). ``set_iso`` moves them. Stock ``volpath`` cannot see them.
     * - iso_only
       - |bool|
       - The surfaces alone: the medium's own density is off. Default: false.
     * - scalars
       - |string|
       - Scalars file for ``filename`` (optional).
     * - data
       - ``AMRCells``
       - The cells themselves (Python scene dictionaries only).
     * - transfer_function
       - |string| or ``TransferFunction``
       - Preset name (``layers``, with options as ``layers:n=8,width=0.2,colormap=plasma``;
         ``spiky``, ``foggy``, ``ramp``, ``constant``, ``dust``, ``blackbody``), a colormap
         name, or a ``.json`` file. Default: ``foggy`` (data planned by
         ``mi-amr render``, ``mi_amr.scene`` and the viewer get ``layers``).
     * - tf_min, tf_max
       - |float|
       - Value domain of a preset TF, and the range a ``.json`` TF is
         rescaled to (as ParaView applies a preset). Default: the data's
         value range (a ParaView preset is rescaled to it; our own format
         keeps the domain it stores).
     * - tf_keep_range
       - |bool|
       - A ``.json`` TF keeps the range it stores (ParaView's "Use preset
         range"; a file may also say ``"keep_range": true``). Default: false.
     * - density_scale
       - |float|
       - Extinction of opacity 1, in inverse world units. Default: 1.
     * - reconstruction
       - |string|
       - ``tent`` (default; continuous) or ``nearest`` (finest cell).
     * - majorant
       - |string|
       - ``ray`` (default): walk the traversal structure along each ray, trim
         empty space at both ends, use the maximum over the rest (only for
         the interaction of the ray last passed to ``intersect_aabb``; any
         other caller gets the global majorant); ``global``: one maximum for
         the whole volume.
     * - grid_resolution
       - |int|
       - Macrocells along the longest axis (of the fine level of a
         two-level grid). Default: chosen by a cost model of the data and
         the TF (`mi_amr.structures.cost_model.auto_grid`).
     * - grid_refinement
       - |int|
       - 1: a uniform grid walked by DDA; a power of two ``f``: a two-level
         grid whose coarse macrocells hold ``f^3`` fine ones, each coarse
         macrocell walked through its fine ones where that saves work for
         the current TF (decided again on every TF change). Default: chosen
         by the cost model; ``grid_resolution`` alone means 1.
     * - thinning_resolution
       - |int|
       - Macrocells along the longest axis of the finer majorants that
         thin ``amrvolpath``'s tentative collisions (docs/design.md section
         5d): a collision drawn against a segment's majorant stays with
         probability ``mu_f / mu`` and only then looks the density up. 0:
         none. Default: for the ``grid`` traversal, the finest grid the
         cost model weighs with at most one macrocell per 20 cells, where it
         is finer than the walked grid (so only on large data).
     * - traversal
       - |string|
       - Segments and majorants for ``amrvolpath`` (and the ray-wise
         majorant in ``volpath``): ``grid`` (default), ``abr``, ``brick``,
         ``kdtree`` (pre-classified SAH kd-tree, rebuilt on a TF change).
     * - sampling
       - |string|
       - Point location of density look-ups: ``hash`` (default), ``abr``
         (the ABR's brick list), ``brick`` (bricks whose extended domain
         contains the point).
     * - brick_size, kdtree_leaves
       - |int|
       - Largest brick side in cells (8); leaf budget of the kd-tree (4096).
     * - value_masks
       - |bool|
       - With ``nearest``: the macrocell grid also records which of 64
         value bins its cells take, and its majorants are the smaller of
         the range's and the bins' (8 bytes per macrocell). Default: true.
         (``tent`` fields are continuous, so a macrocell takes every value
         of an interval and bins add nothing there: not built.)
     * - value_transform
       - |string|
       - ``none`` (default) or ``log10``: the values are replaced by their
         logarithm once at load (zero and negative values by the smallest
         positive one first), and ``tf_min``/``tf_max`` are in those units.
     * - overlap
       - |string|
       - ``error`` (default) rejects overlapping cells; ``finest`` keeps the
         finer ones.
     * - emission
       - |string| or ``TransferFunction``
       - Makes the medium glow (``amrvolpath`` only): an emission TF over
         the emission field, a preset (``blackbody``), a matplotlib colormap
         name or a ``.json`` file. The gas emits ``sigma_a L_e`` per unit
         length with ``L_e = emission_scale * rgb * alpha`` of this TF and
         ``sigma_a = sigma_t (1 - albedo)``. Default: none (no emission).
     * - emission_field
       - |string|
       - The field the emission TF reads: a further field of the data (e.g.
         ``temperature``). Default: the extinction field.
     * - emission_scale
       - |float|
       - Radiance of TF colour 1 at intensity 1. Default: 1.
     * - emission_model
       - |string|
       - ``tf`` (default): the emission TF; ``blackbody``: Planck's law at
         the emission field read in kelvin, ``L_e = emission_scale *
         B(lambda, T) / Y(B(6500 K))``, exact per wavelength in spectral
         variants, its linear-sRGB projection in rgb (no ``emission`` TF).
     * - emission_min, emission_max
       - |float|
       - Value domain of a preset emission TF. Default: the emission
         field's range (after ``emission_transform``).
     * - emission_transform
       - |string|
       - ``none`` (default) or ``log10``, applied to the emission field as
         ``value_transform`` is to the extinction field.
     * - to_world
       - |transform|
       - Placement of the unit cube in the scene.
     * - (nested phase function)
       - |phase|
       - Any phase function except microflake ones (``sggx``), which are
         refused: their projected area would scale the extinction beyond
         the majorants. Default: isotropic. Its parameters appear in
         ``mi.traverse`` under ``phase_function.*``.
     * - sample_emitters
       - |bool|
       - Next-event estimation in the medium. Default: true.
     * - max_iterations
       - |int|
       - Bound on the iterations of one tracking loop (2^20); a ray that
         reaches it stops and is counted as ``capped``.
     * - memory_limit
       - |float|
       - Bytes a structure may need (``MI_AMR_MEMORY_LIMIT`` or half the
         physical memory); larger ones are refused before they are built.

    Scene parameters (``mi.traverse``): ``density_scale``, ``tf_rgba`` (N x 4,
    row major), ``tf_domain``, for a medium that glows ``emission_scale``,
    ``emission_rgba`` and ``emission_domain``, and ``values``: the cell
    values, the flat array in resident order (block ``b``, slot ``s`` ->
    index ``b B^3 + s``, NaN in empty slots; `value_index` maps an
    ``AMRCells`` to it). All but the domains are differentiable: gradients
    flow through the collision terms in Mitsuba's ``prbvolpath``;
    majorants stay detached. ``params.update()`` re-majorises every leaf
    after a change (docs/design.md section 13).
    """

    def __init__(self, props: mi.Properties):
        require_jit_rgb_variant("the 'amr' medium")
        # every option is parsed (and refused) before the base constructor
        # registers this medium with Dr.Jit: a refusal after it left a
        # half-built instance in the registry of media that every vcall
        # over media walks (a segfault in a later render, seen in the suite)
        options = parse_medium_options(props)
        type(self).__base__.__init__(self, props)
        self.m_is_homogeneous = False
        self.m_has_spectral_extinction = False
        if mi.has_flag(self.phase_function().flags(), mi.PhaseFunctionFlags.Microflake):
            raise ParameterError(
                "amr: microflake phase functions (such as sggx) are not supported: their projected area scales the extinction beyond the majorants; "
                "use an isotropic, hg, rayleigh, tabphase or blendphase phase function")
        _warn_slow_settings(options)
        _LIVE.add(self)
        self.options = options
        self.majorant_mode = options.majorant

        # ---- Dr.Jit state (direct attributes and structs: dr.freeze sees them) ----
        self._to_local = mi.Transform4f(options.to_world.inverse())
        self._to_world = mi.Transform4f(options.to_world)
        self._max_iterations = mi.UInt32(options.max_iterations)
        dr.make_opaque(self._to_local, self._to_world, self._max_iterations)
        self.set_clip_plane(*(options.clip or (None,)))
        # the one owner of the TF and the density scale: every change goes
        # through it and then reclassifies the structures
        emission = options.emission
        self.classification = Classification(options.tf, options.density_scale,
                                             emission=None if emission is None else emission.tf,
                                             emission_scale=1.0 if emission is None else emission.scale,
                                             emission_model="tf" if emission is None else emission.model)
        # the isosurfaces (docs/design.md section 15): values, BSDFs, the
        # kernels' opaque view of them
        lo, hi = options.volume.value_range
        self.iso = IsoSurfaces(options.iso, options.iso_bsdfs, options.iso_only, span=hi - lo, tf=options.tf)
        # the `AMRCells` a user gave (``data``), kept for `cells`; the
        # structures read the blocks only
        self._given_cells = options.cells
        self._build_structures(options.volume)
        # the cell values as the scene parameter ``values``: a variable of
        # this medium's own (the same device array until it changes), so
        # that a gradient or an update through it never reaches another
        # medium on the same data (`_apply_values`)
        self._values = mi.Float(device_values(self.volume))
        self._ray_majorant = _RayMajorant()
        self._volpath_checked = False            # `_warn_if_volpath_is_slower` ran for this medium
        # whether amrvolpath's minorant estimators pay on these data (decided
        # once, with the TF given at load: a later TF change compiles nothing)
        self.minorant_fraction = self.structures.minorant_fraction()
        self.minorants_pay = self.minorant_fraction >= MINORANTS_PAY_FRACTION

    def _build_structures(self, volume):
        """Build the structures the traversal and sampling need on
        ``volume``, listen to the classification and compute every majorant."""
        options, emission = self.options, self.options.emission
        self.structures = Structures(volume, options.structures, self.classification,
                                     options.world_scale).build()
        # a medium that glows from a field of its own (or the values under a
        # transform): the flight's one look-up reconstructs that field too
        self._carried = None
        if emission is not None and (emission.field is not None or emission.transform != "none"):
            self._carried = self.structures.field_values(emission.field, emission.transform)
        self.classification.on_change = self._reclassified
        two_level = (options.structures.traversal == "grid"
                     and isinstance(self.structures.device.get("grid"), DeviceTwoLevelGrid))
        self._span_stop = SPAN_STOP_SHARE if two_level else None
        self.structures.update_majorants()

    def _reclassified(self, classification):
        """After a TF or density-scale change: the structures' majorants,
        and the colours of the default iso BSDFs."""
        self.structures.reclassify(classification)
        self.iso.set_tf(classification.tf)

    # ---- Read-only views --------------------------------------------------------
    @property
    def volume(self):
        """The data in their resident form (`mi_amr.data.blocks.BlockVolume`)."""
        return self.structures.volume

    @property
    def cells(self):
        """The data as per-cell records (`AMRCells`): the object given as
        ``data``, or made from the blocks for the caller, not kept (the
        blocks stay the only resident copy; small data only)."""
        return self._given_cells if self._given_cells is not None else self.volume.to_cells()

    @property
    def tf(self) -> TransferFunction:
        """The transfer function (host form; `classification` owns it)."""
        return self.classification.tf

    @property
    def density_scale(self) -> float:
        """Extinction of opacity 1, inverse world units (`classification` owns it)."""
        return self.classification.density_scale

    @property
    def tf_device(self):
        """The TF tables the kernels read (`classification` owns them)."""
        return self.classification.device

    @property
    def reconstruction(self) -> str:
        return self.options.structures.reconstruction

    @property
    def traversal(self) -> str:
        return self.options.structures.traversal

    @property
    def sampling(self) -> str:
        return self.options.structures.sampling

    @property
    def world_scale(self) -> float:
        return self.options.world_scale

    @property
    def grid(self):
        """The host `MacrocellGrid` of the traversal/sampling grid."""
        return self.structures.grid.host

    @property
    def build_seconds(self) -> dict:
        return self.structures.build_seconds

    @property
    def structure_bytes(self) -> int:
        """Memory of every structure built so far (host arrays uploaded)."""
        return self.structures.nbytes

    @property
    def resident_bytes(self) -> int:
        """Memory the medium keeps: its data (`BlockVolume.nbytes`) and every
        structure built so far, each counted once."""
        return self.volume.nbytes + self.structures.nbytes

    @property
    def global_majorant(self) -> float:
        return float(self.structures.global_majorant[0])

    @property
    def majorant_grid(self) -> np.ndarray:
        """Macrocell majorants as a numpy array indexed ``[z, y, x]``."""
        return self.structures.grid.effective_majorants()

    def update_majorants(self):
        """Recompute every majorant from the value ranges and the classification."""
        self.structures.update_majorants()

    # ---- Density ----------------------------------------------------------------
    def eval_local(self, u: mi.Vector3f, active=True, wavelengths=None):
        """``(albedo, sigma_t)`` at local point ``u`` (unit cube); sigma_t in
        inverse world units, 0 outside the data or where no value exists;
        the albedo the variant's spectrum at ``wavelengths`` (spectral
        variants; `Classification.albedo_and_sigma_t`)."""
        value, found = self.structures.sampler().eval(u, active)
        return self.classification.albedo_and_sigma_t(value, found, wavelengths)

    def eval_world(self, p: mi.Point3f, active=True, wavelengths=None):
        """``(albedo, sigma_t)`` at world points ``p`` (`eval_local`)."""
        return self.eval_local(self._to_local @ p, active, wavelengths)

    def value_local(self, u: mi.Vector3f, active=True):
        """``(value, sigma_t)`` at local point ``u``: the reconstructed value
        and sigma_t as in `eval_local`, without the colour (tracking takes
        the albedo of its one real collision from the value, `albedo_of`)."""
        value, found = self.structures.sampler().eval(u, active)
        return value, self.classification.sigma_t(value, found)

    def point_query(self, u: mi.Vector3f, active=True):
        """``(value, sigma_t, carried)`` at local point ``u`` from one
        look-up: `value_local` and, for a medium that glows from a field of
        its own, that field's value at the same point (docs/design.md
        section 12; pbrt-v4's ``SamplePoint`` answers every property at once)."""
        both, found = self.structures.sampler(self._carried).eval(u, active)
        return both.x, self.classification.sigma_t(both.x, found), both.y

    def albedo_of(self, value, active=True, wavelengths=None):
        """The TF's colour (the albedo) at ``value``, the variant's spectrum
        at ``wavelengths`` (`DeviceTransferFunction.eval_colour`)."""
        return self.classification.device.eval_colour(value, active, wavelengths)

    # ---- Emission ---------------------------------------------------------------
    @property
    def glows(self) -> bool:
        """Whether the medium emits (an ``emission`` TF was given at load)."""
        return self.classification.glows

    @property
    def emission_tf(self) -> TransferFunction | None:
        """The emission TF (host form; `classification` owns it), or None."""
        return self.classification.emission

    def emitted_radiance(self, p: mi.Point3f, active=True, wavelengths=None):
        """``L_e`` at world points ``p`` (the radiance of the absorbing gas:
        its emission per unit length is ``sigma_a L_e``) at ``wavelengths``;
        0 outside the data and for a medium that does not glow."""
        if self.options.emission is None:
            return mi.UnpolarizedSpectrum(0.0)
        value, found = self.structures.sampler().eval(self._to_local @ p, active) if self._carried is None \
            else self._carried_at(self._to_local @ p, active)
        return self.classification.emitted_radiance(value, found, wavelengths)

    def _carried_at(self, u, active):
        both, found = self.structures.sampler(self._carried).eval(u, active)
        return both.y, found

    def emitted_radiance_at(self, flight: FreeFlight, p: mi.Point3f, active=True, wavelengths=None):
        """``L_e`` at the real collisions of ``flight`` (world points ``p``)
        from the flight's own point query (`point_query`): the value found
        there, or the emission field carried with it. Only a control
        collision of decomposition tracking, which looked nothing up, looks
        ``p`` up (`emitted_radiance`): every collision costs one look-up."""
        if self.options.emission is None:
            return mi.UnpolarizedSpectrum(0.0)
        found = mi.Bool(active) & flight.looked
        value = flight.value if self._carried is None else flight.carried
        from_value = self.classification.emitted_radiance(value, found, wavelengths)
        return dr.select(found, from_value, self.emitted_radiance(p, mi.Bool(active) & ~flight.looked, wavelengths))

    def set_emission(self, emission: TransferFunction | None = None, emission_scale: float | None = None):
        """A new emission TF and/or scale (None keeps the current one): the
        same path as ``params.update()`` (`Classification.set`); no majorant
        moves and no kernel is recompiled."""
        self.classification.set(emission=emission, emission_scale=emission_scale)

    # ---- Local-majorant tracking (used by the amrvolpath integrator) ---------
    def local_ray(self, ray: mi.Ray3f):
        """``(o, d, s)``: the ray in the unit cube with a unit direction ``d``
        (negligible components flushed to 0, `flush_tiny`) and ``s``, local
        length per world ``t``: the point at world ``t`` is ``o + (s t) d``.
        Unit directions keep the traversal's float maths in range for any
        ``to_world`` scale (1e-20 to 1e20)."""
        o = self._to_local @ ray.o
        d = self._to_local @ ray.d
        m = dr.max(dr.abs(d))
        m = dr.select(m > 0.0, m, 1.0)
        s = m * dr.norm(d * dr.rcp(m))
        return o, flush_tiny(d * dr.rcp(s)), s

    def free_flight(self, ray: mi.Ray3f, t_max, sampler, active, control: bool = False,
                    count: bool = True, replay: Replay | None = None,
                    margin: MajorantMargin | None = None) -> FreeFlight:
        """Delta tracking through local-majorant segments along ``ray`` up to
        ``t_max`` (decomposition tracking against the minorants with
        ``control``): a `FreeFlight`, its ``t`` in world units along ``ray``.
        ``sampler``: a Mitsuba sampler or an `Rng`, which seeds the
        tracking's own random stream; ``count``: keep the event counts (else
        they read 0, and cost nothing); ``replay``: the adjoint of a
        path-replay pass (`replay`; plain delta tracking only); ``margin``:
        raised majorants (`majorant_margin`) for a differentiable walk."""
        carries = self._carried is not None
        lookup = self.point_query if carries else self.value_local
        wavelengths = ray.wavelengths

        def albedo_of(value, active=True):
            return self.albedo_of(value, active, wavelengths)
        if control:
            if replay is not None or margin is not None:
                raise ValueError("free_flight: a differentiable walk tracks without a control extinction")
            tracking = DecompositionTracking(lookup, albedo_of, sampler, self.tf_device.rgb_constant, carries,
                                             count, thin=self._thinning(replay, margin))
        else:
            tracking = DeltaTracking(lookup, albedo_of, sampler, carries, count, replay, margin,
                                     self._thinning(replay, margin))
        return self._track(ray, t_max, active, tracking)

    def transmittance(self, ray: mi.Ray3f, t_max, sampler, active, control: bool = False,
                      count: bool = True, replay: Replay | None = None,
                      margin: MajorantMargin | None = None) -> Transmittance:
        """Ratio-tracking estimate of transmittance along ``ray`` over
        ``[0, t_max]`` (residual ratio tracking against the minorants with
        ``control``): a `Transmittance` (``count``, ``replay`` and
        ``margin`` as in `free_flight`)."""
        if control and margin is not None:
            raise ValueError("transmittance: a differentiable walk tracks without a control extinction")
        tracking = (ResidualRatioTracking if control else RatioTracking)(
            self.value_local, sampler, count=count, replay=replay, margin=margin, thin=self._thinning(replay, margin))
        return self._track(ray, t_max, active, tracking)

    def march(self, ray: mi.Ray3f, t_max, sampler, active, step_scale, brightness, light=None,
              count: bool = True) -> Marched:
        """The sci-vis ray march along ``ray`` up to ``t_max`` through the
        traversal's segments (docs/design.md section 14; `RayMarch`): a
        `Marched` with the radiance collected and the transmittance past
        it. ``step_scale``: steps in finest cells under each segment
        (``tent``; ``nearest`` walks cell faces exactly); ``brightness``:
        the TF colour's factor; ``light(p, active) -> unit direction towards
        the light`` at world points: shade each sample with Blinn-Phong on
        the reconstruction's gradient (`GradientShading`), or None: the TF
        colour as it is. ``sampler`` seeds the jitter and the roulette."""
        carries = self._carried is not None
        wavelengths = ray.wavelengths
        lookup = self.point_query if carries else self.value_local
        s = self.structures

        def colour_of(value, active):
            return self.albedo_of(value, active, wavelengths)

        emission_of = None
        if self.glows:
            def emission_of(value, carried, active):
                return self.classification.emitted_radiance(value if carried is None else carried, active,
                                                            wavelengths)
        shading = None
        if light is not None:
            def value_at(u, active):
                return self.value_local(u, active)[0]
            # half the finest cell of the data, in local units, per axis
            eps = 0.5 * dr.rcp(dr.max(s.extent))
            shading = GradientShading(value_at, eps, lambda g: dr.normalize(self._to_world @ mi.Normal3f(g)),
                                      lambda u, active: light(self._to_world @ mi.Point3f(u), active),
                                      dr.normalize(ray.d))
        # the leaf cell at a point, where the sampling can find it: steps by
        # the level sampled (not only the leaf's finest), cell by cell for nearest
        cell_at = None
        points = s.sampler()
        if hasattr(points, "cell_at") and not carries:
            def cell_at(u, active):
                value, found, level = points.cell_at(u, active)
                return value, self.classification.sigma_t(value, found), level
        tracking = RayMarch(lookup, colour_of, sampler, s.extent, s.offset, step_scale, brightness,
                            exact=self.reconstruction == "nearest", emission_of=emission_of, shading=shading,
                            carries=carries, count=count, cell_at=cell_at)
        return self._track(ray, t_max, active, tracking, levels=True)

    def _thinning(self, replay, margin):
        """The finer majorant a walk thins by (`Structures.thinning`), or
        None: differentiable walks (a ``replay`` or a ``margin``) do not thin
        (docs/design.md section 5d)."""
        return self.structures.thinning() if replay is None and margin is None else None

    def majorant_margin(self, factor: float, floor_share: float) -> MajorantMargin:
        """Raised majorants for differentiable walks (`MajorantMargin`):
        ``factor * mu + floor_share * global majorant``."""
        return MajorantMargin(factor, floor_share * self.structures.global_majorant)

    def replay(self, mode, weight=None) -> Replay:
        """The adjoint hook of a path-replay pass for this medium's walks
        (docs/design.md section 13b): ``mode`` a `dr.ADMode`, ``weight``
        (backward mode) per lane the adjoint radiance times the radiance
        the walk's factors scale, summed over channels."""
        return Replay(mode, self.value_local, weight)

    def set_clip_plane(self, normal=None, offset: float = 0.0):
        """Keep the medium where ``normal . x <= offset`` (world space; the
        rest is empty in every integrator and mode, shadow rays included);
        ``normal`` None keeps all of it. Opaque: another plane compiles
        nothing; the walks only narrow, so a clipped frame never costs more.
        A plane and offset that are not finite are a `ParameterError`."""
        if normal is None:
            n_local, c_local = np.zeros(3), 1.0
        else:
            n = np.asarray(normal, np.float64).reshape(3)
            if not (np.isfinite(n).all() and np.any(n) and np.isfinite(float(offset))):
                raise ParameterError(f"amr: clip plane: a nonzero finite normal and a finite offset, got "
                                     f"{n.tolist()} and {offset}")
            m = np.array(self.options.to_world.matrix, np.float64)       # x_world = A x_local + b
            n_local, c_local = m[:3, :3].T @ n, float(offset) - float(n @ m[:3, 3])
            scale = np.abs(n_local).max()                                 # well-scaled in float32
            n_local, c_local = n_local / scale, c_local / scale
        self.clip = None if normal is None else (np.asarray(normal, np.float64).reshape(3), float(offset))
        self._clip_normal = dr.opaque(mi.Vector3f, [float(x) for x in n_local])
        self._clip_offset = dr.opaque(mi.Float, float(c_local))

    def _clipped(self, o, d, t_lo, t_hi):
        """``(t_lo, t_hi)`` narrowed to the clip plane's kept side (local units)."""
        return clip_to_half_space(o, d, t_lo, t_hi, self._clip_normal, self._clip_offset)

    def _track(self, ray, t_max, active, tracking, levels: bool = False):
        """The result of the estimator ``tracking`` walked along ``ray`` in
        the unit cube up to ``t_max`` (`walk_segments`), on the clip plane's
        kept side; ``levels``: its segments carry their finest level."""
        local, active = self._walked_ray(ray, t_max, active)
        active &= self.structures.global_majorant * self.iso.volume_on > 0.0
        return walk_segments(self.structures.segments(levels), local, active, tracking, self._max_iterations)

    def _walked_ray(self, ray, t_max, active):
        """``(local, active)``: ``ray`` up to world ``t_max`` as the `LocalRay`
        a walk takes (the unit cube's span on the clip plane's kept side),
        and the lanes where that span is not empty."""
        o, d, s = self.local_ray(ray)
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        t_lo, t_hi = self._clipped(o, d, dr.maximum(t0, 0.0), dr.minimum(t1, t_max * s))
        local = LocalRay(o=o, d=d, t_lo=t_lo, t_hi=t_hi, scale=s)
        return local, mi.Bool(active) & hit & (s > 0.0) & (local.t_lo < local.t_hi)

    # ---- Isosurfaces (docs/design.md section 15) -----------------------------------
    @property
    def iso_values(self) -> tuple:
        """The iso values, in the medium's value units (after its ``value_transform``)."""
        return self.iso.values

    @property
    def iso_only(self) -> bool:
        """Whether the medium shows its surfaces alone (its own density off)."""
        return self.iso.only

    @property
    def has_iso(self) -> bool:
        """Whether the integrators search this medium for surfaces: once an
        iso value was set (at load or by `set_iso`). A Python constant of the
        kernels: moving, adding or removing values later compiles nothing."""
        return self.iso.enabled

    def set_iso(self, values=None, bsdfs=None, only: bool | None = None):
        """New iso values (value units; None keeps them; at most
        `MAX_ISO_VALUES`), BSDFs by slot (None keeps them; a None entry: the
        default, two-sided diffuse in the TF's colour at the value) and
        ``only`` (the surfaces alone; None keeps it). Opaque: compiles
        nothing once the medium has surfaces (`has_iso`)."""
        self.iso.set(values, bsdfs, only)

    def iso_bsdf(self, slot, active=True):
        """The BSDF (``mi.BSDFPtr``) of iso slot ``slot`` per lane."""
        return self.iso.bsdf(slot, active)

    def iso_hit(self, ray: mi.Ray3f, t_max, active, count: bool = False) -> IsoHit:
        """The first isosurface along ``ray`` before world ``t_max`` (on the
        clip plane's kept side), found by the one walk (`IsoSearch`): an
        `IsoHit` in world space, its normal the normalised gradient of the
        reconstruction (central differences over half a finest cell),
        turned towards lower values (``-ray.d`` where it vanishes)."""
        local, active = self._walked_ray(ray, t_max, active)
        points = self.structures.sampler()

        def value_at(u, active):
            value, found = points.eval(u, active)
            return dr.select(found, value, dr.nan)
        search = IsoSearch(value_at, self.iso.slots, self.iso.tolerance, self.structures.extent, count,
                           exact=self.reconstruction == "nearest", offset=self.structures.offset)
        found = walk_segments(self.structures.segments(True, True), local, active, search, self._max_iterations)
        u = local.o + local.d * dr.select(found.found, found.t, 0.0)
        g = central_gradient(value_at, u, 0.5 * dr.rcp(dr.max(self.structures.extent)), found.found)
        n = dr.normalize(self._to_world @ mi.Normal3f(-g))
        usable = found.found & dr.all(dr.isfinite(n)) & (dr.squared_norm(g) > 0.0)
        n = mi.Vector3f(dr.select(usable, n, -dr.normalize(ray.d)))
        t = dr.select(found.found, local.world_t(found.t), dr.inf)
        return IsoHit(t=t, found=found.found, p=ray(dr.select(found.found, t, 0.0)), n=n, slot=found.slot,
                      counts=found.counts)

    # ---- Mitsuba medium interface -------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        # only Mitsuba's sample_interaction calls this (amrvolpath tracks by
        # segments itself): a stock integrator is rendering this medium
        _warn_if_volpath_is_slower(self)
        _warn_if_emission_is_ignored(self)
        _warn_if_iso_is_ignored(self)
        key = self._ray_majorant.key_of(ray)
        o, d, s = self.local_ray(ray)
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        t0, t1 = self._clipped(o, d, t0, t1)
        hit &= (s > 0.0) & (t0 <= t1)
        global_mu = self.structures.global_majorant
        local = LocalRay(o=o, d=d, t_lo=dr.maximum(t0, 0.0), t_hi=dr.minimum(t1, ray.maxt * s), scale=s)
        if self.majorant_mode == "global":
            return hit & (global_mu > 0.0), local.world_t(t0), local.world_t(t1)
        segments = self.structures.segments()
        span = walk_segments(segments, local, hit, SpanMajorant(global_mu, self._span_stop),
                             segments.max_steps())
        if self._differentiated():
            # the ray's majorant raised (`MajorantMargin`'s defaults), over the
            # whole cube: a null collision wherever sigma_t may change
            self._ray_majorant.store(key, self.majorant_margin(GRADIENT_MARGIN, GRADIENT_FLOOR)(span.mu))
            return hit & (global_mu > 0.0), local.world_t(t0), local.world_t(t1)
        self._ray_majorant.store(key, span.mu)
        return span.found, span.t_first, span.t_last

    def _majorant_for(self, mei):
        """The ray-wise majorant where ``mei`` belongs to the ray last passed
        to ``intersect_aabb`` (Mitsuba's sample_interaction), else the global
        one, raised while differentiated (`_differentiated`): never below
        sigma_t on the caller's ray."""
        mu = self._ray_majorant.lookup(mei)
        if mu is None:
            mu = self.structures.global_majorant
            return mu * GRADIENT_MARGIN if self._differentiated() else mu
        return mu

    def _differentiated(self) -> bool:
        """Whether a parameter of the extinction (density scale, TF table,
        cell values) has gradients enabled. Mitsuba's integrators then get
        the ray's majorant raised as `MajorantMargin` raises a leaf's
        (`GRADIENT_MARGIN` times it plus `GRADIENT_FLOOR` of the global one)
        over the whole cube, not over the ray's span: where a majorant
        equals sigma_t (a constant region)
        no null collision is sampled, and the derivative of sigma_t that
        they carry would be lost (docs/design.md section 13b). Checked with
        gradients resumed (Mitsuba renders under ``dr.suspend_grad``)."""
        c = self.classification
        with dr.resume_grad():
            return any(dr.grad_enabled(v) for v in (c.scale, c.tf_rgba, self._values))

    def get_majorant(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._majorant_for(mei)
        return mi.UnpolarizedSpectrum(dr.select(mu > 0.0, mu, 1.0))

    def get_scattering_coefficients(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._majorant_for(mei)
        self._ray_majorant.clear()       # sample_interaction calls this last
        albedo, sigma_t = self.eval_local(self._to_local @ mei.p, active, mei.wavelengths)
        sigma_s = albedo * sigma_t
        sigma_n = dr.maximum(mu - sigma_t, 0.0)
        return (mi.UnpolarizedSpectrum(sigma_s), mi.UnpolarizedSpectrum(sigma_n),
                mi.UnpolarizedSpectrum(sigma_t))

    # ---- Scene parameters (mi.traverse) ------------------------------------------
    def traverse(self, callback):
        """Expose ``density_scale``, the TF table ``tf_rgba`` (flat float
        array, N x 4, row major), ``tf_domain`` ([lo, hi]), for a medium
        that glows ``emission_scale``, ``emission_rgba`` and
        ``emission_domain``, and the nested phase function;
        ``params.update()`` then reclassifies the medium exactly as
        `set_transfer_function` (`set_emission`) does."""
        self.classification.traverse(callback)
        callback.put("values", self._values, mi.ParamFlags.Differentiable)
        callback.put("phase_function", self.phase_function(), mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=None):
        """Validate the updated parameters (a bad value raises and the last
        valid ones are put back), then use them (`_apply_values`,
        `Classification.apply_parameters`)."""
        if not keys or "values" in keys:
            self._apply_values()
        self.classification.apply_parameters(keys or None)

    def _apply_values(self):
        """Take the cell values ``params.update()`` wrote into ``values``.

        They must keep the layout: finite where a cell is, NaN in the empty
        slots (else a `ParameterError`, and the last valid values are put
        back). The kernels then read that very variable (with its gradient,
        if enabled). New values re-range the macrocell grid in place
        (`Structures.revalue`) or, for other structures, rebuild them on
        the new values (every leaf's value range, then the majorants from
        the TF: docs/design.md section 13); unchanged values (gradients just
        enabled) only make the look-ups read the variable."""
        var, old = self._values, self.volume.values
        host = np.asarray(dr.detach(var).numpy(), dtype=np.float32)
        empty = np.isnan(old)
        if host.shape != old.shape or not np.array_equal(np.isnan(host), empty) \
                or not np.all(np.isfinite(host[~empty])):
            mi.set_property(var, mi.Float(np.array(old, dtype=np.float32)))
            dr.make_opaque(var)
            raise ParameterError(f"amr: values must hold {old.size} values, finite where a cell is and NaN "
                                 f"in the {int(empty.sum())} empty slots (the layout of `value_index`); "
                                 f"the last valid values were put back")
        dr.make_opaque(var)
        if np.array_equal(host, old, equal_nan=True):
            for struct in self.structures.device.values():
                if "values" in getattr(struct, "JIT_FIELDS", {}):
                    struct.values = var
            return
        volume = self.volume.with_values(host)
        commit_values(volume, var)           # the structures read the parameter itself
        with dr.suspend_grad():              # host builds: no gradient graph
            if not self.structures.revalue(volume, var):
                self._build_structures(volume)

    def value_index(self, cells=None) -> np.ndarray:
        """For each cell of ``cells`` (an `AMRCells`; default: the cells
        given as ``data``, else `cells`) its index in the ``values``
        parameter (int64; -1 where this medium holds no such cell): block
        ``b``, slot ``s`` of the resident `volume` is index ``b B^3 + s``
        (`BlockVolume.value_index`). ``params[key][value_index()]`` lists
        the cells' values in the order of ``cells``; the other slots are
        NaN (no cell)."""
        cells = self.cells if cells is None else cells
        return self.volume.value_index(cells.pos, cells.level)

    def set_transfer_function(self, tf: TransferFunction, density_scale=None):
        """Use a new TF (new table, domain or size) and/or density scale: the
        same path as ``params.update()`` (`Classification.set`): uploads the
        small table, rebuilds what was built for the old classification (the
        pre-classified kd-tree) and recomputes every majorant; no kernel is
        recompiled (all TF data are opaque)."""
        self.classification.set(tf, density_scale)

    def to_string(self):
        return (f"AMRMedium[\n  cells = {len(self.volume)},\n  levels = "
                f"{self.volume.levels.tolist()},\n  reconstruction = {self.reconstruction},\n"
                f"  majorant = {self.majorant_mode},\n  traversal = {self.traversal},\n"
                f"  sampling = {self.sampling},\n  structures = {sorted(self.structures.built)},\n"
                f"  density_scale = {self.density_scale},\n  transfer_function = {self.tf}\n]")


def medium_class():
    """The ``amr`` medium class of the active variant."""
    return AMRMedium.variant_class()
