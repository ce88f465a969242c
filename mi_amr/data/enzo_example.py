"""A small simulation output that mi-amr writes in a real code's format:
an Enzo 2 output (parameter file, ``.hierarchy`` text with the grid tree as
``Pointer:`` lines, packed HDF5 ``.cpu0000`` with one group per grid, values
stored z slowest), read back by yt's own Enzo reader. `write_example`: a
log-normal "cosmic web" density with a gas temperature that rises with it
(the README's and notebooks/quickstart.ipynb's data, no download);
`write_enzo`: any root grid and level-1 grids (the tests' outputs);
`write_enzo_grids`: a grid tree of any depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def cosmic_web(n: int, rng) -> np.ndarray:
    """A log-normal field on ``n``^3 cells with a red power spectrum:
    filaments and knots spanning several decades (g/cm^3-like values from
    about 1e-31)."""
    k = np.fft.fftfreq(n)
    kk = np.sqrt(k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2)
    amp = np.exp(-(kk * 12) ** 2) * np.where(kk > 0, np.maximum(kk, 1e-9) ** -1.6, 0.0)
    g = np.real(np.fft.ifftn(amp * np.exp(2j * np.pi * rng.random((n, n, n)))))
    g = (g - g.mean()) / g.std()
    return 1e-29 * np.exp(2.3 * g)


def temperature(density):
    """A synthetic gas temperature (K): shock-heated where the gas is dense,
    ``1e4 K (rho / 1e-29)^0.7``, from about 1e3 K in voids to 1e6 K in knots."""
    return 1e4 * (np.asarray(density) / 1e-29) ** 0.7


def write_example(out, root: int = 64, grids: int = 24, name: str = "DD0018", seed: int = 18) -> Path:
    """The Enzo-format example in ``out/NAME``: ``root``^3 root cells (a
    multiple of 8) over the unit cube, level-1 grids of ``root/4``^3 cells
    over the ``grids`` boxes of highest peak density, fields Density and
    Temperature. Returns the parameter file's path (what ``yt.load`` and
    ``mi_amr.scene`` take)."""
    if root % 8 or root < 8:
        raise ValueError(f"root: a multiple of 8, at least 8, got {root}")
    rng = np.random.default_rng(seed)
    fine = cosmic_web(2 * root, rng)                 # the field at level-1 resolution
    root_cells = fine.reshape(root, 2, root, 2, root, 2).mean(axis=(1, 3, 5))
    b = root // 8                                    # root cells per box side; a box refines to 2b
    blocks = root_cells.reshape(8, b, 8, b, 8, b).max(axis=(1, 3, 5))
    order = np.argsort(blocks.ravel())[::-1][:grids]
    children = []
    for k in order:
        i, j, l = np.unravel_index(k, blocks.shape)
        start = np.array([i, j, l]) * 2 * b
        children.append((start, fine[start[0]:start[0] + 2 * b, start[1]:start[1] + 2 * b, start[2]:start[2] + 2 * b]))
    return write_enzo(Path(out) / name, name, root_cells, children, extra={"Temperature": temperature})


def write_enzo(directory, name, root, children, field="Density", extra=None):
    """Write an Enzo output ``directory/name`` (parameter file, ``.hierarchy``
    and one packed-HDF5 ``.cpu0000`` file) as Enzo 2 writes it: one root
    grid ``root`` (values indexed ``[i, j, k]``) over the unit cube and
    level-1 grids ``children``: ``(start, data)`` with ``start`` the first
    level-1 cell index. ``extra``: further fields, ``{name: f}`` with ``f``
    mapping a grid's ``field`` values to that field's (e.g. a temperature
    from the density). Returns the parameter file's path."""
    grids = [EnzoGrid(0, np.zeros(3, int), root, None)]
    grids += [EnzoGrid(1, np.asarray(s), d, 0) for s, d in children]
    return write_enzo_grids(directory, name, grids, field=field, extra=extra)


class EnzoGrid:
    """One grid of an Enzo hierarchy: its ``level`` (0 = root), ``start``
    (index of its first cell among all cells of that level over the
    domain), ``data`` (values indexed ``[i, j, k]``) and ``parent`` (index of
    the parent grid in the list handed to `write_enzo_grids`; None for the
    root grid, which must come first)."""

    def __init__(self, level: int, start, data, parent):
        self.level, self.start, self.data, self.parent = int(level), np.asarray(start, int), data, parent


def pointer_order(grids) -> list[int]:
    """The order in which yt's Enzo reader numbers the grids: it reads the
    grid blocks in file order and gives a new grid the next id each time a
    ``NextGridThisLevel`` or ``NextGridNextLevel`` pointer (in that order)
    names one, so grid ids must follow that discovery: a queue that starts
    at the root and appends, per grid, its next sibling then its first child."""
    children = {}
    for i, g in enumerate(grids):
        if g.parent is not None:
            children.setdefault(g.parent, []).append(i)
    sibling = {a: b for kids in children.values() for a, b in zip(kids, kids[1:])}
    order = [0]
    for i in order:                             # grows while iterating: a queue
        order += [j for j in (sibling.get(i), children.get(i, [None])[0]) if j is not None]
    return order


def write_enzo_grids(directory, name, grids, field="Density", extra=None):
    """Write an Enzo 2 output ``directory/name`` of a grid tree of any depth
    (``grids``: `EnzoGrid` s, the root grid first, over the unit cube, each
    level refining by 2): the parameter file, the ``.hierarchy`` with the
    tree as ``Pointer:`` lines and one packed-HDF5 ``.cpu0000`` file. yt
    marks a grid's cells under a child grid as covered (``child_mask``), so
    its leaf cells are the finest cells present everywhere. ``extra`` as in
    `write_enzo`. Returns the parameter file's path."""
    extra = dict(extra or {})
    import h5py                                   # lazy: the mi-amr[yt] extra
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if not grids or grids[0].parent is not None or grids[0].level != 0:
        raise ValueError("write_enzo_grids: the root grid (level 0, no parent) must come first")
    dims = np.asarray(grids[0].data.shape)
    (directory / name).write_text("\n".join([
        "InitialTime = 0", "TopGridRank = 3", f"TopGridDimensions = {dims[0]} {dims[1]} {dims[2]}",
        "DomainLeftEdge = 0 0 0", "DomainRightEdge = 1 1 1", "RefineBy = 2",
        "LeftFaceBoundaryCondition = 3 3 3", "ComovingCoordinates = 0", "Gamma = 1.6667",
        "NumberOfParticles = 0", "VersionNumber = 2.0", "LengthUnits = 1", "DensityUnits = 1",
        "TimeUnits = 1", "HydroMethod = 0", "MultiSpecies = 0", "DualEnergyFormalism = 0", "Mu = 0.6", ""]))
    data_file = f"{name}.cpu0000"
    order = pointer_order(grids)
    gid = {i: k + 1 for k, i in enumerate(order)}          # list index -> Enzo grid id (1-based)
    children = {}
    for i, g in enumerate(grids):
        if g.parent is not None:
            children.setdefault(g.parent, []).append(i)
    sibling = {a: b for kids in children.values() for a, b in zip(kids, kids[1:])}
    lines = []
    with h5py.File(directory / data_file, "w") as h5:
        for i in order:
            g = grids[i]
            n = np.asarray(g.data.shape)
            cell = 1.0 / (dims * 2 ** g.level)
            left, right = g.start * cell, (g.start + n) * cell
            group = h5.create_group(f"Grid{gid[i]:08d}")
            group.create_dataset(field, data=np.asarray(g.data, "<f8").transpose(2, 1, 0))
            for other, f in extra.items():
                group.create_dataset(other, data=np.asarray(f(g.data), "<f8").transpose(2, 1, 0))
            lines += [f"Grid = {gid[i]}", "GridRank = 3", f"GridDimension = {n[0]} {n[1]} {n[2]}",
                      "GridStartIndex = 0 0 0", f"GridEndIndex = {n[0] - 1} {n[1] - 1} {n[2] - 1}",
                      "GridLeftEdge = " + " ".join(f"{x:.17g}" for x in left),
                      "GridRightEdge = " + " ".join(f"{x:.17g}" for x in right),
                      "Time = 0", "SubgridsAreStatic = 0", f"NumberOfBaryonFields = {1 + len(extra)}",
                      "FieldType = " + " ".join(str(t) for t in range(1 + len(extra))),
                      f"BaryonFileName = {data_file}", "NumberOfParticles = 0"]
            this = gid[sibling[i]] if i in sibling else 0
            below = gid[children[i][0]] if i in children else 0
            lines += [f"Pointer: Grid[{gid[i]}]->NextGridThisLevel = {this}",
                      f"Pointer: Grid[{gid[i]}]->NextGridNextLevel = {below}", ""]
    (directory / f"{name}.hierarchy").write_text("\n".join(lines) + "\n")
    return directory / name
