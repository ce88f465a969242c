"""yt grid hierarchies -> AMRCells.

yt numbers levels from the coarsest (0) and keeps every grid's cells, also
those covered by finer grids; AMRCells number levels from the finest (0)
and hold leaf cells only. `from_yt` keeps the cells each grid's
``child_mask`` marks as not covered, inverts the level numbering and places
every cell in finest-level units from the domain's left edge.
"""

from __future__ import annotations

import numpy as np

from .cells import AMRCells


def from_yt(ds, field, *, overlap: str = "error") -> AMRCells:
    """Leaf cells of any grid-based yt dataset (Enzo, FLASH, AMReX/BoxLib,
    Athena++, ``yt.load_amr_grids``...) with the values of ``field`` (a name
    or a ``(type, name)`` tuple). Only ``refine_by = 2`` is supported."""
    refine_by = int(np.max(np.atleast_1d(getattr(ds, "refine_by", 2))))
    if refine_by != 2:
        raise ValueError(f"{ds}: refine_by = {refine_by}; AMR cells need a refinement ratio of 2")
    max_level = int(ds.index.max_level)
    dle = np.asarray(ds.domain_left_edge.to("code_length").d, dtype=np.float64)
    dre = np.asarray(ds.domain_right_edge.to("code_length").d, dtype=np.float64)
    dims0 = np.asarray(ds.domain_dimensions, dtype=np.int64)
    dx_finest = (dre - dle) / (dims0 * (1 << max_level))
    pos, level, value = [], [], []
    for g in ds.index.grids:
        mask = np.asarray(g.child_mask, dtype=bool)
        if not mask.any():
            continue
        amr_level = max_level - int(g.Level)
        w = 1 << amr_level
        start = np.rint((np.asarray(g.LeftEdge.to("code_length").d) - dle) / dx_finest).astype(np.int64)
        ijk = np.argwhere(mask)
        pos.append(start + ijk * w)
        level.append(np.full(len(ijk), amr_level, dtype=np.int32))
        value.append(np.asarray(g[field], dtype=np.float64)[mask].astype(np.float32))
    if not pos:
        raise ValueError(f"{ds}: no leaf cells found")
    cells = AMRCells(np.concatenate(pos), np.concatenate(level), np.concatenate(value),
                     overlap=overlap, source=f"yt dataset {ds} field {field}")
    try:
        units = str(ds.field_info[field].units) if field in ds.field_info else ""
    except Exception:          # yt's field lookup varies by frontend: units are informative only
        units = ""
    cells.meta = {"domain_left_edge": dle.tolist(), "domain_right_edge": dre.tolist(),
                  "domain_cells": (dims0 * (1 << max_level)).tolist(), "length_unit": "code_length",
                  "field": str(field), "units": units,
                  "code": str(getattr(ds, "dataset_type", type(ds).__name__))}
    return cells


def world_transform(ds):
    """``to_world`` that maps the unit cube onto the dataset's domain (code
    units), for an ``amr`` medium built from `from_yt` data that covers the
    whole domain."""
    import mitsuba as mi
    dle = [float(x) for x in ds.domain_left_edge.to("code_length").d]
    ext = [float(b - a) for a, b in zip(ds.domain_left_edge.to("code_length").d,
                                        ds.domain_right_edge.to("code_length").d)]
    return mi.ScalarTransform4f().translate(dle) @ mi.ScalarTransform4f().scale(ext)
