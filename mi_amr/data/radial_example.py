"""An analytic radial field on two or three AMR levels whose level
boundaries cut through its level sets: the isosurface tests' and the yt
comparison's data (docs/manual/isosurfaces.md).

The field is ``f(x) = |x - centre|`` (unit-cube units; ``"distance"``) or
its square (``"distance_squared"``), sampled at cell centres. Its level
set ``f = R`` is the sphere of radius ``R`` (``sqrt(R)`` for the square),
so the exact hit of a ray is `ray_sphere`. Level 0 is a ``root``^3 grid
over the unit cube; each finer level refines one box of the level above by
2 (`DEFAULT_BOXES`): level 1 the quarter prism ``x, y >= 0.375`` (its two
faces pass 0.125 from the centre), level 2 a box inside it whose faces
pass 0.0625 and 0.1875 from the centre. Every sphere of radius about 0.2
to 0.35 about the default centre is thus cut by the level boundaries, on
faces and edges.

`radial_cells`: the leaf cells (`AMRCells`, level 0 = finest, as mi-amr
numbers them); `write_enzo_radial`: the same grids as an Enzo 2 output yt
reads (its leaf cells are the same cells with the same values).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .cells import AMRCells
from .enzo_example import EnzoGrid, write_enzo_grids

#: Refined boxes ``(lower, upper)`` in the unit cube, one per level above 0
#: (yt's level numbers: box 0 is level 1's).
DEFAULT_BOXES = (((0.375, 0.375, 0.0), (1.0, 1.0, 1.0)),
                 ((0.4375, 0.4375, 0.3125), (0.9375, 0.9375, 0.6875)))
FIELDS = ("distance", "distance_squared")


def radial_grids(levels: int = 2, root: int = 16, centre=(0.5, 0.5, 0.5), refine_box=None,
                 field: str = "distance") -> list[EnzoGrid]:
    """The grids of the hierarchy, coarsest first, one per level: level
    ``l`` (0 = root) holds cell-centred values of the field over its box
    (all of the unit cube for level 0, ``refine_box[l - 1]`` above;
    ``refine_box``: ``levels - 1`` pairs ``(lower, upper)`` in the unit cube,
    default `DEFAULT_BOXES`, each on the cell corners of the level above it
    and inside its box)."""
    if int(levels) != levels or levels < 1:
        raise ValueError(f"levels: a whole number >= 1, got {levels!r}")
    if int(root) != root or root < 2:
        raise ValueError(f"root: a whole number of cells >= 2, got {root!r}")
    if field not in FIELDS:
        raise ValueError(f"field: one of {', '.join(FIELDS)}, got {field!r}")
    levels, root = int(levels), int(root)
    centre = np.asarray(centre, dtype=np.float64)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise ValueError(f"centre: 3 finite numbers, got {centre.tolist()}")
    if refine_box is None:
        if levels - 1 > len(DEFAULT_BOXES):
            raise ValueError(f"levels: at most {len(DEFAULT_BOXES) + 1} without refine_box, got {levels}")
        refine_box = DEFAULT_BOXES[:levels - 1]
    if len(refine_box) != levels - 1:
        raise ValueError(f"refine_box: {levels - 1} boxes (one per level above 0), got {len(refine_box)}")
    grids = [EnzoGrid(0, np.zeros(3, int), radial_values(np.zeros(3, int), np.full(3, root), root, centre, field),
                      None)]
    for level, box in enumerate(refine_box, 1):
        lo, hi = (np.asarray(b, dtype=np.float64) for b in box)
        n_parent = root * 2 ** (level - 1)           # cells of the level above across the domain
        a, b = lo * n_parent, hi * n_parent
        if lo.shape != (3,) or hi.shape != (3,) or np.any(np.abs(a - np.rint(a)) > 1e-9) \
                or np.any(np.abs(b - np.rint(b)) > 1e-9):
            raise ValueError(f"refine_box {level - 1}: corners {lo.tolist()}, {hi.tolist()} must lie on the "
                             f"level-{level - 1} cell corners (multiples of 1/{n_parent})")
        start, end = 2 * np.rint(a).astype(int), 2 * np.rint(b).astype(int)
        parent = grids[-1]
        p_lo, p_hi = 2 * parent.start, 2 * (parent.start + np.asarray(parent.data.shape))
        if np.any(end <= start) or np.any(start < p_lo) or np.any(end > p_hi):
            raise ValueError(f"refine_box {level - 1}: {lo.tolist()}..{hi.tolist()} must be a non-empty box "
                             f"inside level {level - 1}'s grid")
        grids.append(EnzoGrid(level, start, radial_values(start, end - start, root * 2 ** level, centre, field),
                              len(grids) - 1))
    return grids


def radial_values(start, shape, n: int, centre, field: str) -> np.ndarray:
    """The field at the centres of cells ``start .. start + shape`` of a
    level with ``n`` cells across the unit cube, indexed ``[i, j, k]``."""
    axes = [(start[a] + np.arange(shape[a]) + 0.5) / n - centre[a] for a in range(3)]
    r2 = axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2 + axes[2][None, None, :] ** 2
    return r2 if field == "distance_squared" else np.sqrt(r2)


def radial_cells(levels: int = 2, root: int = 16, centre=(0.5, 0.5, 0.5), refine_box=None,
                 field: str = "distance") -> AMRCells:
    """The leaf cells of `radial_grids` as `AMRCells` (positions in
    finest-level cells, level 0 = finest; the domain is the unit cube in
    ``meta``): every grid's cells not covered by the next level's box."""
    grids = radial_grids(levels, root, centre, refine_box, field)
    finest = len(grids) - 1
    pos, lev, val = [], [], []
    for g, child in zip(grids, grids[1:] + [None]):
        ijk = np.stack(np.meshgrid(*[np.arange(s) for s in g.data.shape], indexing="ij"), -1).reshape(-1, 3)
        keep = np.ones(len(ijk), dtype=bool)
        if child is not None:                         # child cell index // 2: the parent cell it refines
            c_lo = child.start // 2 - g.start
            c_hi = (child.start + np.asarray(child.data.shape)) // 2 - g.start
            keep = ~np.all((ijk >= c_lo) & (ijk < c_hi), axis=1)
        width = 1 << (finest - g.level)
        pos.append((g.start + ijk[keep]) * width)
        lev.append(np.full(int(keep.sum()), finest - g.level, dtype=np.int32))
        val.append(g.data.reshape(-1)[keep])
    cells = AMRCells(np.concatenate(pos), np.concatenate(lev), np.concatenate(val),
                     source=f"radial example ({levels} levels, {field})")
    cells.meta = {"domain_left_edge": [0.0, 0.0, 0.0], "domain_right_edge": [1.0, 1.0, 1.0],
                  "domain_cells": [root << finest] * 3, "length_unit": "unit cube", "field": field,
                  "units": "unit cube" if field == "distance" else "unit cube^2", "code": "mi_amr.radial_example"}
    return cells


def level_boundaries(levels: int = 2, refine_box=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The refined boxes ``(lower, upper)`` (unit cube) of a hierarchy with
    ``levels`` levels: the level boundaries are their faces inside the domain."""
    boxes = DEFAULT_BOXES[:levels - 1] if refine_box is None else refine_box
    return [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes]


def boundary_distance(x, levels: int = 2, refine_box=None) -> np.ndarray:
    """Distance (unit cube) of points ``x`` (..., 3) to the nearest level
    boundary: the nearest face of a refined box that is not on the domain's
    boundary (inf with one level)."""
    x = np.asarray(x, dtype=np.float64)
    best = np.full(x.shape[:-1], np.inf)
    for lo, hi in level_boundaries(levels, refine_box):
        for a in range(3):
            others = [b for b in range(3) if b != a]
            for plane in (lo[a], hi[a]):
                if plane <= 0.0 or plane >= 1.0:        # on the domain's face: no level boundary
                    continue
                # distance to the face: the plane's offset and how far outside the face's rectangle
                out = [np.maximum(np.maximum(lo[b] - x[..., b], x[..., b] - hi[b]), 0.0) for b in others]
                d = np.sqrt((x[..., a] - plane) ** 2 + out[0] ** 2 + out[1] ** 2)
                best = np.minimum(best, d)
    return best


def ray_sphere(o, d, centre, radius) -> np.ndarray:
    """The first ``t >= 0`` where the rays ``o + t d`` (arrays (..., 3);
    ``d`` need not be unit) meet the sphere ``|x - centre| = radius``
    (its far side when ``o`` is inside); ``inf`` where they miss it."""
    o, d = np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64)
    oc = o - np.asarray(centre, dtype=np.float64)
    a = np.sum(d * d, axis=-1)
    b = np.sum(oc * d, axis=-1)
    c = np.sum(oc * oc, axis=-1) - float(radius) ** 2
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = (-b - root) / a, (-b + root) / a
    t = np.where(near >= 0.0, near, far)
    return np.where((disc >= 0.0) & (a > 0.0) & (t >= 0.0), t, np.inf)


def write_enzo_radial(path, levels: int = 2, root: int = 16, centre=(0.5, 0.5, 0.5), refine_box=None,
                      field: str = "distance") -> Path:
    """`radial_grids` as an Enzo 2 output in the folder ``path`` (its
    parameter file ``path/NAME`` with ``NAME`` the folder's name), the
    field as ``Density`` (yt's ``("gas", "density")``, with its unit
    g/cm^3 and the values unchanged). Returns the parameter file's path
    (what ``yt.load`` and ``mi_amr.scene`` take)."""
    path = Path(path)
    return write_enzo_grids(path, path.name, radial_grids(levels, root, centre, refine_box, field))
