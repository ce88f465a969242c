"""The uniform macrocell grid: per-macrocell value ranges and level masks.

The grid covers the AMR bounding box, which the medium maps to the unit
cube; macrocell ``(i, j, k)`` of a ``(rx, ry, rz)`` grid spans
``[i/rx, (i+1)/rx] x ...`` in that unit cube. Each macrocell keeps

* ``vmin, vmax``: the range of values of every cell whose *support*
  overlaps it (inclusive), so that any value the reconstruction can produce
  inside the macrocell lies in the range (docs/design.md section 4);
* ``level_bits``: bit L set when a level-L cell's support overlaps it; the
  reconstruction only visits those levels.

Majorants are derived from the ranges through the transfer function (see
`mi_amr.transfer.device`), so a TF change needs no rebuild.
"""

from __future__ import annotations

import threading

import numpy as np

from ..data.blocks import BlockVolume
from ..memory import grid_bytes, require
from ..parallel import build_threads, ordered_map
from ..progress import progress
from ..reconstruction import DEFAULT_METHOD, Reconstruction
from .block_windows import block_window_reduce, block_windows
from .value_masks import ValueBins, value_masks

#: Cells per chunk of blocks that one thread reduces onto the macrocells.
BLOCK_CHUNK = 1 << 20

def axis_resolution(longest: int, extent) -> np.ndarray:
    """Per-axis cell counts of a grid over a box of ``extent`` (x, y, z) with
    ``longest`` cells along its longest axis, the others in proportion."""
    ext = np.asarray(extent, dtype=np.float64)
    return np.maximum(1, np.round(longest * ext / ext.max())).astype(np.int64)


def default_resolution(cells: BlockVolume) -> np.ndarray:
    """Grid resolution chosen from the data: about 8 cells per macrocell on
    average, a power of two along the longest axis between 8 and 128, never
    finer than the finest level, other axes in proportion. (Measured on the
    bundled scenes: 16-32 macrocells per axis for 20k cells beat 8 and 64.)"""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    longest = 2 ** round(np.log2(max(len(cells) / 8.0, 1.0)) / 3)
    longest = int(np.clip(longest, 8, 128))
    res = axis_resolution(longest, ext)
    return np.minimum(res, np.maximum(1, ext.astype(np.int64)))


#: The finest level of a leaf that no cell reaches (its majorant is 0 too):
#: `finest_levels_in_boxes`, the region trees' and the device grids' levels.
NO_LEVEL = 31


def finest_levels_in_boxes(level_bits: np.ndarray, tree) -> np.ndarray:
    """The finest level set in the level masks ``level_bits`` (indexed
    ``[x, y, z]``) over each leaf box ``[leaf_lo, leaf_hi)`` of ``tree``
    (macrocell units): uint32 per leaf, `NO_LEVEL` where no bit is set. One summed
    table per level present, so the cost is per macrocell and per leaf, not
    per (leaf, macrocell) pair."""
    lo = np.asarray(tree.leaf_lo, np.int64)
    hi = np.asarray(tree.leaf_hi, np.int64)
    out = np.full(len(lo), NO_LEVEL, np.uint32)
    present = int(np.bitwise_or.reduce(level_bits, axis=None)) if level_bits.size else 0
    for L in reversed(range(32)):                 # coarsest first: finer levels overwrite
        if not present >> L & 1:
            continue
        s = np.zeros(tuple(n + 1 for n in level_bits.shape), np.int64)
        s[1:, 1:, 1:] = ((level_bits >> np.uint32(L)) & np.uint32(1)).astype(np.int64).cumsum(0).cumsum(1).cumsum(2)
        x0, y0, z0, x1, y1, z1 = lo[:, 0], lo[:, 1], lo[:, 2], hi[:, 0], hi[:, 1], hi[:, 2]
        count = (s[x1, y1, z1] - s[x0, y1, z1] - s[x1, y0, z1] - s[x1, y1, z0]
                 + s[x0, y0, z1] + s[x0, y1, z0] + s[x1, y0, z0] - s[x0, y0, z0])
        out[count > 0] = L
    return out


#: Host bytes of `MacrocellGrid.incidence`'s temporaries: per present cell
#: (its slot, block, level, six macrocell bounds and counts, int64) and per
#: (cell, macrocell) pair (owner, offset, three coordinates and the results).
INCIDENCE_CELL_BYTES = 96
INCIDENCE_PAIR_BYTES = 64


class MacrocellGrid:
    """Value ranges and level masks on a uniform grid over the data bounds.

    Parameters
    ----------
    cells : BlockVolume
        Read block by block (`block_chunks`).
    resolution : int or (3,) ints, optional
        Macrocells per axis (x, y, z). ``None`` picks `default_resolution`;
        a single int is the count along the longest axis.
    support : Reconstruction
        The reconstruction method (`mi_amr.reconstruction`): each cell is
        splatted over its support box (`Reconstruction.support_box`:
        ``tent`` ``[c - w, c + w]``, ``nearest`` the cell itself).
    chunk : int
        Macrocell entries expanded at once (bounds the build's temporaries).
    memory_limit : float, optional
        Bytes; a grid that would need more raises `MemoryLimitError` before
        anything is allocated.
    masks : bool
        Also keep per-macrocell value masks (``masks``, uint64; see
        `mi_amr.structures.value_masks`), else ``masks`` is None.
    """

    def __init__(self, cells: BlockVolume, resolution=None, support: Reconstruction = DEFAULT_METHOD,
                 chunk: int = 1 << 20, memory_limit: float | None = None, masks: bool = False):
        lo, hi = cells.bounds
        ext = (hi - lo).astype(np.float64)
        if resolution is None:
            res = default_resolution(cells)
        elif np.ndim(resolution) == 0:
            r = int(resolution)
            if r < 1:
                raise ValueError(f"grid_resolution must be >= 1, got {r}")
            res = axis_resolution(r, ext)
        else:
            res = np.asarray(resolution, dtype=np.int64)
            if res.shape != (3,) or np.any(res < 1):
                raise ValueError(f"grid_resolution must be 3 positive ints, got {resolution}")
        self.res = res
        self.lo, self.extent = lo, ext
        if self._from_file(cells, support, masks):
            return
        slots = cells.values.size
        require(grid_bytes(float(np.prod(res)), slots),
                f"a macrocell grid of {'x'.join(str(int(r)) for r in res)} cells", memory_limit,
                "choose a smaller grid_resolution")
        n = int(np.prod(res))
        vmin = np.full(n, np.inf, dtype=np.float32)
        vmax = np.full(n, -np.inf, dtype=np.float32)
        bits = np.zeros(n, dtype=np.uint32)
        splat = _RangeSplat(cells.origin, lo, hi, res, support, chunk, vmin, vmax, bits)
        with progress(len(cells), f"macrocell ranges {'x'.join(str(int(r)) for r in res)}") as bar:
            def add(chunk):
                level, coord, values = chunk
                splat.add_blocks(level, coord, values, cells.log2_block)
                return int(np.count_nonzero(~np.isnan(values)))
            # chunks of about BLOCK_CHUNK cells, reduced on every core
            for n in ordered_map(add, cells.block_chunks(BLOCK_CHUNK), build_threads()):
                bar.update(n)
            splat.finish()
        self.vmin, self.vmax, self.level_bits = vmin, vmax, bits
        self.masks = self.bins = None
        if masks:
            self.bins = ValueBins.of(cells)
            self.masks = value_masks(cells, self, support, self.bins)

    def incidence(self, cells: BlockVolume, support: Reconstruction, max_pairs: int,
                  memory_limit: float | None = None):
        """``(slots, macrocells)``: for each present cell of ``cells`` (its
        slot in ``cells.values``), every macrocell (flat index ``x + rx (y +
        ry z)``) its support box overlaps, one pair each: the fold the build
        makes, as index pairs, so that new values of the same cells give new
        ranges by two scatter-reductions (`Structures.revalue`). None when
        there would be more than ``max_pairs`` pairs. The temporaries
        (about `INCIDENCE_CELL_BYTES` a cell and `INCIDENCE_PAIR_BYTES` a
        pair) are checked against the memory limit first (`MemoryLimitError`)."""
        what = f"the macrocell incidence of {len(cells)} cells"
        require(INCIDENCE_CELL_BYTES * len(cells), what, memory_limit)
        lb = cells.log2_block
        slots = np.flatnonzero(~np.isnan(cells.values))
        block = slots >> (3 * lb)
        level = cells.level[block].astype(np.int64)
        width = (np.int64(1) << level).astype(np.float64)
        span = []
        for axis in range(3):
            q = (cells.coord[block, axis].astype(np.int64) << lb) + ((slots >> (axis * lb)) & ((1 << lb) - 1))
            qw = (q << level) + (np.int64(cells.origin[axis]) - np.int64(self.lo[axis]))
            a, b = support.support_box(qw.astype(np.float64), width)
            top = self.res[axis] - 1
            scale = self.res[axis] / self.extent[axis]
            span.append((np.clip(np.floor(a * scale), 0, top).astype(np.int64),
                         np.clip(np.floor(b * scale), 0, top).astype(np.int64)))
        n = [i1 - i0 + 1 for i0, i1 in span]
        count = n[0] * n[1] * n[2]
        total = int(count.sum())
        if total > max_pairs:
            return None
        require(INCIDENCE_CELL_BYTES * len(cells) + INCIDENCE_PAIR_BYTES * total, what, memory_limit)
        owner = np.repeat(np.arange(slots.size), count)
        k = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
        nx, ny = n[0][owner], n[1][owner]
        ix = span[0][0][owner] + k % nx
        iy = span[1][0][owner] + (k // nx) % ny
        iz = span[2][0][owner] + k // (nx * ny)
        return slots[owner], ix + self.res[0] * (iy + self.res[1] * iz)

    def _from_file(self, cells, support, masks: bool) -> bool:
        """Take the grid a native file stored for this method and resolution
        (`BlockVolume.stored_grids`, made by the same build when the file
        was written); False when it has none."""
        g = getattr(cells, "stored_grids", {}).get(support.name)
        if g is None or not np.array_equal(g["res"], self.res) or (masks and g["masks"] is None):
            return False
        self.vmin, self.vmax, self.level_bits = g["vmin"], g["vmax"], g["bits"]
        self.masks = g["masks"] if masks else None
        self.bins = ValueBins(*g["bins"]) if masks else None
        return True

    def to_file(self) -> dict:
        """This grid as `mi_amr.data.amrb.write_amrb` stores it."""
        return {"res": self.res, "vmin": self.vmin, "vmax": self.vmax, "bits": self.level_bits,
                "masks": self.masks, "bins": None if self.bins is None else (self.bins.lo, self.bins.hi)}

    def pooled(self, resolution: int) -> "MacrocellGrid | None":
        """The grid of ``resolution`` (longest axis) made by merging blocks of
        this grid's macrocells (min, max, or): exactly what a build at that
        resolution gives when its macrocells tile this grid's, else None."""
        res = axis_resolution(resolution, self.extent)
        f = self.res // res
        if np.any(f < 1) or np.any(f * res != self.res) or len(set(f.tolist())) != 1:
            return None
        f = int(f[0])
        shape = (int(self.res[2]), int(self.res[1]), int(self.res[0]))
        g = MacrocellGrid.__new__(MacrocellGrid)
        g.res, g.lo, g.extent = res, self.lo, self.extent

        def pool(a, op):
            a = a.reshape(shape[0] // f, f, shape[1] // f, f, shape[2] // f, f)
            return op.reduce(op.reduce(op.reduce(a, axis=5), axis=3), axis=1).reshape(-1)
        g.vmin, g.vmax = pool(self.vmin, np.minimum), pool(self.vmax, np.maximum)
        g.level_bits = pool(self.level_bits, np.bitwise_or)
        g.masks = None if self.masks is None else pool(self.masks, np.bitwise_or)
        g.bins = self.bins
        return g

    @property
    def nbytes(self) -> int:
        masks = 0 if self.masks is None else self.masks.nbytes
        return self.vmin.nbytes + self.vmax.nbytes + self.level_bits.nbytes + 4 * self.vmin.size + masks


class _RangeSplat:
    """Folds cells into the macrocell ranges and level masks, chunk by chunk.

    Coarse levels (their level grid at most `DENSE_FACTOR` times the
    macrocell count) are first written into a dense grid of the level, then
    reduced with windowed min/max along each axis: a macrocell's window is
    exactly the cells whose support box overlaps it. Finer levels, whose
    supports span at most 3 macrocells per axis, are folded in with one
    vectorised pass per offset; anything wider goes through `expand_boxes`.
    Every path gives the same ranges as folding each cell into each
    macrocell its support overlaps.
    """

    DENSE_FACTOR = 4

    def __init__(self, origin, lo, hi, res, support, chunk, vmin, vmax, bits):
        self.origin, self.lo, self.res = np.asarray(origin, np.int64), np.asarray(lo, np.int64), res
        self.ext = (np.asarray(hi, np.int64) - self.lo).astype(np.float64)
        self.scale = res / self.ext
        self.support, self.chunk = support, chunk
        self.vmin, self.vmax, self.bits = vmin, vmax, bits
        self.hi = np.asarray(hi, np.int64)
        self.dense = {}               # level -> (qmin (3,), values (nz, ny, nx) float32, NaN = no cell)
        # add_blocks runs in several threads (numpy releases the GIL in the
        # reductions): the lazily made level grids and the folds into the
        # shared arrays are taken one thread at a time
        self._grid_lock = threading.Lock()
        self._fold_lock = threading.Lock()

    def _dense_shape(self, L):
        qmin = (self.lo - self.origin) >> L
        qmax = (self.hi - 1 - self.origin) >> L
        return qmin, (qmax - qmin + 1)

    def _is_dense(self, L):
        _, n = self._dense_shape(L)
        return float(np.prod(n.astype(np.float64))) <= self.DENSE_FACTOR * float(np.prod(self.res))

    def _dense_grid(self, L):
        """``(qmin, grid)`` of level ``L``: its level grid, NaN where no cell yet."""
        with self._grid_lock:
            if L not in self.dense:
                qmin, n = self._dense_shape(L)
                self.dense[L] = (qmin, np.full((int(n[2]), int(n[1]), int(n[0])), np.nan, np.float32))
            return self.dense[L]

    def _macrocells(self, qw, w, axis=slice(None)):
        """First and last macrocell (``i0``, ``i1``, clipped) that the support
        of cells with lower corners ``qw`` (finest units relative to lo,
        along ``axis``, or all three) overlaps; ``w`` the cell width."""
        a, b = self.support.support_box(qw, w)
        top = self.res[axis] - 1
        return (np.clip(np.floor(a * self.scale[axis]), 0, top).astype(np.int64),
                np.clip(np.floor(b * self.scale[axis]), 0, top).astype(np.int64))

    def _level_macrocells(self, q, L, axis):
        """`_macrocells` of level-``L`` cells at level coordinates ``q`` (any shape) on ``axis``."""
        qw = (q << L) + (self.origin[axis] - self.lo[axis])
        return self._macrocells(qw.astype(np.float64), float(1 << L), axis)

    def add_blocks(self, level, coord, values, log2_block):
        """Fold blocks of cells: ``level`` (k,), block coordinates ``coord``
        (k, 3), ``values`` (k, B, B, B) indexed [block, z, y, x], NaN = no
        cell. Dense levels are written into their level grid; on the others
        each block is reduced over the window of cells that reach each
        macrocell, axis by axis, and folded in once per macrocell."""
        B = 1 << log2_block
        for L in np.unique(level):
            L = int(L)
            sel = np.nonzero(level == L)[0]
            q0 = coord[sel].astype(np.int64) << log2_block          # first cell of each block
            v = values[sel]
            if self._is_dense(L):
                qmin, grid = self._dense_grid(L)
                r = q0 - qmin
                t = np.arange(B)
                iz = np.broadcast_to(r[:, 2, None, None, None] + t[None, :, None, None], v.shape)
                iy = np.broadcast_to(r[:, 1, None, None, None] + t[None, None, :, None], v.shape)
                ix = np.broadcast_to(r[:, 0, None, None, None] + t[None, None, None, :], v.shape)
                ok = ~np.isnan(v)                  # present cells lie inside the level grid
                grid[iz[ok], iy[ok], ix[ok]] = v[ok]
                continue
            vmin = np.where(np.isnan(v), np.inf, v)
            vmax = np.where(np.isnan(v), -np.inf, v)
            idx, (vmin, vmax), ok = block_windows(
                q0, B, lambda q, axis: self._level_macrocells(q, L, axis), self.res,
                [(vmin, np.minimum, np.inf), (vmax, np.maximum, -np.inf)])
            ok &= vmax > -np.inf
            idx = idx[ok]
            with self._fold_lock:
                np.minimum.at(self.vmin, idx, vmin[ok])
                np.maximum.at(self.vmax, idx, vmax[ok])
                np.bitwise_or.at(self.bits, idx, np.uint32(1 << L))

    def finish(self):
        """Reduce the dense levels into the macrocells: the minima and the
        maxima of each level are independent reductions, run on every core."""
        res = self.res
        size = int(np.prod(res))

        def reduce(L, qmin, grid, op, fill):
            # the whole level grid as one block, axis 0 of size 1
            a = np.where(np.isnan(grid), fill, grid)[None]
            for axis in range(3):                  # x, y, z: array axes 3, 2, 1
                i0, i1 = self._level_macrocells(qmin[axis] + np.arange(a.shape[3 - axis]), L, axis)
                j = np.arange(res[axis])
                qa = np.searchsorted(i1, j, side="left")[None]   # first cell reaching macrocell j
                qb = np.searchsorted(i0, j, side="right")[None] - 1   # last cell starting at or before j
                a = block_window_reduce(a, 3 - axis, qa, qb, op, fill)
            assert a.size == size
            return L, op, a.reshape(-1)

        tasks = [(L, qmin, grid, op, fill) for L, (qmin, grid) in self.dense.items()
                 for op, fill in ((np.minimum, np.inf), (np.maximum, -np.inf))]
        for L, op, a in ordered_map(lambda t: reduce(*t), tasks, build_threads()):
            if op is np.minimum:
                np.minimum(self.vmin, a, out=self.vmin)
            else:
                np.maximum(self.vmax, a, out=self.vmax)
                self.bits |= np.where(a > -np.inf, np.uint32(1 << L), np.uint32(0))
        self.dense.clear()


