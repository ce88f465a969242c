"""yt grid hierarchies -> AMRCells or the compact BlockVolume.

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
    or a ``(type, name)`` tuple), as per-cell records. Only ``refine_by = 2``
    is supported. For large data `from_yt_blocks` goes straight to the
    compact form."""
    layout = _layout(ds)
    parts = list(_grid_cells(ds, field, layout))
    if not parts:
        raise ValueError(f"{ds}: no leaf cells found")
    cells = AMRCells(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                     np.concatenate([p[2] for p in parts]), overlap=overlap,
                     source=f"yt dataset {ds} field {field}")
    cells.meta = _metadata(ds, field, layout)
    return cells


def from_yt_blocks(ds, field, *, overlap: str = "error", method: str = "tent", fields=()):
    """`from_yt` straight into a `BlockVolume`: each grid's uncovered cells
    (``child_mask``, vectorised over the grid) stream into the blocks, with
    the same validation and no per-cell array of the whole data set.
    ``fields``: further fields to read onto the same cells (names or
    ``(type, name)`` tuples; stored under their last name, e.g.
    ``temperature``, `BlockVolume.add_field`)."""
    from .blocks import BlockVolume
    layout = _layout(ds)
    vol = BlockVolume.from_chunks(lambda: _grid_cells(ds, field, layout), f"yt dataset {ds} field {field}",
                                  overlap=overlap, method=method)
    vol.meta = _metadata(ds, field, layout)
    for extra in fields:
        vol.add_field(field_key(extra), lambda extra=extra: _grid_cells(ds, extra, layout))
    return vol


def field_key(field) -> str:
    """The name a yt field is stored under beside the main one: its last
    part (``("gas", "temperature")`` -> ``temperature``)."""
    return str(field[-1] if isinstance(field, tuple) else field).split(",")[-1].strip()


def _layout(ds):
    """``(max_level, left edge, right edge, root cells, finest cell size)``
    of a grid-based 3D dataset with refine_by 2, or a ValueError naming
    what is not supported."""
    dim = int(getattr(ds, "dimensionality", 3))
    if dim != 3:
        raise ValueError(f"{ds}: {dim}D data are not supported; mi-amr renders 3D volumes")
    if not hasattr(ds.index, "grids"):
        kind = type(ds.index).__name__
        raise ValueError(f"{ds}: its index ({kind}) has no grid patches: octree-based AMR (e.g. RAMSES) and "
                         f"particle-only data are not supported; mi-amr reads grid-based AMR (Enzo, AMReX/"
                         f"BoxLib, FLASH, Athena++, Chombo)")
    refine_by = int(np.max(np.atleast_1d(getattr(ds, "refine_by", 2))))
    if refine_by != 2:
        raise ValueError(f"{ds}: refine_by = {refine_by}; AMR cells need a refinement ratio of 2")
    max_level = int(ds.index.max_level)
    dle = np.asarray(ds.domain_left_edge.to("code_length").d, dtype=np.float64)
    dre = np.asarray(ds.domain_right_edge.to("code_length").d, dtype=np.float64)
    dims0 = np.asarray(ds.domain_dimensions, dtype=np.int64)
    return max_level, dle, dre, dims0, (dre - dle) / (dims0 * (1 << max_level))


def _grid_cells(ds, field, layout):
    """Per grid: ``(pos (m, 3), level (m,), value (m,))`` of its cells not
    covered by a finer grid, in finest-level units from the domain's left
    edge (levels inverted: 0 = finest)."""
    max_level, dle, _, _, dx_finest = layout
    for g in ds.index.grids:
        mask = np.asarray(g.child_mask, dtype=bool)
        if not mask.any():
            continue
        amr_level = max_level - int(g.Level)
        start = np.rint((np.asarray(g.LeftEdge.to("code_length").d) - dle) / dx_finest).astype(np.int64)
        ijk = np.argwhere(mask)
        yield (start + ijk * (1 << amr_level), np.full(len(ijk), amr_level, dtype=np.int32),
               np.asarray(g[field], dtype=np.float64)[mask].astype(np.float32))


def _metadata(ds, field, layout) -> dict:
    max_level, dle, dre, dims0, _ = layout
    try:
        units = str(ds.field_info[field].units) if field in ds.field_info else ""
    except Exception:          # yt's field lookup varies by frontend: units are informative only
        units = ""
    return {"domain_left_edge": dle.tolist(), "domain_right_edge": dre.tolist(),
            "domain_cells": (dims0 * (1 << max_level)).tolist(), "length_unit": "code_length",
            "field": str(field), "units": units, "code": str(getattr(ds, "dataset_type", type(ds).__name__))}


def world_transform(ds):
    """``to_world`` that maps the unit cube onto the dataset's domain (code
    units), for an ``amr`` medium built from `from_yt` data that covers the
    whole domain."""
    import mitsuba as mi
    dle = [float(x) for x in ds.domain_left_edge.to("code_length").d]
    ext = [float(b - a) for a, b in zip(ds.domain_left_edge.to("code_length").d,
                                        ds.domain_right_edge.to("code_length").d)]
    return mi.ScalarTransform4f().translate(dle) @ mi.ScalarTransform4f().scale(ext)
