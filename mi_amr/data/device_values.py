"""The one device copy of a volume's cell values."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
from ..data.transform import log10_values, positive_floor


def device_values(volume) -> mi.Float:
    """The cell values of ``volume`` (a `BlockVolume`) as one opaque device
    array, made once per volume and variant, so that every structure and
    every medium on the same data reads the same copy. On the CPU backend
    the device array is host memory: the volume's ``values`` become a view
    of it, so the values are kept once in all."""
    values = volume.__dict__.get("_device_values")
    if not isinstance(values, mi.Float):        # none yet, or made for another variant
        values = mi.Float(volume.values)
        dr.make_opaque(values)
        volume._device_values = values
        if dr.backend_v(values) == dr.JitBackend.LLVM:
            volume.values = values.numpy()
    return values


def shares_host_values(values: mi.Float) -> bool:
    """Whether ``values`` are the volume's host values too (CPU backend)."""
    return dr.backend_v(values) == dr.JitBackend.LLVM


def device_field(volume, name: str | None, transform: str = "none") -> mi.Float:
    """A field of ``volume`` as an opaque device array laid out as its values
    (`BlockVolume.field`; None: the values themselves, `device_values`),
    with ``transform`` (``none`` or ``log10``, `mi_amr.data.transform`)
    applied; made once per (field, transform) and variant. On the CPU
    backend an untransformed field becomes a view of the device array, as
    the values do, so it is kept once."""
    if name is None and transform == "none":
        return device_values(volume)
    cache = volume.__dict__.setdefault("_device_fields", {})
    values = cache.get((name, transform))
    if not isinstance(values, mi.Float):
        host = volume.field(name)
        if transform == "log10":
            host = log10_values(host, positive_floor(host, f"{volume.source} field {name or 'value'}"))
        elif transform != "none":
            raise ValueError(f"unknown field transform {transform!r}")
        values = mi.Float(host)
        dr.make_opaque(values)
        cache[(name, transform)] = values
        if transform == "none" and dr.backend_v(values) == dr.JitBackend.LLVM:
            volume.fields[name] = values.numpy()
    return values


class CellValues:
    """What a reconstruction gathers at a cell: the main field's value and,
    where a medium needs a second field at the same points (the emission
    field of a glowing medium), that one too, from the same look-up
    (docs/design.md section 12). Both arrays share the volume's layout.

    A gathered value is a ``Float``, or a ``Vector2f`` (main, carried) when
    a field is carried; reconstruction sums and selects either alike."""

    def __init__(self, values: mi.Float, carried: mi.Float | None = None):
        self.values, self.carried = values, carried

    def zero(self):
        """The value of no cell (the loop state's start)."""
        return mi.Float(0.0) if self.carried is None else mi.Vector2f(0.0)

    def gather(self, index, active):
        """The value(s) of cells ``index`` of the volume's layout."""
        v = dr.gather(mi.Float, self.values, index, active)
        if self.carried is None:
            return v
        return mi.Vector2f(v, dr.gather(mi.Float, self.carried, index, active))

    @staticmethod
    def main(v):
        """The main field's part of a gathered value."""
        return v.x if isinstance(v, mi.Vector2f) else v
