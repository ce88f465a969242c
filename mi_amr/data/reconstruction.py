"""The reconstruction methods' names, kept importable here for existing
callers (the ``amr`` options); the methods themselves live in
`mi_amr.reconstruction`, one module each (docs/design.md section 3)."""

from __future__ import annotations

from ..reconstruction import METHODS, WEIGHT_EPS, check_method, reconstruction_method

__all__ = ["METHODS", "WEIGHT_EPS", "check_method", "reconstruction_method"]
