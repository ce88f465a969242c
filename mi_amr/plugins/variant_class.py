"""Plugin classes defined once and built for each Mitsuba variant.

Mitsuba's base classes (``mi.Medium``, ``mi.SamplingIntegrator``) differ
per variant, so a class deriving from one at import time is bound to the
variant active then. A class with the `VariantPlugin` metaclass holds the
plugin's methods only; `VariantPlugin.variant_class` derives the real
plugin class from the active variant's base on first use. Calling the
class instantiates that variant class, and ``isinstance`` holds for the
instances of every variant.
"""

from __future__ import annotations

import mitsuba as mi

_SKIP = ("__dict__", "__weakref__", "_variants", "_mitsuba_base")


class VariantPlugin(type):
    """Metaclass; ``base`` names the Mitsuba base class (``"Medium"``), or
    is a function returning the active variant's base class."""

    def __new__(mcls, name, bases, ns, base: str = "Object"):
        cls = super().__new__(mcls, name, bases, ns)
        cls._mitsuba_base = base
        cls._variants = {}
        return cls

    def __init__(cls, name, bases, ns, base: str = "Object"):
        super().__init__(name, bases, ns)

    def variant_class(cls):
        """The plugin class for the active variant."""
        variant = mi.variant()
        if variant not in cls._variants:
            ns = {}
            for klass in reversed(cls.__mro__[:-1]):     # a plugin's own methods override its parents'
                ns.update({k: v for k, v in vars(klass).items() if k not in _SKIP})
            base = cls._mitsuba_base
            base = base() if callable(base) else getattr(mi, base)
            cls._variants[variant] = type(cls.__name__, (base,), ns)
        return cls._variants[variant]

    def __call__(cls, *args, **kwargs):
        return cls.variant_class()(*args, **kwargs)

    def __instancecheck__(cls, obj):
        return type(obj) in cls._variants.values()
