"""The one device copy of a volume's cell values."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


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
