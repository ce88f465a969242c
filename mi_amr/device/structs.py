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

import mitsuba as mi

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
    cls.DRJIT_STRUCT = {k: (getattr(mi, v) if isinstance(v, str) else v)
                        for k, v in cls.JIT_FIELDS.items()}


def refresh():
    """Re-resolve every struct's field types for the active variant."""
    for cls in _STRUCTS:
        _resolve(cls)
