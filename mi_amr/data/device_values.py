"""The one device copy of a volume's cell values.

A volume is committed to the device once per variant: its values (and any
further field a medium reads, under a transform) become opaque device
arrays that every structure and every medium on the same volume read. The
copies are kept in `DEVICE_COPIES`, keyed by the volume's identity (they go
with the volume; `mi_amr.core.identity_cache`), not on the volume: a
medium that takes new values commits them for its new volume
(`commit_values`), and a caller's data object carries nothing of ours. On
the CPU backend a device array is host memory: the volume's ``values`` (and
an untransformed field) become a view of it, so they are kept once in all.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
from ..core.identity_cache import IdentityCache
from ..data.transform import log10_values, positive_floor

#: Device arrays per volume (by identity) and (field, transform, variant).
DEVICE_COPIES = IdentityCache()


def device_values(volume) -> mi.Float:
    """The cell values of ``volume`` (a `BlockVolume`) as one opaque device
    array, made once per volume and variant (`DEVICE_COPIES`)."""
    return device_field(volume, None)


def commit_values(volume, values: mi.Float) -> None:
    """Make ``values`` (an opaque device array in ``volume``'s layout, such
    as a medium's ``values`` parameter) the device copy of ``volume``'s
    values, so that the structures built on ``volume`` read it."""
    DEVICE_COPIES.put(volume, (None, "none", mi.variant()), values)


def shares_host_values(values: mi.Float) -> bool:
    """Whether ``values`` are the volume's host values too (CPU backend)."""
    return dr.backend_v(values) == dr.JitBackend.LLVM


def device_field(volume, name: str | None, transform: str = "none") -> mi.Float:
    """A field of ``volume`` as an opaque device array laid out as its values
    (`BlockVolume.field`; None: the values themselves), with ``transform``
    (``none`` or ``log10``, `mi_amr.data.transform`) applied; made once per
    (field, transform) and variant."""
    if transform not in ("none", "log10"):
        raise ValueError(f"unknown field transform {transform!r}")

    def make():
        host = volume.values if name is None else volume.field(name)
        if transform == "log10":
            host = log10_values(host, positive_floor(host, f"{volume.source} field {name or 'value'}"))
        values = mi.Float(host)
        dr.make_opaque(values)
        if transform == "none" and shares_host_values(values):     # one copy in all (CPU backend)
            if name is None:
                volume.values = values.numpy()
            else:
                volume.fields[name] = values.numpy()
        return values
    return DEVICE_COPIES.get(volume, (name, transform, mi.variant()), make)


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
