"""Reconstruction methods of the scalar field f(x) from AMR cells.

One object per method, chosen once where the ``reconstruction`` option (or
any other string) comes in: `reconstruction_method` resolves a name and
passes a method object through. Everything that depends on the method asks
the object (`mi_amr.reconstruction.base` lists what it supplies), never its
name. Methods (docs/design.md section 3), ``x`` in finest-level cell units:

* ``tent`` (`mi_amr.reconstruction.tent`, the default): normalised tent
  weights, continuous across levels, trilinear inside a same-level region.
  Cost: one block look-up (8 values) per level that can contribute.
* ``nearest`` (`mi_amr.reconstruction.nearest`): the value of the finest
  cell containing ``x`` (piecewise constant). Cost: one hash look-up per
  level, coarsest first, stopping at the first hit.

Implementations of each: the numpy oracle over all cells
(`mi_amr.testing.brute_force`), numpy over the blocks of a `BlockVolume`
(`mi_amr.structures.host_reconstruction`, for dense references) and the
Dr.Jit samplers of `mi_amr.device` (while rendering).

A new method: a module with a `Reconstruction` subclass, and its line in
`METHODS`.
"""

from __future__ import annotations

from .base import WEIGHT_EPS, Reconstruction
from .nearest import Nearest
from .tent import Tent

#: The methods by option name; the first is the default.
METHODS: dict[str, type[Reconstruction]] = {
    "tent": Tent,
    "nearest": Nearest,
}

#: The default method's object (the defaults of functions that take a method).
DEFAULT_METHOD: Reconstruction = Tent()

__all__ = ["DEFAULT_METHOD", "METHODS", "WEIGHT_EPS", "Reconstruction", "check_method", "reconstruction_method"]


def reconstruction_method(method: str | Reconstruction) -> Reconstruction:
    """The method object of a name in `METHODS`, or ``method`` itself when
    it is one already; `ValueError` for an unknown name."""
    if isinstance(method, Reconstruction):
        return method
    if isinstance(method, str) and method in METHODS:
        return METHODS[method]()
    raise ValueError(f"unknown reconstruction {method!r} (choose from {', '.join(METHODS)})")


def check_method(method: str | Reconstruction) -> str:
    """The name of a known method (`ValueError` otherwise)."""
    return reconstruction_method(method).name
