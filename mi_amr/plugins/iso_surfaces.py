"""The isosurfaces of an ``amr`` medium: its iso values and their BSDFs
(docs/design.md section 15).

`IsoSurfaces` owns what the kernels read: the `MAX_ISO_VALUES` slots of
one opaque array (NaN where unused: a new value, or another number of
them, compiles nothing), the value tolerance of a hit, the factor that
keeps or removes the medium's own density (``iso_only``), and one BSDF per
slot as a pointer array that the integrator gathers by the slot of a hit.
A slot without a BSDF of the user's gets a two-sided diffuse one coloured
by the TF at its value (`surface_colours`), recoloured on every TF change.

Values are in the medium's value units: after its ``value_transform``
(log10 units for a ``log10`` medium), as ``tf_min``/``tf_max``.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..core.jit_struct import jit_struct, owned
from ..device.isosurface import ISO_VALUE_TOLERANCE, MAX_ISO_VALUES
from ..params import ParameterError


def parse_iso_values(spec, plugin: str = "amr") -> tuple[float, ...]:
    """Iso values from a parameter: a number, a string of numbers separated
    by spaces or commas, or a sequence of numbers; at most
    `MAX_ISO_VALUES`, each finite. A `ParameterError` names what is wrong."""
    if spec is None:
        return ()
    if isinstance(spec, str):
        parts = [p for p in spec.replace(",", " ").split() if p]
    elif isinstance(spec, (int, float, np.integer, np.floating)) and not isinstance(spec, bool):
        parts = [spec]
    else:
        try:
            parts = list(spec)
        except TypeError:
            raise ParameterError(f"{plugin}: iso must be numbers (a number, or a string such as '0.3 0.5'), "
                                 f"got {type(spec).__name__}") from None
    values = []
    for p in parts:
        try:
            v = float(p)
        except (TypeError, ValueError):
            raise ParameterError(f"{plugin}: iso values must be numbers, got {p!r}") from None
        if not math.isfinite(v):
            raise ParameterError(f"{plugin}: iso values must be finite, got {v}")
        values.append(v)
    if len(values) > MAX_ISO_VALUES:
        raise ParameterError(f"{plugin}: at most {MAX_ISO_VALUES} iso values, got {len(values)}")
    return tuple(values)


#: A TF colour darker than this (luminance) is no surface colour: the
#: default BSDF takes the nearest table entry that is lighter.
MIN_SURFACE_LUMINANCE = 0.05


def surface_colours(tf, values) -> np.ndarray:
    """The default BSDFs' reflectances (n, 3): the TF's colour at each
    value, or, where that is nearly black (the transparent ends of many
    TFs, a value outside the TF's domain), the colour of the nearest table
    entry that is not (light grey where none is)."""
    values = np.asarray(values, np.float64).reshape(-1)
    rgb = np.asarray(tf(values), np.float64)[:, :3]
    table = np.asarray(tf.rgba, np.float64)[:, :3]
    luminance = table @ np.array([0.2126, 0.7152, 0.0722])
    lit = np.flatnonzero(luminance >= MIN_SURFACE_LUMINANCE)
    dark = rgb @ np.array([0.2126, 0.7152, 0.0722]) < MIN_SURFACE_LUMINANCE
    for k in np.flatnonzero(dark):
        if len(lit) == 0:
            rgb[k] = 0.8
            continue
        position = tf.normalize(values[k]) * (len(table) - 1)
        rgb[k] = table[lit[np.argmin(np.abs(lit - position))]]
    return np.clip(rgb, 0.0, 1.0)


def default_bsdf(rgb) -> "mi.BSDF":
    """A two-sided diffuse BSDF of reflectance ``rgb`` (the TF's colour),
    opaque from the start: a slot's first value (its colour set) changes no
    literal of the kernels, so a frozen render replays (not recorded again)."""
    bsdf = mi.load_dict({"type": "twosided", "surface": {"type": "diffuse", "reflectance": {
        "type": "rgb", "value": [float(c) for c in np.clip(rgb, 0.0, 1.0)]}}})
    params = mi.traverse(bsdf)
    key = next(name for name in params.keys() if name.endswith("reflectance.value"))
    colour = mi.Color3f(*[float(c) for c in np.clip(rgb, 0.0, 1.0)])
    dr.make_opaque(colour)
    params[key] = colour
    params.update()
    return bsdf


@jit_struct(slots="Float", tolerance="Float", volume_on="Float", pointers="BSDFPtr")
class IsoSurfaces:
    """Iso values, their BSDFs and the kernels' view of them (see the module
    docstring); a device struct (`jit_struct`), so that ``dr.freeze`` sees
    its arrays as inputs: a frozen render follows `set` without recording
    again, and records again when the first value makes ``pointers``. ``span``: the data's value range width (value units), which
    scales the hit tolerance; ``tf``: the medium's TF (`TransferFunction`),
    whose colours the default BSDFs take (`set_tf` after a change)."""

    def __init__(self, values=(), bsdfs=(), only: bool = False, *, span: float, tf):
        self.tf = tf
        self.slots = dr.opaque(mi.Float, float("nan"), MAX_ISO_VALUES)
        self.tolerance = dr.opaque(mi.Float, ISO_VALUE_TOLERANCE * max(float(span), 1e-30))
        self.volume_on = dr.opaque(mi.Float, 1.0)
        self.values: tuple[float, ...] = ()
        self.only = False
        self.user_bsdfs: list = [None] * MAX_ISO_VALUES
        self.bsdfs: list = []                # one per slot, made when the first value is set
        self.pointers = None
        self.set(values, bsdfs, only)

    @property
    def enabled(self) -> bool:
        """Whether the kernels search for surfaces: once a value was set
        (a Python constant of the kernels; moving, adding or removing
        values afterwards compiles nothing)."""
        return bool(self.bsdfs)

    def set(self, values=None, bsdfs=None, only: bool | None = None):
        """New iso values (None keeps them), BSDFs by slot (a sequence, None
        entries or a short list keeping the default; None keeps the
        user's) and ``only`` (the medium's own density off while values
        are set; None keeps it). Validated first: a bad value changes nothing."""
        values = self.values if values is None else parse_iso_values(values)
        if bsdfs is not None:
            bsdfs = list(bsdfs)
            if len(bsdfs) > MAX_ISO_VALUES:
                raise ParameterError(f"amr: at most {MAX_ISO_VALUES} iso BSDFs, got {len(bsdfs)}")
            if any(b is not None and not isinstance(b, mi.BSDF) for b in bsdfs):
                raise ParameterError("amr: iso BSDFs must be Mitsuba BSDFs")
        only = self.only if only is None else bool(only)
        self.values, self.only = values, only
        if bsdfs is not None:
            self.user_bsdfs = bsdfs + [None] * (MAX_ISO_VALUES - len(bsdfs))
        slots = np.full(MAX_ISO_VALUES, np.nan, np.float32)
        slots[:len(values)] = values
        self.slots = owned(mi.Float, slots)     # a copy of its own, aligned: a frozen render replays
        dr.make_opaque(self.slots)
        self.volume_on = dr.opaque(mi.Float, 0.0 if (only and values) else 1.0)
        if values and not self.bsdfs:
            self.bsdfs = [default_bsdf((0.8, 0.8, 0.8)) for _ in range(MAX_ISO_VALUES)]
        if self.bsdfs:
            self.recolour()

    def recolour(self):
        """The default BSDFs' colours: the TF's at their values (after a
        value or TF change); the pointer array of the slots' BSDFs."""
        if not self.bsdfs:
            return
        rgb = surface_colours(self.tf, self.values) if self.values else np.zeros((0, 3))
        for k, value in enumerate(self.values):
            params = mi.traverse(self.bsdfs[k])
            key = next(name for name in params.keys() if name.endswith("reflectance.value"))
            colour = mi.Color3f(*[float(c) for c in np.clip(rgb[k, :3], 0.0, 1.0)])
            dr.make_opaque(colour)
            params[key] = colour
            params.update()
        chosen = [u if u is not None else b for u, b in zip(self.user_bsdfs, self.bsdfs)]
        self.pointers = mi.BSDFPtr(chosen)
        dr.make_opaque(self.pointers)

    def set_tf(self, tf):
        """The medium's new TF: the default BSDFs take its colours."""
        self.tf = tf
        self.recolour()

    def bsdf(self, slot, active=True) -> "mi.BSDFPtr":
        """The BSDF of each lane's iso slot."""
        return dr.gather(mi.BSDFPtr, self.pointers, mi.UInt32(slot), active)
