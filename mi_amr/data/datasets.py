"""Synthetic AMR data sets, deterministic by seed.

Each data set is an analytic scalar field on the unit cube, sampled by
top-down refinement: start from a coarse grid at level ``levels - 1``,
refine (split into 8) the cells where the field varies most, down to level
0. The refinement fraction per level is set so that the result has about
``cells`` cells; every level from 0 to ``levels - 1`` is present.

* ``cloud``: turbulent density (a sum of random Fourier modes) thresholded
  inside a soft ball, with large empty space around it.
* ``shell``: a thin, dense, finely refined shock shell around a sparse,
  faintly turbulent interior, like an impact.
* ``stadium``: a small, finely refined object (a torus) inside a large,
  coarse, almost empty domain: the "teapot in a stadium" case.

These three refine cell by cell (octree-like: about 8 cells per same-level
box). Simulation codes write *block-structured* data instead, and so does

* ``blocks``: the ``cloud`` field on fixed-size blocks of ``nxb^3`` cells
  (8^3-32^3, as FLASH/PARAMESH writes them): the same top-down refinement,
  applied to whole blocks. `block_leaves` gives the blocks, `block_cells`
  their cells chunk by chunk, so that 10^8-10^9-cell files are written
  without holding per-cell arrays of the whole data (`write_block_dataset`).
  With several sizes (``nxb=(8, 16, 32)``) each leaf is cut into blocks of
  one of them: *mixed* blocks, as codes with per-patch sizes write them.
* ``cosmo``: a cosmology-like density on Enzo-like 8^3 blocks: a log-normal
  cosmic web (filaments and voids) with compact halos on its densest
  parts, values (g/cm^3-like, from about 1e-32) spanning several decades,
  blocks refined top-down where the density is high. Its domain is a
  power of two of finest cells per side, so dense resamples at 2^k voxels
  per side align with the cells (`mi_amr.bench.resample`).

One data set has a single level (`uniform_dataset`; ``levels`` does not
apply):

* ``sparse``: the ``cloud`` field on a uniform n^3 grid, as a uniform
  simulation or a resampled volume gives it (e.g. 128^3): most cells hold
  0, empty space around the cloud.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..parallel import ordered_map
from ..core.block_keys import block_offsets
from .cells import AMRCells
from .io import save_cells

NAMES = ("cloud", "shell", "stadium", "blocks", "cosmo")
#: Block-structured data sets: name -> (field, default cells per block side or None).
BLOCK_DATASETS = {"blocks": ("cloud", None), "cosmo": ("cosmo", 8)}
#: Single-level data sets (``levels`` does not apply to them).
UNIFORM_NAMES = ("sparse",)
#: Cells per block side of the ``blocks`` data set, by default.
DEFAULT_NXB = 16


class _Noise:
    """Band-limited turbulence: a sum of random Fourier modes, amplitude ~ 1/k."""

    def __init__(self, rng, modes=32, kmin=2.0, kmax=16.0):
        k = np.exp(rng.uniform(np.log(kmin), np.log(kmax), modes))
        d = rng.normal(size=(modes, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        self.freq = 2 * np.pi * d * k[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, modes)
        self.amp = 1.0 / k
        self.amp /= np.sqrt(0.5 * (self.amp ** 2).sum())

    def __call__(self, x):
        out = np.zeros(len(x))
        for f, p, a in zip(self.freq, self.phase, self.amp):
            out += a * np.sin(x @ f + p)
        return out


def _field(name: str, seed: int):
    """The field ``f(x)`` of a data set (x in the unit cube, (M, 3)) and a
    feature test ``g(centre, half_diagonal)``: does a cell touch the
    feature that must be refined first (the shell, the small object)?"""
    rng = np.random.default_rng(seed)
    noise = _Noise(rng)
    feature = None
    if name == "cloud":
        def f(x):
            r = np.linalg.norm(x - 0.5, axis=1)
            ball = np.clip(1.0 - (r / 0.42) ** 2, 0.0, 1.0)
            return np.clip(0.6 * noise(x) + 1.4 * ball - 0.75, 0.0, None)
    elif name == "shell":
        center = np.array([0.5, 0.5, 0.5]) + rng.uniform(-0.05, 0.05, 3)

        def f(x):
            r = np.linalg.norm(x - center, axis=1)
            rr = 0.33 + 0.015 * noise(x)
            shell = np.exp(-(((r - rr) / 0.012) ** 2))
            inner = np.where(r < rr, 0.06 * (1 + 0.5 * noise(2 * x)), 0.0)
            return shell + np.clip(inner, 0.0, None)

        def feature(c, h):
            return np.abs(np.linalg.norm(c - center, axis=1) - 0.33) < h + 0.03
    elif name == "stadium":
        center = np.array([0.55, 0.45, 0.5]) + rng.uniform(-0.03, 0.03, 3)

        def f(x):
            p = x - center
            q = np.sqrt(p[:, 0] ** 2 + p[:, 2] ** 2) - 0.03      # torus, R=0.03
            d = np.sqrt(q ** 2 + p[:, 1] ** 2) - 0.012            # tube radius 0.012
            torus = np.clip(1.0 - d / 0.006, 0.0, 1.0)
            fog = 0.02 * np.clip(noise(x * 0.5) + 0.5, 0, None)
            return torus + fog

        def feature(c, h):
            return np.linalg.norm(c - center, axis=1) < h + 0.05
    elif name == "cosmo":
        web = _Noise(rng, modes=48, kmin=1.5, kmax=40.0)
        # halos on the web's densest parts: the densest of random candidates
        cand = rng.random((4096, 3))
        centre = cand[np.argsort(-web(cand))[:HALOS]]
        radius = np.exp(rng.uniform(np.log(0.002), np.log(0.015), HALOS))
        peak = 30.0 * (radius / 0.002) ** 1.2       # larger halos are denser on the web's scale

        def f(x):
            out = np.ones(len(x))
            for c, r, a in zip(centre, radius, peak):
                out += a / (1.0 + ((x - c) ** 2).sum(axis=1) / r ** 2) ** 1.5
            return COSMO_DENSITY * np.exp(1.8 * web(x)) * out
    else:
        raise ValueError(f"unknown data set {name!r} (choose from {', '.join(NAMES)})")
    return f, feature


#: Halos of the ``cosmo`` field, and its mean-density scale (g/cm^3-like).
HALOS = 48
COSMO_DENSITY = 1e-29


def _variation(f, lo, w, base_vals):
    """How much the field varies over each cell: spread of f at the centre
    and the 8 corners, plus the cell's peak value (so bright features refine)."""
    vals = [base_vals]
    for c in range(8):
        off = np.array([(c >> a) & 1 for a in range(3)], dtype=np.float64)
        vals.append(f(lo + off * w[:, None] * 0.999))
    v = np.stack(vals)
    return v.max(axis=0) - v.min(axis=0)


def make_dataset(name: str, cells: int = 20000, levels: int = 4, seed: int = 0) -> AMRCells:
    """Synthetic AMR data set ``name`` with about ``cells`` cells over
    ``levels`` levels (>= 2), deterministic for a given seed.

    Positions are in finest-level units; the domain is a cube of
    ``base * 2**(levels - 1)`` finest cells per side.
    """
    if name in UNIFORM_NAMES:
        return uniform_dataset(name, cells, seed)
    if name not in NAMES:
        raise ValueError(f"unknown data set {name!r} (choose from {', '.join(NAMES + UNIFORM_NAMES)})")
    if name in BLOCK_DATASETS:
        field, nxb = BLOCK_DATASETS[name]
        leaves = block_leaves(cells, levels, seed, nxb, field=field)
        parts = list(block_cells(*leaves, field=field))
        return AMRCells(*(np.concatenate([p[i] for p in parts]) for i in range(3)),
                        source=f"dataset {name}(cells={cells}, levels={levels}, seed={seed})", validate=False)
    return _refined(name, cells, levels, seed)


def _refined(name: str, cells: int, levels: int, seed: int) -> AMRCells:
    """Top-down cell-by-cell refinement of field ``name`` (see `make_dataset`);
    ``cosmo`` starts from a power-of-two coarse grid."""
    if levels < 2 or levels > 12:
        raise ValueError(f"levels must be in 2..12, got {levels}")
    if cells < 64:
        raise ValueError(f"cells must be >= 64, got {cells}")
    f, feature = _field(name, seed)
    # Nominal growth with a share p = 25% refined per level: c_{L} = (1 - p) + 8 p c_{L-1}.
    share = 0.25
    growth = _growth(share, levels - 1)
    base = max(2, int(round((cells / growth) ** (1 / 3))))
    if name == "cosmo":             # a power-of-two domain, the refined share to match
        base = 1 << max(1, int(np.floor(np.log2(base))))
        lo_p, hi_p = 0.0, 1.0
        for _ in range(40):
            share = 0.5 * (lo_p + hi_p)
            lo_p, hi_p = (share, hi_p) if base ** 3 * _growth(share, levels - 1) < cells else (lo_p, share)
    top = levels - 1
    n_fine = base << top                              # finest cells per axis
    g = np.stack(np.meshgrid(*[np.arange(base)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pos = (g << top).astype(np.int64)
    out_pos, out_lvl, out_val = [], [], []
    budget = float(cells)
    for L in range(top, -1, -1):
        w = np.full(len(pos), float(1 << L))
        x = (pos + 0.5 * w[:, None]) / n_fine
        val = f(x)
        if L == 0:
            keep = np.ones(len(pos), dtype=bool)
        else:
            crit = _variation(f, pos / n_fine, w / n_fine, val)
            if name == "cosmo":                       # in units of the mean density
                crit = crit / COSMO_DENSITY
            if feature is not None:
                crit = crit + 10.0 * feature(x, 0.87 * w / n_fine)
            # Refine as many cells as the remaining budget allows at this level.
            finer_growth = _growth(share, L - 1)
            emitted = sum(len(p) for p in out_pos)
            n_ref = int(np.clip((budget - emitted - len(pos)) / (8 * finer_growth - 1), 1, len(pos)))
            n_ref = min(n_ref, int((crit > 1e-6).sum()) or 1)
            order = np.argsort(-crit, kind="stable")
            keep = np.ones(len(pos), dtype=bool)
            keep[order[:n_ref]] = False
        out_pos.append(pos[keep])
        out_lvl.append(np.full(int(keep.sum()), L, dtype=np.int32))
        out_val.append(val[keep])
        if L > 0:
            parents = pos[~keep]
            h = 1 << (L - 1)
            offs = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=np.int64) * h
            pos = (parents[:, None, :] + offs[None]).reshape(-1, 3)
    return AMRCells(np.concatenate(out_pos), np.concatenate(out_lvl),
                    np.concatenate(out_val).astype(np.float32),
                    source=f"dataset {name}(cells={cells}, levels={levels}, seed={seed})",
                    validate=False)


def _growth(share: float, steps: int) -> float:
    """Cells per coarse cell after ``steps`` levels refining ``share`` of the cells."""
    growth = 1.0
    for _ in range(steps):
        growth = (1.0 - share) + 8.0 * share * growth
    return growth


def uniform_dataset(name: str, cells: int = 128 ** 3, seed: int = 0, chunk: int = 1 << 20) -> AMRCells:
    """Single-level data set ``name`` (``sparse``: the ``cloud`` field) on
    a uniform n^3 grid, n the nearest integer to ``cells ** (1/3)``: one
    level-0 cell per grid point, valued at its centre (finest units)."""
    if name not in UNIFORM_NAMES:
        raise ValueError(f"unknown single-level data set {name!r} (choose from {', '.join(UNIFORM_NAMES)})")
    n = int(round(cells ** (1 / 3)))
    if n < 4:
        raise ValueError(f"cells must be >= 64, got {cells}")
    f, _ = _field("cloud", seed)
    i = np.arange(n ** 3, dtype=np.int64)
    pos = np.stack([i % n, (i // n) % n, i // (n * n)], axis=1)
    value = np.empty(n ** 3, dtype=np.float32)
    for start in range(0, n ** 3, chunk):          # the field's modes over chunks of points
        value[start:start + chunk] = f((pos[start:start + chunk] + 0.5) / n)
    return AMRCells(pos, np.zeros(n ** 3, dtype=np.int32), value,
                    source=f"dataset {name}(cells={n}^3, seed={seed})", validate=False)


def ensure_dataset(path, name: str, cells: int = 20000, levels: int = 4, seed: int = 0) -> Path:
    """Write data set ``name`` to ``path`` (``.cells`` or ``.npz``) unless it
    already exists; returns the path. Used to generate larger data on first use."""
    path = Path(path)
    if not path.exists() and name in BLOCK_DATASETS and path.suffix == ".cells":
        return write_block_dataset(path, cells, levels, seed, name=name)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_cells(make_dataset(name, cells, levels, seed), path)
    return path


def block_leaves(cells: int, levels: int = 4, seed: int = 0, nxb=None, field: str = "cloud"):
    """Leaf blocks of the ``blocks`` data set: about ``cells / nxb^3`` blocks
    of ``nxb^3`` cells each, refined top-down like the ``cloud`` data set
    (one block there stands for one cell here). ``nxb`` defaults to
    `DEFAULT_NXB`, less for data sets under 64 such blocks. A sequence of
    sizes (e.g. ``(8, 16, 32)``) gives *mixed* blocks: each leaf of the
    largest size is cut into same-level blocks of one of the sizes, chosen
    at random by seed. Returns ``(lo (K, 3) int64 finest units, level (K,),
    nxb (an int, or (K,) sizes when mixed), n_fine, seed)``: the argument
    list of `block_cells`. ``field``: the field refined (``cloud``, ``cosmo``)."""
    sizes = None
    if nxb is not None and np.ndim(nxb) > 0:
        sizes = np.array(sorted(set(int(s) for s in nxb)), dtype=np.int64)
        if len(sizes) == 1:
            nxb, sizes = int(sizes[0]), None
        else:
            nxb = int(sizes[-1])
    if nxb is None:
        nxb = int(np.clip(2 ** int(np.floor(np.log2(max(cells / 64, 8)) / 3)), 2, DEFAULT_NXB))
    for s in ([nxb] if sizes is None else sizes):
        if s < 2 or s & (s - 1):
            raise ValueError(f"nxb must be a power of two >= 2, got {int(s)}")
    units = _refined(field, max(64, int(round(cells / nxb ** 3))), levels, seed)
    lo_units, hi_units = units.bounds
    n_fine = int((hi_units - lo_units).max()) * nxb
    lo, level = units.pos * nxb, units.level
    if sizes is None:
        return lo, level, nxb, n_fine, seed
    choice = sizes[np.random.default_rng(seed + 1).integers(len(sizes), size=len(level))]
    parts = []                                   # (unit, sub-block, lo, level, size) per size
    for s in sizes:
        u = np.nonzero(choice == s)[0]
        cut = nxb // int(s)
        sub_lo, sub_level = _sub_blocks(lo[u], level[u], cut, int(s))
        parts.append((np.repeat(u, cut ** 3), np.tile(np.arange(cut ** 3), len(u)), sub_lo,
                      sub_level, np.full(len(sub_level), s)))
    unit, sub, sub_lo, sub_level, size = (np.concatenate([p[i] for p in parts]) for i in range(5))
    order = np.lexsort((sub, unit))              # the blocks of each leaf together, leaves in order
    return sub_lo[order], sub_level[order], size[order], n_fine, seed


def _sub_blocks(lo, level, cut: int, s: int):
    """Each block ``lo`` (k, 3) finest units, ``level`` (k,) cut into
    ``cut^3`` same-level blocks of ``s`` cells per side: ``(lo (k cut^3, 3),
    level (k cut^3,))``, the sub-blocks of each block together."""
    offs = block_offsets(cut) * s                                    # sub-block corners, level units
    w = (np.int64(1) << np.asarray(level).astype(np.int64))[:, None, None]
    return (lo[:, None, :] + offs[None] * w).reshape(-1, 3), np.repeat(level, len(offs))


def _block_chunk(lo, level, size, n_fine: int, f, order: str = "F"):
    """Cells of the blocks ``lo``/``level`` of sizes ``size`` (K,), grouped
    by size, each block's cells together: ``(pos, level, value)``; inside a
    block x fastest (``order`` "F", as Fortran codes write) or z fastest
    ("C", numpy's order of an array indexed [x, y, z])."""
    out = []
    for s in np.unique(size):
        sel = np.nonzero(size == s)[0]
        local = block_offsets(int(s))
        if order == "C":
            local = np.stack(np.unravel_index(np.arange(int(s) ** 3), (int(s),) * 3, order="C"), axis=1)
        L = level[sel].astype(np.int64)
        w = (np.int64(1) << L)[:, None, None]
        pos = (lo[sel][:, None, :] + local[None] * w).reshape(-1, 3)
        lev = np.repeat(L, len(local)).astype(np.int32)
        x = (pos + 0.5 * np.repeat(w[:, 0, 0], len(local))[:, None]) / n_fine
        out.append((pos, lev, f(x).astype(np.float32)))
    if len(out) == 1:
        return out[0]
    return tuple(np.concatenate([o[i] for o in out]) for i in range(3))


def _chunk_bounds(size, chunk: int):
    """Block ranges ``[s, e)`` of about ``chunk`` cells each."""
    ends = np.cumsum(size.astype(np.int64) ** 3)
    cuts = np.searchsorted(ends, np.arange(chunk, int(ends[-1]), chunk), side="right")
    edges = np.unique(np.concatenate([[0], np.maximum(cuts, 1), [len(size)]]))
    return list(zip(edges[:-1], edges[1:]))


def block_cells(lo, level, nxb, n_fine: int, seed: int, chunk: int = 1 << 21, threads: int | None = 1,
                field: str = "cloud", order: str = "F"):
    """Yield ``(pos int64 (m, 3), level int32 (m,), value float32 (m,))`` of
    the cells of the blocks ``lo``/``level`` of ``nxb`` cells per side (an
    int, or one size per block; see `block_leaves`), about ``chunk`` cells
    at a time; the values sample ``field`` (``cloud``, ``cosmo``) at cell centres.
    ``threads``: chunks computed in that many threads (None: every core).
    ``order``: cells inside a block x fastest ("F") or z fastest ("C")."""
    f, _ = _field(field, seed)
    size = np.broadcast_to(np.asarray(nxb, dtype=np.int64), level.shape)
    if not len(level):
        return
    yield from ordered_map(lambda r: _block_chunk(lo[r[0]:r[1]], level[r[0]:r[1]], size[r[0]:r[1]], n_fine, f,
                                                  order),
                           _chunk_bounds(size, chunk), threads=threads)


#: File layouts of `write_block_dataset`: how other writers order the same
#: kind of data. ``blocks``: this generator's (each block's cells together, x
#: fastest, blocks in refinement order); ``zfast``: the same with z fastest
#: inside a block (numpy's C order, as writers that dump [x, y, z] arrays
#: give); ``level``: blocks of one physical size on every level, so coarser
#: blocks hold fewer cells (``nxb >> level`` per side), refined region by
#: region (a third of the coarser blocks at random hold the next finer level:
#: a different cell set), z fastest, the file grouped by level, coarsest
#: first (as yt grids and many codes write);
#: ``space``: blocks sorted by position (x fastest inside); ``shuffled``: the
#: cells in random order (a file that keeps no order at all).
LAYOUTS = ("blocks", "zfast", "level", "space", "shuffled")


def _layout_leaves(args, layout: str):
    """`block_leaves` output rearranged for ``layout`` (see `LAYOUTS`):
    ``(lo, level, size, n_fine, seed)`` and the cell order inside blocks."""
    lo, level, nxb, n_fine, seed = args
    size = np.broadcast_to(np.asarray(nxb, dtype=np.int64), level.shape).copy()
    if layout == "level":                       # cut each leaf into blocks of nxb >> level cells per side
        top = int(size.max())
        sub = np.maximum(top >> level.astype(np.int64), 2)
        lo_parts, lev_parts, size_parts = [], [], []
        for s in np.unique(sub):
            u = np.nonzero(sub == s)[0]
            for s0 in np.unique(size[u]):
                v = u[size[u] == s0]
                s1 = min(int(s), int(s0))
                sub_lo, sub_level = _sub_blocks(lo[v], level[v], max(1, int(s0) // int(s)), s1)
                lo_parts.append(sub_lo)
                lev_parts.append(sub_level)
                size_parts.append(np.full(len(sub_level), s1))
        lo, level, size = (np.concatenate(p) for p in (lo_parts, lev_parts, size_parts))
        # refined region by region, as patch-based codes flag them: a third of the coarser
        # blocks, picked at random, hold the next finer level (same extent, 2x the cells per
        # side), so coarse blocks no longer come in aligned groups of 2^3
        finer = (level > 0) & (np.random.default_rng(seed + 3).random(len(level)) < 1 / 3)
        level = np.where(finer, level - 1, level).astype(level.dtype)
        size = np.where(finer, size * 2, size)
        order = np.argsort(-level.astype(np.int64), kind="stable")     # coarsest level first
        return (lo[order], level[order], size[order], n_fine, seed), "C"
    if layout == "space":
        order = np.lexsort((lo[:, 0], lo[:, 1], lo[:, 2]))
        return (lo[order], level[order], size[order], n_fine, seed), "F"
    return (lo, level, size, n_fine, seed), ("C" if layout == "zfast" else "F")


def write_block_dataset(path, cells: int, levels: int = 4, seed: int = 0, nxb=None, progress_bar=None,
                        name: str = "blocks", layout: str = "blocks") -> Path:
    """Write the block-structured data set ``name`` (``blocks``, ``cosmo``) as
    an ExaBricks pair ``path`` (``.cells``) + ``.scalars``, streaming block by
    block on every core (memory: a few chunks; ``shuffled`` holds the whole
    file's records, 16 B/cell, and a permutation); ``nxb``: see
    `block_leaves` (default: the data set's own); ``layout``: the order of
    the cells in the file (see `LAYOUTS`)."""
    if name not in BLOCK_DATASETS:
        raise ValueError(f"unknown block-structured data set {name!r} (choose from {', '.join(BLOCK_DATASETS)})")
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (choose from {', '.join(LAYOUTS)})")
    field, default_nxb = BLOCK_DATASETS[name]
    path = Path(path)
    if path.suffix != ".cells":
        raise ValueError(f"{path}: the streaming writer writes .cells files")
    path.parent.mkdir(parents=True, exist_ok=True)
    args, order = _layout_leaves(block_leaves(cells, levels, seed, default_nxb if nxb is None else nxb,
                                              field=field), layout)
    tmp_c, tmp_s = path.with_suffix(".cells.part"), path.with_suffix(".scalars.part")
    parts = block_cells(*args, threads=None, field=field, order=order)
    if layout == "shuffled":                     # all records, then one permutation
        parts = list(parts)
        all_rec = np.concatenate([np.column_stack([p, lv]).astype("<i4") for p, lv, _ in parts])
        all_val = np.concatenate([v for _, _, v in parts]).astype("<f4")
        del parts
        perm = np.random.default_rng(seed + 2).permutation(len(all_val))
        all_rec, all_val = all_rec[perm], all_val[perm]
        del perm
        step = 1 << 22
        parts = ((all_rec[s:s + step, :3], all_rec[s:s + step, 3], all_val[s:s + step])
                 for s in range(0, len(all_val), step))
    with open(tmp_c, "wb") as fc, open(tmp_s, "wb") as fs:
        for pos, lev, val in parts:
            if progress_bar is not None:
                progress_bar.update(len(lev))
            rec = np.empty((len(lev), 4), dtype="<i4")
            rec[:, :3], rec[:, 3] = pos, lev
            fc.write(rec.tobytes())
            fs.write(val.astype("<f4").tobytes())
    tmp_c.replace(path)
    tmp_s.replace(path.with_suffix(".scalars"))
    return path
