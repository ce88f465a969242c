"""Device state as Dr.Jit structs (``DRJIT_STRUCT``).

Every Dr.Jit array a kernel reads lives in a struct field (or in a dict or
list of them) reachable from the Mitsuba object that uses it: ``dr.freeze``
and Dr.Jit's traversal of Python plugins see exactly those, and nothing in
plain helper objects (docs/design.md section 6).

Field types are named (``"Float"``, ``"UInt32"``, ...) and resolved against
the active Mitsuba variant, again on every variant change (`refresh`), so no
struct keeps the types of the variant that was active at import.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

_STRUCTS: list[type] = []


def jit_struct(**fields):
    """Class decorator: declare the Dr.Jit fields of a device struct.
    Values are Mitsuba type names (``"Vector3f"``) or Python types (``dict``)."""
    def wrap(cls):
        cls.JIT_FIELDS = dict(fields)
        _STRUCTS.append(cls)
        _resolve(cls)
        return cls
    return wrap


def _resolve(cls):
    if mi.variant() is None:
        cls.DRJIT_STRUCT = {k: object for k in cls.JIT_FIELDS}
        return
    # (a type this variant lacks, such as MediumPtr in scalar variants: the
    # plugins refuse those variants before any struct is made)
    cls.DRJIT_STRUCT = {k: (getattr(mi, v, object) if isinstance(v, str) else v)
                        for k, v in cls.JIT_FIELDS.items()}


def refresh():
    """Re-resolve every struct's field types for the active variant."""
    for cls in _STRUCTS:
        _resolve(cls)


#: Bytes of alignment of the host copies `owned` makes: one AVX-512 packet.
ALIGN = 64


def owned(array_type, host):
    """A 1-D ``array_type`` holding a fresh, 64-byte aligned copy of ``host``.

    On the CPU backend ``array_type(numpy_array)`` maps the NumPy memory
    instead of copying it. For tables that are uploaded again on every TF
    change this matters twice: two uploads of one host array alias one
    buffer (and an in-place edit of the host array reaches the kernels
    behind the majorants' back), and NumPy aligns to 16 bytes only, so
    whether an upload is packet-aligned changes from one allocation to the
    next. ``dr.freeze`` keys its recordings on both (a frozen render was
    recorded again after most TF changes: 10 recordings after 12 changes),
    and a kernel that loads the table contiguously compiles once per
    alignment. The cell values are shared with the host on purpose
    (`mi_amr.data.device_values`) and uploaded once."""
    dtype = {dr.VarType.Float32: np.float32, dr.VarType.UInt32: np.uint32}[dr.type_v(array_type)]
    host = np.asarray(host, dtype=dtype).ravel()
    buf = np.empty(host.size + ALIGN // host.itemsize, dtype=dtype)
    start = (-buf.ctypes.data % ALIGN) // host.itemsize
    copy = buf[start:start + host.size]
    copy[...] = host
    return array_type(copy)
