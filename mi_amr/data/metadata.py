"""Physical metadata that travels with AMR data.

Cells are stored in finest-level index units; what they mean physically is
kept beside them as a small dict (``AMRCells.meta``, ``BlockVolume.meta``):

* ``domain_left_edge``, ``domain_right_edge`` (3 floats each) and
  ``domain_cells`` (3 ints: the domain in finest-level cells): cell ``i``
  spans ``left + i * (right - left) / domain_cells`` along each axis, so
  cells may be anisotropic; ``length_unit`` names the unit;
* ``field``, ``units``, ``code``: what the values are and what wrote them;
* ``value_transform``, ``log_floor``: set when the values were replaced by
  their log10 (`mi_amr.data.transform`).

``.npz`` files keep it as a JSON string member ``meta``; ``.cells`` files in
a sidecar ``NAME.cells.json`` (ExaBricks tools ignore it). Files without it
keep working: their cells are unit cubes and their bounds are the domain.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

DOMAIN_KEYS = ("domain_left_edge", "domain_right_edge", "domain_cells")


def sidecar_path(cells_path) -> Path:
    return Path(str(cells_path) + ".json")


def read_sidecar(cells_path) -> dict:
    p = sidecar_path(cells_path)
    if not p.is_file():
        return {}
    try:
        meta = json.loads(p.read_text())
    except ValueError as e:
        raise ValueError(f"{p}: not valid JSON metadata ({e})") from e
    return check(meta, str(p))


def check(meta: dict, source: str) -> dict:
    """``meta`` if its domain entries are consistent, else a `ValueError`."""
    if not isinstance(meta, dict):
        raise ValueError(f"{source}: metadata must be a JSON object")
    present = [k for k in DOMAIN_KEYS if k in meta]
    if present and len(present) != len(DOMAIN_KEYS):
        raise ValueError(f"{source}: metadata has {present} but not all of {list(DOMAIN_KEYS)}")
    if present:
        lo, hi = np.asarray(meta["domain_left_edge"], float), np.asarray(meta["domain_right_edge"], float)
        n = np.asarray(meta["domain_cells"])
        if lo.shape != (3,) or hi.shape != (3,) or n.shape != (3,) or not np.all(np.isfinite(lo)) \
                or not np.all(hi > lo) or not np.all(n >= 1):
            raise ValueError(f"{source}: metadata domain must be 3 finite left < right edges and 3 cell "
                             f"counts >= 1, got {meta['domain_left_edge']}, {meta['domain_right_edge']}, "
                             f"{meta['domain_cells']}")
    return meta


def cell_size(meta: dict) -> np.ndarray | None:
    """Physical size of a finest-level cell (3,), or None without a domain."""
    if not all(k in meta for k in DOMAIN_KEYS):
        return None
    lo, hi = np.asarray(meta["domain_left_edge"], float), np.asarray(meta["domain_right_edge"], float)
    return (hi - lo) / np.asarray(meta["domain_cells"], float)


def physical_box(data) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lower corner, extent)`` of the data's bounds in physical units, or
    None when the data carry no domain."""
    dx = cell_size(getattr(data, "meta", {}) or {})
    if dx is None:
        return None
    lo, hi = data.bounds
    left = np.asarray(data.meta["domain_left_edge"], float)
    return left + lo * dx, (hi - lo) * dx
