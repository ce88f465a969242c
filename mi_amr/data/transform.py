"""Value transforms applied once when AMR data are loaded.

``log10``: densities of astrophysical simulations span many decades (a
cosmology run: 3e-31 to 3e-26 g/cm^3), so a TF only makes sense over their
logarithm. Values that have no logarithm (zero or negative) are first raised
to the *floor*, the smallest positive value of the data, so no NaN or -inf
ever reaches the TF; the floor is reported (and kept in converted files'
metadata). Cells absent from a block (NaN) stay absent.
"""

from __future__ import annotations

import numpy as np

from .blocks import BlockVolume
from .cells import AMRCells

VALUE_TRANSFORMS = ("none", "log10")
#: Values per chunk of the two passes over the data.
CHUNK = 1 << 22


def positive_floor(values: np.ndarray, source: str = "AMR data") -> float:
    """Smallest positive (finite) value, chunk by chunk; a `ValueError`
    naming ``source`` when there is none."""
    floor = np.inf
    for s in range(0, len(values), CHUNK):
        v = values[s:s + CHUNK]
        v = v[v > 0]
        if v.size:
            floor = min(floor, float(v.min()))
    if not np.isfinite(floor):
        raise ValueError(f"{source}: value_transform='log10' needs positive values, but none is above 0")
    return floor


def log10_values(values: np.ndarray, floor: float, out: np.ndarray | None = None) -> np.ndarray:
    """``log10(max(v, floor))`` as float32, chunk by chunk (NaN stays NaN);
    ``out`` may be ``values`` itself."""
    out = np.empty(values.shape, np.float32) if out is None else out
    for s in range(0, len(values), CHUNK):
        v = values[s:s + CHUNK].astype(np.float64)
        out[s:s + CHUNK] = np.log10(np.maximum(v, floor, where=~np.isnan(v), out=v.copy()))
    return out


def apply_value_transform(data: AMRCells | BlockVolume, kind: str, inplace: bool = False):
    """``(data with transformed values, floor or None)``. The input is
    copied unless ``inplace`` (a volume this process just loaded)."""
    if kind not in VALUE_TRANSFORMS:
        raise ValueError(f"value_transform must be one of {', '.join(VALUE_TRANSFORMS)}, got {kind!r}")
    if kind == "none":
        return data, None
    if data.meta.get("value_transform") == "log10":
        raise ValueError(f"{data.source}: the values are already log10 (metadata says so); "
                         f"use value_transform='none'")
    meta = dict(data.meta, value_transform="log10")
    if isinstance(data, AMRCells):
        floor = positive_floor(data.values, data.source)
        out = AMRCells(data.pos, data.level, log10_values(data.values, floor), validate=False,
                       source=f"log10 of {data.source}", fields=data.fields)
        out.meta = dict(meta, log_floor=floor)
        return out, floor
    floor = positive_floor(data.values, data.source)
    values = log10_values(data.values, floor, out=data.values if inplace else None)
    return BlockVolume(data.block, data.level, data.coord, values, data.origin, data.lo, data.hi,
                       data.n_cells, f"log10 of {data.source}", dict(meta, log_floor=floor),
                       fields=data.fields), floor
