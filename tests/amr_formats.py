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

`write_ramses`: a RAMSES output directory (``info_XXXXX.txt``,
``amr_XXXXX.out00001``, ``hydro_XXXXX.out00001``,
``hydro_file_descriptor.txt``): one CPU, Fortran unformatted sequential
records, the octs of every level from 1 to the deepest (RAMSES keeps the
complete tree above ``levelmin``), cells x fastest within an oct.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_amr.data import enzo_example as _package_enzo


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


write_enzo = _package_enzo.write_enzo        # the package writes it (mi_amr.data.enzo_example)


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


def _record(f, *arrays):
    """One Fortran unformatted sequential record: its byte length (int32)
    before and after the data."""
    data = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)
    n = np.int32(len(data)).tobytes()
    f.write(n + data + n)


RAMSES_FIELDS = ("density", "velocity_x", "velocity_y", "velocity_z", "pressure")


def write_ramses(directory, levelmin, refined, value, iout=1, fields=RAMSES_FIELDS):
    """Write ``directory/output_{iout:05d}`` as RAMSES 3D hydro writes it (one
    CPU, periodic box of length 1, code units = cgs). ``levelmin``: the
    uniform level, 2^levelmin cells per side; ``refined``: per level from
    ``levelmin`` on, the integer coordinates ``(m, 3)`` of that level's
    cells that have children (an oct at the next level; each inside a
    refined cell of the level above); ``value(level, ijk (m, 3)) -> (m,
    len(fields))``: the variables of leaf cells of RAMSES level ``level``
    (width 2^-level). Cells that have children hold -1. Returns the path of
    the info file."""
    out = Path(directory) / f"output_{iout:05d}"
    out.mkdir(parents=True, exist_ok=True)
    child = np.array([(i & 1, i >> 1 & 1, i >> 2 & 1) for i in range(8)], np.int64)   # RAMSES: x fastest
    levels = []                  # per RAMSES level L = 1..: (oct coords k (n, 3), cells' values (8, nvar, n))
    octs = np.zeros((1, 3), np.int64)
    L = 1
    while len(octs):
        cells = 2 * octs[:, None, :] + child[None]                       # (n, 8, 3) at level L
        flat = cells.reshape(-1, 3)
        if L < levelmin:
            has_children = np.ones(len(flat), bool)
        else:
            r = np.asarray(refined[L - levelmin], np.int64).reshape(-1, 3) if L - levelmin < len(refined) else \
                np.zeros((0, 3), np.int64)
            key = lambda c: (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
            has_children = np.isin(key(flat), key(r))
            assert has_children.sum() == len(r), f"level {L}: refined cells outside the octs of that level"
        values = np.full((len(flat), len(fields)), -1.0)
        leaf = ~has_children
        if leaf.any():
            values[leaf] = np.asarray(value(L, flat[leaf]), np.float64).reshape(-1, len(fields))
        levels.append((octs, values.reshape(len(octs), 8, len(fields)).transpose(1, 2, 0)))
        octs = flat[has_children]
        L += 1
    nlevelmax, ncpu = len(levels), 1
    numbl = np.array([len(k) for k, _ in levels], np.int32)
    ngrid = int(numbl.sum())
    with open(out / f"amr_{iout:05d}.out00001", "wb") as f:
        i4, f8 = np.int32, np.float64
        for rec in ([ncpu], [3], [1, 1, 1], [nlevelmax], [ngrid + 100], [0], [ngrid]):
            _record(f, np.array(rec, i4))
        _record(f, np.array([1.0], f8))                                   # boxlen
        _record(f, np.array([1, iout, 1], i4))                           # noutput, iout, ifout
        for rec in ([0.0], [1.0], [0.0], np.zeros(nlevelmax), np.zeros(nlevelmax)):   # tout aout t dtold dtnew
            _record(f, np.array(rec, f8))
        _record(f, np.array([0, 0], i4))                                 # nstep
        for rec in (np.zeros(3), [0, 0, 1, 1, 0, 0, 0], np.zeros(5), [0.0]):          # stat cosm timing mass_sph
            _record(f, np.array(rec, f8))
        first = np.concatenate([[1], 1 + np.cumsum(numbl)[:-1]]).astype(i4)
        _record(f, first)                                                # headl (ncpu x nlevelmax)
        _record(f, (first + numbl - 1).astype(i4))                       # taill
        _record(f, numbl)                                                # numbl
        _record(f, np.zeros(10 * nlevelmax, i4))                         # numbtot
        _record(f, np.zeros(5, i4))                                      # free_mem
        _record(f, np.frombuffer(b"hilbert".ljust(128), np.uint8))       # ordering
        _record(f, np.array([0.0, 8.0 ** nlevelmax], f8))                # bound_key
        for _ in range(3):                                               # coarse son, flag1, cpu_map
            _record(f, np.array([1], i4))
        for L, (k, _) in enumerate(levels, 1):
            n = len(k)
            ind = np.arange(first[L - 1], first[L - 1] + n, dtype=i4)
            _record(f, ind)                                              # grid index
            _record(f, np.where(ind < ind[-1], ind + 1, 0).astype(i4))    # next
            _record(f, np.where(ind > ind[0], ind - 1, 0).astype(i4))     # prev
            for a in range(3):                                           # oct centres, box units
                _record(f, ((2 * k[:, a] + 1) * 0.5 ** L).astype(f8))
            for _ in range(1 + 6 + 8 + 8 + 8):                           # father, nbor, son, cpu_map, flag1
                _record(f, np.zeros(n, i4))
    with open(out / f"hydro_{iout:05d}.out00001", "wb") as f:
        for rec in ([ncpu], [len(fields)], [3], [nlevelmax], [0]):
            _record(f, np.array(rec, np.int32))
        _record(f, np.array([5.0 / 3.0]))                                # gamma
        for L, (k, v) in enumerate(levels, 1):
            _record(f, np.array([L], np.int32))
            _record(f, np.array([len(k)], np.int32))
            for ind in range(8):
                for var in range(len(fields)):
                    _record(f, v[ind, var].astype(np.float64))
    (out / "hydro_file_descriptor.txt").write_text(
        "# version:  1\n# ivar, variable_name, variable_type\n"
        + "".join(f"{i:3d}, {name}, d\n" for i, name in enumerate(fields, 1)))
    info = out / f"info_{iout:05d}.txt"
    head = [("ncpu", ncpu), ("ndim", 3), ("levelmin", levelmin), ("levelmax", nlevelmax), ("ngridmax", ngrid + 100),
            ("nstep_coarse", 0)]
    units = [("boxlen", 1.0), ("time", 0.0), ("aexp", 1.0), ("H0", 1.0), ("omega_m", 1.0), ("omega_l", 0.0),
             ("omega_k", 0.0), ("omega_b", 0.0), ("unit_l", 1.0), ("unit_d", 1.0), ("unit_t", 1.0)]
    info.write_text("".join(f"{k:<12}={v:11d}\n" for k, v in head) + "\n"
                    + "".join(f"{k:<12}={v:23.15E}\n" for k, v in units) + "\n"
                    + "ordering type=hilbert\n   DOMAIN   ind_min                 ind_max\n"
                    + f"       1   0.000000000000000E+00   {8.0 ** nlevelmax:.15E}\n")
    return info
