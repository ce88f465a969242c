"""Cell-centric AMR data: the `AMRCells` container and its validation.

Coordinates are integers in *finest-level cell units*: a cell of ``level`` L
has width ``w = 2**L`` and covers ``[pos, pos + w)`` on each axis. Level 0 is
the finest level (docs/design.md section 1).
"""

from __future__ import annotations

import numpy as np
import mitsuba as mi

#: Largest supported cell level (a level-30 cell is 2**30 finest cells wide).
MAX_LEVEL = 30


class AMRCells(mi.Object):
    """A set of AMR cells: lower corners, levels and scalar values.

    Subclasses ``mitsuba.Object`` so that an instance can be passed as the
    ``data`` entry of a ``mi.load_dict`` scene dictionary.

    Parameters
    ----------
    pos : int array (N, 3)
        Lower cell corners in finest-level units, aligned to ``2**level``.
    level : int array (N,)
        Cell levels, ``0`` = finest.
    value : float array (N,)
        One finite scalar per cell (kept as ``values``, the name
        `BlockVolume` uses; ``value`` is a read-only alias).
    overlap : {"error", "finest"}
        What to do with cells that cover the same space: raise ``ValueError``
        (default) or keep the finer cells and drop the coarser ones.
    source : str
        Name used in error messages (e.g. the file the data came from).
    fields : dict of name -> float array (N,), optional
        Further fields on the same cells (one finite value per cell each),
        e.g. a temperature beside the density in ``value``.
    """

    def __init__(self, pos, level, value, *, overlap: str = "error",
                 source: str = "AMR data", validate: bool = True, fields=None):
        super().__init__()
        pos = np.asarray(pos)
        level = np.asarray(level)
        value = np.asarray(value)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"{source}: pos must have shape (N, 3), got {pos.shape}")
        n = pos.shape[0]
        if level.shape != (n,) or value.shape != (n,):
            raise ValueError(
                f"{source}: inconsistent sizes: pos has {n} cells, level has "
                f"{level.shape}, value has {value.shape}")
        if n == 0:
            raise ValueError(f"{source}: contains no cells")
        if overlap not in ("error", "finest"):
            raise ValueError(f"{source}: overlap must be 'error' or 'finest', got {overlap!r}")
        self.source = source
        self.pos = np.ascontiguousarray(pos, dtype=np.int64)
        self.level = np.ascontiguousarray(level, dtype=np.int32)
        self.values = np.ascontiguousarray(value, dtype=np.float32)
        #: physical metadata (`mi_amr.data.metadata`): domain, field, units, code
        self.meta = {}
        #: further named fields, one value per cell each
        self.fields = {}
        for name, f in (fields or {}).items():
            f = np.ascontiguousarray(f, dtype=np.float32)
            if f.shape != (n,):
                raise ValueError(f"{source}: field {name!r} has shape {f.shape}, the cells {n}")
            if validate and not np.all(np.isfinite(f)):
                raise ValueError(f"{source}: field {name!r} has NaN or Inf values")
            self.fields[str(name)] = f
        if validate:
            self._validate(overlap)

    def __reduce__(self):
        """Pickled as its arrays (for Dask workers), not validated again."""
        return (_cells_from_arrays, (self.pos, self.level, self.values, self.source, self.meta, self.fields))

    # ---- Validation ----------------------------------------------------
    def _validate(self, overlap: str):
        src = self.source
        check_cells(self.pos, self.level, self.values, src)
        w = (np.int64(1) << self.level.astype(np.int64))[:, None]
        lo = self.pos.min(axis=0)
        hi = (self.pos + w).max(axis=0)
        if np.any(hi - lo > 2**31 - 1):
            raise ValueError(f"{src}: bounding box {lo.tolist()}..{hi.tolist()} "
                             "exceeds 2**31 finest cells")
        keep = _non_overlapping(self.pos, self.level)
        if not np.all(keep):
            if overlap == "error":
                i = int(np.argmax(~keep))
                raise ValueError(
                    f"{src}: {int((~keep).sum())} cells overlap finer or duplicate "
                    f"cells (first: cell {i} at {self.pos[i].tolist()}, level "
                    f"{self.level[i]}); pass overlap='finest' to keep the finer ones")
            self.pos, self.level, self.values = self.pos[keep], self.level[keep], self.values[keep]
            self.fields = {name: f[keep] for name, f in self.fields.items()}

    # ---- Properties ----------------------------------------------------
    @property
    def value(self) -> np.ndarray:
        """The per-cell values, read-only alias of `values` (the name used
        inside the package and by `BlockVolume`)."""
        return self.values

    def __len__(self):
        return int(self.values.shape[0])

    def cell_chunks(self, max_cells: int = 1 << 22):
        """Yield ``(pos, level, value)`` slices of at most ``max_cells`` cells
        (the same reading interface as `BlockVolume.cell_chunks`)."""
        for s in range(0, len(self), max_cells):
            yield self.pos[s:s + max_cells], self.level[s:s + max_cells], self.values[s:s + max_cells]

    def weighted_values(self, field: str | None = None):
        """Yield ``(values float64, volume weights)`` of the cells (weights
        in finest-cell volumes, 8^level); ``field``: a further field (None:
        the values). The same reading interface as `BlockVolume.weighted_values`."""
        values = self.values if field is None else self.fields[field]
        yield values.astype(np.float64), np.exp2(3.0 * self.level)

    @property
    def origin(self) -> np.ndarray:
        """Lower data corner aligned to the coarsest level present (the key
        origin of point location; finest units)."""
        lmax = int(self.level.max())
        return (self.bounds[0] >> lmax) << lmax

    @property
    def width(self) -> np.ndarray:
        """Cell widths ``2**level`` in finest-level units, int64 (N,)."""
        return np.int64(1) << self.level.astype(np.int64)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box ``(lo, hi)`` of all cells, int64, finest-level units."""
        return self.pos.min(axis=0), (self.pos + self.width[:, None]).max(axis=0)

    @property
    def levels(self) -> np.ndarray:
        """Sorted distinct levels present."""
        return np.unique(self.level)

    @property
    def value_range(self) -> tuple[float, float]:
        return float(self.values.min()), float(self.values.max())

    @property
    def nbytes(self) -> int:
        """Memory of the raw data in the ExaBricks layout (20 bytes per cell)."""
        return 20 * len(self)

    def __repr__(self):
        lo, hi = self.bounds
        return (f"AMRCells[{len(self)} cells, levels {self.levels.tolist()}, "
                f"bounds {lo.tolist()}..{hi.tolist()}, values "
                f"[{self.value_range[0]:.4g}, {self.value_range[1]:.4g}]]")

    def summary(self) -> str:
        """Human-readable summary: cells per level, bounds, values, memory."""
        lo, hi = self.bounds
        lines = [f"source       : {self.source}",
                 f"cells        : {len(self)}",
                 f"bounding box : {lo.tolist()} .. {hi.tolist()} (finest-cell units)",
                 f"extent       : {(hi - lo).tolist()}",
                 f"value range  : [{self.value_range[0]:.6g}, {self.value_range[1]:.6g}]",
                 f"memory       : {self.nbytes / 2**20:.2f} MiB (cells + scalars)",
                 "cells per level:"]
        for L in self.levels:
            n = int((self.level == L).sum())
            lines.append(f"  level {int(L):2d} (width {2**int(L):>6d}): {n}")
        return "\n".join(lines)


def check_cells(pos, level, value, source: str, start: int = 0):
    """Validate one batch of raw cells (levels in range, finite values, corners
    aligned to the cell width); ``start`` is the index of the batch's first
    cell in the whole data, for the error message."""
    level = np.asarray(level)
    if np.any(level < 0):
        i = int(np.argmax(level < 0))
        raise ValueError(f"{source}: cell {start + i} has negative level {level[i]}")
    if np.any(level > MAX_LEVEL):
        i = int(np.argmax(level > MAX_LEVEL))
        raise ValueError(f"{source}: cell {start + i} has level {level[i]} > {MAX_LEVEL}")
    if not np.all(np.isfinite(value)):
        i = int(np.argmax(~np.isfinite(value)))
        raise ValueError(f"{source}: cell {start + i} has non-finite value {value[i]}")
    w = (np.int64(1) << level.astype(np.int64))[:, None]
    bad = np.any(np.asarray(pos) & (w - 1) != 0, axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(
            f"{source}: cell {start + i} at {np.asarray(pos[i]).tolist()} (level {level[i]}) "
            f"is not aligned to its width {int(w[i, 0])}")


def _non_overlapping(pos: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Mask of cells that overlap no finer (or duplicate earlier) cell.

    A coarse cell overlaps a finer one exactly when the finer cell's ancestor
    at the coarse level has the coarse cell's key; we test this per pair of
    present levels, vectorised with sorted keys.
    """
    keep = np.ones(len(level), dtype=bool)
    levels = np.unique(level)
    origin = pos.min(axis=0)
    rel = pos - origin
    for L in levels:
        sel = np.nonzero(level == L)[0]
        k = cell_keys(rel[sel] >> L)
        _, first = np.unique(k, return_index=True)
        dup = np.ones(len(sel), dtype=bool)
        dup[first] = False            # duplicates at one level: keep the first
        keep[sel[dup]] = False
    for Lf in levels:
        fine = rel[level == Lf]
        for Lc in levels[levels > Lf]:
            sel = np.nonzero(level == Lc)[0]
            ancestors = cell_keys(fine >> Lc)
            keep[sel[np.isin(cell_keys(rel[sel] >> Lc), ancestors)]] = False
    return keep


def cell_keys(q: np.ndarray) -> np.ndarray:
    """One sortable key per row of a non-negative int (M, 3) array.

    int64 with 21 bits per axis; a void view (exact, slower) for larger
    coordinates.
    """
    q = np.ascontiguousarray(q, dtype=np.int64)
    if q.size == 0 or q.max() < (1 << 21):
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]
    return q.view(np.dtype((np.void, 24))).ravel()


def _cells_from_arrays(pos, level, value, source, meta=None, fields=None):
    """`AMRCells` from arrays that were valid when pickled."""
    cells = AMRCells(pos, level, value, source=source, validate=False, fields=fields)
    cells.meta = dict(meta or {})
    return cells
