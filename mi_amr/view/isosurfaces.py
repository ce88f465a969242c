"""A view's isosurfaces (docs/manual/isosurfaces.md): its iso values,
checked against the data, and put into the scene's medium before each of
its passes.

A view holds up to `MAX_ISO_VALUES` iso values in the **field's own units**
(the values the data hold, before the log10 a medium may store: the units of
``mi-amr render --iso`` and ``DataScene.iso``) and whether the surfaces are
drawn alone (``only``: the gas off). The page shows them over the TF
editor's histogram in its display units (log10 of them in the log10
display). `apply_iso` puts them into the medium in its value units (log10
of them where it stores log10 values) through `AMRMedium.set_iso`: opaque
slots, so moving, adding or removing a value replays the frozen passes and
compiles nothing. The first value given to a medium loaded without any
makes its kernels search for surfaces (`AMRMedium.has_iso`): every
recording is then dropped and made again, once (`apply_iso` says so, and
the scheduler records ahead again).
"""

from __future__ import annotations

import math

import numpy as np

from ..device.isosurface import MAX_ISO_VALUES
from ..plugins.integrator import AMRVolpathIntegrator
from .scene import LoadedScene

#: A value this share of the data's range beyond either end is still taken
#: (round-off of the page's log10 and back), and put at that end.
RANGE_SLACK = 1e-6


def iso_note(loaded: LoadedScene) -> str:
    """Why the scene cannot draw isosurfaces ("" when it can): its
    integrator must be ``amrvolpath`` (or ``amrprbvolpath``)."""
    if loaded.scene is None or loaded.medium is None:
        return "no scene is loaded"
    integrator = loaded.scene.integrator()
    if isinstance(integrator, AMRVolpathIntegrator):
        return ""
    kind = integrator.class_name() if integrator is not None else "none"
    return f"the scene's integrator is {kind}: isosurfaces need amrvolpath"


def value_range(loaded: LoadedScene) -> tuple[float, float]:
    """The data's values ``(lo, hi)`` in the field's own units (``10**`` of
    the medium's where it stores log10 values)."""
    lo, hi = (float(x) for x in loaded.medium.volume.value_range)
    return (10.0 ** lo, 10.0 ** hi) if loaded.stored_log else (lo, hi)


def check_iso(loaded: LoadedScene, values) -> tuple[float, ...]:
    """``values`` (field units) as the view keeps them: at most
    `MAX_ISO_VALUES` finite numbers inside the data's range (`value_range`;
    a value within `RANGE_SLACK` outside is put at the end). A `ValueError`
    names what is wrong."""
    note = iso_note(loaded)
    if note:
        raise ValueError(f"iso: {note}")
    try:
        values = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"iso: numbers in the field's own units, got {values!r}") from None
    if len(values) > MAX_ISO_VALUES:
        raise ValueError(f"iso: at most {MAX_ISO_VALUES} values, got {len(values)}")
    lo, hi = value_range(loaded)
    slack = RANGE_SLACK * max(hi - lo, abs(hi), 1e-300)
    out = []
    for v in values:
        if not math.isfinite(v) or not lo - slack <= v <= hi + slack:
            raise ValueError(f"iso: {v:.6g} lies outside the data's values, {lo:.6g} to {hi:.6g} "
                             f"({'field units' if not loaded.units else loaded.units})")
        out.append(min(max(v, lo), hi))
    return tuple(out)


def medium_values(loaded: LoadedScene, values) -> tuple[float, ...]:
    """Field-unit ``values`` in the medium's value units."""
    values = np.asarray(values, np.float64)
    return tuple(float(v) for v in (np.log10(values) if loaded.stored_log else values))


def field_values(loaded: LoadedScene, values) -> tuple[float, ...]:
    """The medium's value-unit ``values`` in the field's own units."""
    values = np.asarray(values, np.float64)
    return tuple(float(v) for v in (10.0 ** values if loaded.stored_log else values))


def scene_iso(loaded: LoadedScene) -> tuple[tuple[float, ...], bool]:
    """``(values, only)`` the scene's medium was loaded with (field units):
    where a new view starts."""
    return field_values(loaded, loaded.medium.iso_values), bool(loaded.medium.iso_only)


def apply_iso(loaded: LoadedScene, values, only: bool) -> bool:
    """A view's isosurfaces (field units) into the medium, when others are
    there (under `JIT_LOCK`). Returns whether its kernels changed (the first
    value of a medium loaded without any): the frozen passes are then
    dropped, to be recorded again."""
    key = (tuple(values), bool(only))
    if loaded.applied.get("iso") == key:
        return False
    searched = loaded.medium.has_iso
    loaded.medium.set_iso(medium_values(loaded, values), only=bool(only))
    loaded.applied["iso"] = key
    if loaded.medium.has_iso != searched:
        loaded.passes.clear()
        return True
    return False


def iso_hello(loaded: LoadedScene, values, only: bool) -> dict:
    """`protocol.Hello`'s ``iso``: the view's ``values`` (field units) and
    ``only``, the most values, the data's ``range`` (field units; None
    without a medium), ``note`` why there are no isosurfaces ("" where
    there are), ``searching``: whether the kernels search for surfaces
    already (else the first value records the passes again, once)."""
    medium = loaded.medium
    return {"values": [float(v) for v in values], "only": bool(only), "max": MAX_ISO_VALUES,
            "range": None if medium is None else list(value_range(loaded)), "note": iso_note(loaded),
            "searching": bool(medium is not None and medium.has_iso)}
