"""What a yt data set holds, from its headers and index alone: no field
value is read (``mi-amr info DATA`` without ``--field``).

Levels are counted as yt counts them: 0 = the root (coarsest) level, unlike
`AMRCells` (0 = finest). Grid codes (Enzo, AMReX, Athena++...): grids and
cells per level from ``ds.index.grid_levels``/``grid_dimensions``, the cells
of every grid, also those a finer grid covers, where the code keeps them.
RAMSES: octs per level from the AMR files' headers (yt's
``domain.level_count``), cells 8 per oct, leaves 8 per oct less the octs of
the level below; other octree codes: the number of levels only. Cell
sizes in code units (``code_length``) and, with yt's length unit, in cm.
"""

from __future__ import annotations

import numpy as np

from .yt_import import CODE_NAMES, _is_octree, require_3d


def summarise(ds) -> dict:
    """Code, dimensionality, domain, levels and every field with its units
    (on disk and derived by yt) of a loaded, 3-D yt data set, as plain JSON
    types."""
    require_3d(ds)
    frontend = type(ds).__module__.split(".")[2] if type(ds).__module__.startswith("yt.frontends.") else ""
    dle = np.asarray(ds.domain_left_edge.to("code_length").d, np.float64)
    dre = np.asarray(ds.domain_right_edge.to("code_length").d, np.float64)
    root = np.asarray(ds.domain_dimensions, np.int64)
    ratio = float(np.atleast_1d(getattr(ds, "refine_by", 2) or 2)[0])
    index = ds.index
    octree = _is_octree(index)
    rows = _octree_levels(ds, index) if octree else _grid_levels(index)
    for row in rows:
        row["cell_size"] = ((dre - dle) / (root * ratio ** row["level"])).tolist()
    try:
        cm = float(ds.length_unit.in_cgs().d)
    except Exception:          # a frontend without a length unit
        cm = None
    disk = [tuple(f) for f in ds.field_list]
    derived = [tuple(f) for f in ds.derived_field_list if tuple(f) not in set(disk)]
    return {
        "dataset": str(getattr(ds, "parameter_filename", ds)),
        "code": CODE_NAMES.get(frontend, frontend or type(ds).__name__),
        "dataset_type": str(getattr(ds, "dataset_type", "")),
        "dimensionality": 3, "index": "octree" if octree else "grids",
        "domain": {"left": dle.tolist(), "right": dre.tolist(), "unit": "code_length", "cm_per_unit": cm,
                   "root_cells": root.tolist(), "refine_by": ratio},
        "max_level": int(getattr(index, "max_level", getattr(ds, "max_level", 0))),
        "levels": rows,
        "fields_on_disk": {",".join(f): _units(ds, f) for f in disk},
        "fields_derived": {",".join(f): _units(ds, f) for f in derived},
    }


def _grid_levels(index) -> list[dict]:
    """Per level: grids and the cells they hold (yt's index arrays)."""
    levels = np.asarray(index.grid_levels).ravel()
    cells = np.prod(np.asarray(index.grid_dimensions, np.int64), axis=1)
    return [{"level": int(L), "grids": int((levels == L).sum()), "cells": int(cells[levels == L].sum())}
            for L in np.unique(levels)]


def _octree_levels(ds, index) -> list[dict]:
    """Per level: octs, cells and leaf cells where the reader counts octs
    per level (RAMSES), else only the level numbers."""
    counts = [getattr(d, "level_count", None) for d in getattr(index, "domains", [])]
    if counts and all(c is not None for c in counts):
        octs = sum(np.asarray(c, np.int64) for c in counts)        # as yt's own level_stats sums them
        octs = octs.reshape(-1, octs.shape[-1]).sum(axis=0)
        octs = octs[:np.flatnonzero(octs)[-1] + 1] if octs.any() else octs[:1]
        below = np.r_[octs[1:], 0]
        return [{"level": L, "octs": int(n), "cells": int(8 * n), "leaf_cells": int(8 * n - m)}
                for L, (n, m) in enumerate(zip(octs, below))]
    top = int(getattr(index, "max_level", getattr(ds, "max_level", 0)))
    return [{"level": L} for L in range(top + 1)]


def _units(ds, field) -> str:
    """The units yt gives ``field`` ('' when it cannot say)."""
    try:
        return str(ds.field_info[field].units)
    except Exception:          # yt's field lookup varies by frontend: units are informative only
        return ""
