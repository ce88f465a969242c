"""Typed reading of plugin parameters (``mi.Properties``) with errors that
name the plugin, the parameter, the value and what was expected.

Mitsuba's XML parser types values itself (``<float>``, ``<integer>``,
``<string>``); Python scene dictionaries can hold anything, so every value is
checked here before it is used.
"""

from __future__ import annotations

import math
import numbers


class ParameterError(ValueError):
    """A plugin parameter with a wrong type or value."""


def _describe(v) -> str:
    return f"{v!r} ({type(v).__name__})"


def get_float(props, plugin: str, name: str, default, *, minimum=None, maximum=None, positive=False):
    """A finite real number (int or float; not bool, not a string)."""
    if name not in props.keys():
        return default
    v = props[name]
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ParameterError(f"{plugin}: {name} must be a number, got {_describe(v)}")
    v = float(v)
    if not math.isfinite(v):
        raise ParameterError(f"{plugin}: {name} must be finite, got {v}")
    if minimum is not None and v < minimum:
        raise ParameterError(f"{plugin}: {name} must be >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise ParameterError(f"{plugin}: {name} must be <= {maximum:g}, got {v:g}")
    if positive and v <= 0:
        raise ParameterError(f"{plugin}: {name} must be > 0, got {v}")
    return v


def get_int(props, plugin: str, name: str, default, *, minimum=None, maximum=None):
    """An integer (a float only when it is integral, as XML may give)."""
    if name not in props.keys():
        return default
    v = props[name]
    if isinstance(v, numbers.Real) and not isinstance(v, bool) and not isinstance(v, numbers.Integral):
        if not (math.isfinite(v) and float(v).is_integer()):
            raise ParameterError(f"{plugin}: {name} must be an integer, got {_describe(v)}")
    elif isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ParameterError(f"{plugin}: {name} must be an integer, got {_describe(v)}")
    v = int(v)
    if minimum is not None and v < minimum:
        raise ParameterError(f"{plugin}: {name} must be >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise ParameterError(f"{plugin}: {name} must be <= {maximum}, got {v}")
    return v


def get_bool(props, plugin: str, name: str, default: bool) -> bool:
    if name not in props.keys():
        return default
    v = props[name]
    if not isinstance(v, bool):
        raise ParameterError(f"{plugin}: {name} must be true or false, got {_describe(v)}")
    return v


def get_string(props, plugin: str, name: str, default, choices=None) -> str:
    """A string, optionally one of ``choices``."""
    if name not in props.keys():
        return default
    v = props[name]
    if not isinstance(v, str):
        raise ParameterError(f"{plugin}: {name} must be a string, got {_describe(v)}")
    if choices is not None and v not in choices:
        raise ParameterError(f"{plugin}: unknown {name} {v!r} (choose from {', '.join(choices)})")
    return v


def check_known(props, plugin: str, known, allow=lambda key, value: False):
    """Refuse parameters outside ``known`` (unless ``allow(key, value)``)."""
    for k in props.keys():
        if k in known or allow(k, props[k]):
            continue
        raise ParameterError(f"{plugin}: unknown parameter {k!r} (known: {', '.join(sorted(known))})")


def plugin_error(message: str) -> str:
    """Mitsuba's "failed to instantiate" message without the plugin's
    traceback: where it happened and the exception it raised (one line)."""
    where, _, trace = message.partition("Traceback (most recent call last):")
    lines = [ln for ln in trace.splitlines() if ln.strip()]
    return f"{where.strip()} {lines[-1].strip()}" if lines else where.strip()
