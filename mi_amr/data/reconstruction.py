"""Reconstruction methods of the scalar field f(x) from AMR cells.

Methods (docs/design.md section 3), ``x`` in finest-level cell units:

* ``tent`` (default): ``f(x) = sum_i phi_i(x) v_i / sum_i phi_i(x)`` with
  ``phi_i(x) = prod_k max(0, 1 - |x_k - c_ik| / w_i)``; continuous across
  level boundaries, trilinear inside a same-level region. No value where
  ``sum phi <= 1e-20``. Cost: one block lookup (8 values) per level that can contribute.
* ``nearest``: the value of the finest cell containing ``x`` (piecewise
  constant). Cost: one hash lookup per level, coarsest first, stopping at
  the first hit (leaf cells do not overlap, so the order does not change
  the cell found).

Implementations: `mi_amr.testing.brute_force` (numpy, O(cells) per point,
the test oracle), `mi_amr.structures.host_reconstruction` (numpy over the
blocks of a `BlockVolume`, for dense references) and the samplers of `mi_amr.device`
(Dr.Jit, while rendering).
"""

from __future__ import annotations

METHODS = ("tent", "nearest")
WEIGHT_EPS = 1e-20


def check_method(method: str) -> str:
    if method not in METHODS:
        raise ValueError(f"unknown reconstruction {method!r} (choose from {', '.join(METHODS)})")
    return method


# ---- numpy oracle --------------------------------------------------------
