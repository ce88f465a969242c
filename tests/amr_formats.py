"""Small simulation outputs written by the tests themselves, in the codes'
own on-disk formats, so that the readers yt uses for real data are exercised
without downloading anything.

`write_amrex_plotfile`: an AMReX/BoxLib plotfile directory (``Header``,
``Level_L/Cell_H`` and ``Level_L/Cell_D_00000``), as AMReX's
``WriteMultiLevelPlotfile`` lays it out (format "HyperCLaw-V1.1", one FAB file
per level, little-endian doubles, x fastest).

`write_enzo`: an Enzo 2 output (parameter file, ``.hierarchy`` text with the
grid tree as ``Pointer:`` lines, packed HDF5 ``.cpu0000`` with one group per
grid, values stored z slowest).

`write_athena_pp`: an Athena++ ``.athdf`` file (leaf mesh blocks of one size,
face coordinates per block, ``prim`` stored [variable, block, k, j, i]).

`octree`: an octree as ``yt.load_octree`` takes it (a depth-first refinement
mask) with its leaf cells in the same order, built level by level.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_amrex_plotfile(path, levels, prob_lo, prob_hi, field="density"):
    """Write a plotfile. ``levels``: per level, a list of ``(lo, data)``
    boxes, ``lo`` the box's first cell index (i, j, k) at that level and
    ``data`` its values indexed ``[i, j, k]``; level 0 must cover the domain
    and each finer level refines by 2."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    prob_lo, prob_hi = np.asarray(prob_lo, float), np.asarray(prob_hi, float)
    hi0 = np.max([np.asarray(lo) + np.asarray(d.shape) for lo, d in levels[0]], axis=0) - 1
    finest = len(levels) - 1
    dims = [(hi0 + 1) * 2 ** L for L in range(finest + 1)]
    dx = [(prob_hi - prob_lo) / d for d in dims]

    def box(lo, hi):
        return f"(({lo[0]},{lo[1]},{lo[2]}) ({hi[0]},{hi[1]},{hi[2]}) (0,0,0))"
    lines = ["HyperCLaw-V1.1", "1", field, "3", "0.0", str(finest),
             " ".join(f"{x:.17g}" for x in prob_lo), " ".join(f"{x:.17g}" for x in prob_hi),
             " ".join("2" for _ in range(finest)),
             " ".join(box((0, 0, 0), d - 1) for d in dims),
             " ".join("0" for _ in range(finest + 1))]
    lines += [" ".join(f"{x:.17g}" for x in d) for d in dx]
    lines += ["0", "0"]
    for L, boxes in enumerate(levels):
        lines += [f"{L} {len(boxes)} 0.0", "0"]
        for lo, data in boxes:
            lo = np.asarray(lo)
            for a in range(3):
                lines.append(f"{prob_lo[a] + lo[a] * dx[L][a]:.17g} "
                             f"{prob_lo[a] + (lo[a] + data.shape[a]) * dx[L][a]:.17g}")
        lines.append(f"Level_{L}/Cell")
        _write_level(path / f"Level_{L}", boxes, box)
    (path / "Header").write_text("\n".join(lines) + "\n")
    return path


def _write_level(level_dir, boxes, box):
    level_dir.mkdir(exist_ok=True)
    offsets = []
    with open(level_dir / "Cell_D_00000", "wb") as f:
        for lo, data in boxes:
            lo = np.asarray(lo)
            hi = lo + np.asarray(data.shape) - 1
            offsets.append(f.tell())
            f.write(f"FAB ((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1))){box(lo, hi)} 1\n"
                    .encode("ascii"))
            f.write(np.asarray(data, "<f8").ravel(order="F").tobytes())
    head = ["1", "0", "1", "0", f"({len(boxes)} 0"]
    head += [box(np.asarray(lo), np.asarray(lo) + np.asarray(d.shape) - 1) for lo, d in boxes]
    head += [")", str(len(boxes))]
    head += [f"FabOnDisk: Cell_D_00000 {o}" for o in offsets]
    (level_dir / "Cell_H").write_text("\n".join(head) + "\n")


def write_enzo(directory, name, root, children, field="Density", extra=None):
    """Write an Enzo output ``directory/name`` (parameter file, ``.hierarchy``
    and one packed-HDF5 ``.cpu0000`` file) as Enzo 2 writes it: one root
    grid ``root`` (values indexed ``[i, j, k]``) over the unit cube and
    level-1 grids ``children``: ``(start, data)`` with ``start`` the first
    level-1 cell index. ``extra``: further fields, ``{name: f}`` with ``f``
    mapping a grid's ``field`` values to that field's (e.g. a temperature
    from the density). Returns the parameter file's path."""
    extra = dict(extra or {})
    import h5py
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    dims = np.asarray(root.shape)
    (directory / name).write_text("\n".join([
        "InitialTime = 0", "TopGridRank = 3", f"TopGridDimensions = {dims[0]} {dims[1]} {dims[2]}",
        "DomainLeftEdge = 0 0 0", "DomainRightEdge = 1 1 1", "RefineBy = 2",
        "LeftFaceBoundaryCondition = 3 3 3", "ComovingCoordinates = 0", "Gamma = 1.6667",
        "NumberOfParticles = 0", "VersionNumber = 2.0", "LengthUnits = 1", "DensityUnits = 1",
        "TimeUnits = 1", "HydroMethod = 0", "MultiSpecies = 0", "DualEnergyFormalism = 0", "Mu = 0.6", ""]))
    data_file = f"{name}.cpu0000"
    grids = [(0, np.zeros(3, int), root)] + [(1, np.asarray(s), d) for s, d in children]
    lines = []
    with h5py.File(directory / data_file, "w") as h5:
        for gid, (level, start, data) in enumerate(grids, 1):
            n = np.asarray(data.shape)
            cell = 1.0 / (dims * 2 ** level)
            left, right = start * cell, (start + n) * cell
            group = h5.create_group(f"Grid{gid:08d}")
            group.create_dataset(field, data=np.asarray(data, "<f8").transpose(2, 1, 0))
            for other, f in extra.items():
                group.create_dataset(other, data=np.asarray(f(data), "<f8").transpose(2, 1, 0))
            lines += [f"Grid = {gid}", "GridRank = 3", f"GridDimension = {n[0]} {n[1]} {n[2]}",
                      "GridStartIndex = 0 0 0", f"GridEndIndex = {n[0] - 1} {n[1] - 1} {n[2] - 1}",
                      "GridLeftEdge = " + " ".join(f"{x:.17g}" for x in left),
                      "GridRightEdge = " + " ".join(f"{x:.17g}" for x in right),
                      "Time = 0", "SubgridsAreStatic = 0", f"NumberOfBaryonFields = {1 + len(extra)}",
                      "FieldType = " + " ".join(str(t) for t in range(1 + len(extra))),
                      f"BaryonFileName = {data_file}", "NumberOfParticles = 0"]
            # root: first child below; children: the next sibling on level 1
            this = gid + 1 if level == 1 and gid < len(grids) else 0
            below = 2 if level == 0 and len(grids) > 1 else 0
            lines += [f"Pointer: Grid[{gid}]->NextGridThisLevel = {this}",
                      f"Pointer: Grid[{gid}]->NextGridNextLevel = {below}", ""]
    (directory / f"{name}.hierarchy").write_text("\n".join(lines) + "\n")
    return directory / name


def write_athena_pp(path, levels, root_cells, box=(1.0, 1.0, 1.0), field="rho"):
    """Write an Athena++ ``.athdf`` file: mesh blocks of one size (only the
    leaves, as Athena++ writes them), face coordinates per block, and the
    primitive variables stored ``[variable, block, k, j, i]``. ``levels``:
    per level, ``(first cell index at that level, values [i, j, k])`` blocks."""
    import h5py
    blocks = [(L, np.asarray(lo), np.asarray(d)) for L, boxes in enumerate(levels) for lo, d in boxes]
    size = blocks[0][2].shape
    assert all(d.shape == size for _, _, d in blocks), "Athena++ mesh blocks share one size"
    root_cells, box = np.asarray(root_cells), np.asarray(box, float)
    with h5py.File(path, "w") as h5:
        a = h5.attrs
        a["NumMeshBlocks"] = np.int32(len(blocks))
        a["MeshBlockSize"] = np.asarray(size, np.int32)
        a["RootGridSize"] = root_cells.astype(np.int32)
        for k, name in enumerate(("RootGridX1", "RootGridX2", "RootGridX3")):
            a[name] = np.array([0.0, box[k], 1.0])
        a["MaxLevel"] = np.int32(len(levels) - 1)
        a["Coordinates"] = np.bytes_("cartesian")
        a["DatasetNames"] = np.array([b"prim"])
        a["NumVariables"] = np.array([1], np.int32)
        a["VariableNames"] = np.array([field.encode()])
        a["Time"] = 0.0
        a["NumCycles"] = np.int32(0)
        faces = []
        for k in range(3):
            f = np.empty((len(blocks), size[k] + 1))
            for b, (L, lo, _) in enumerate(blocks):
                f[b] = (lo[k] + np.arange(size[k] + 1)) * box[k] / (root_cells[k] * 2 ** L)
            faces.append(f)
        h5["x1f"], h5["x2f"], h5["x3f"] = faces
        h5["Levels"] = np.array([L for L, _, _ in blocks], np.int32)
        h5["LogicalLocations"] = np.array([lo // np.asarray(size) for _, lo, _ in blocks], np.int64)
        h5["prim"] = np.stack([d.transpose(2, 1, 0) for _, _, d in blocks])[None].astype("<f4")
    return Path(path)


def octree(max_depth, refine):
    """An octree over the domain (one root oct, ``num_zones=1``), refined
    level by level: ``refine(coords (m, 3), depth)`` says which nodes of a
    depth (integer coordinates at that depth) have children; nothing is
    refined below ``max_depth``. Returns ``(mask uint8, pos (n, 3), level
    (n,))``: the depth-first mask ``yt.load_octree`` reads (8 for a refined
    node, 0 for a leaf; children in yt's order, x slowest) and the leaves in
    that order, in mi-amr's units (finest-level cells, level 0 = finest)."""
    coords, depths, inner = [], [], []
    c = np.zeros((1, 3), np.int64)
    for d in range(max_depth + 1):
        r = np.asarray(refine(c, d), bool) if d < max_depth else np.zeros(len(c), bool)
        coords.append(c)
        depths.append(np.full(len(c), d))
        inner.append(r)
        child = np.array([(i >> 2 & 1, i >> 1 & 1, i & 1) for i in range(8)], np.int64)
        c = ((2 * c[r])[:, None, :] + child[None]).reshape(-1, 3)
        if not len(c):
            break
    coords, depths, inner = np.concatenate(coords), np.concatenate(depths), np.concatenate(inner)
    deepest = int(depths[~inner].max())
    corner = coords << (deepest - depths)[:, None]
    key = np.zeros(len(corner), np.int64)
    for b in range(deepest):                    # Morton order, x the slowest of each bit triple
        for a in range(3):
            key |= ((corner[:, a] >> b) & 1) << (3 * b + 2 - a)
    order = np.lexsort((depths, key))           # depth first: a node before its children
    inner, corner, depths = inner[order], corner[order], depths[order]
    leaf = ~inner
    return np.where(inner, 8, 0).astype(np.uint8), corner[leaf], (deepest - depths[leaf]).astype(np.int32)
