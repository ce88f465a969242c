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

import numpy as np

from ..data.cells import AMRCells
from ..memory import BYTES_PER_MACROCELL, require
from .boxes import expand_boxes

#: Boxes of more macrocells than this are written as array slices.
LARGE_BOX = 4096


def axis_resolution(longest: int, extent) -> np.ndarray:
    """Per-axis cell counts of a grid over a box of ``extent`` (x, y, z) with
    ``longest`` cells along its longest axis, the others in proportion."""
    ext = np.asarray(extent, dtype=np.float64)
    return np.maximum(1, np.round(longest * ext / ext.max())).astype(np.int64)


def default_resolution(cells: AMRCells) -> np.ndarray:
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


class MacrocellGrid:
    """Value ranges and level masks on a uniform grid over the data bounds.

    Parameters
    ----------
    cells : AMRCells
    resolution : int or (3,) ints, optional
        Macrocells per axis (x, y, z). ``None`` picks `default_resolution`;
        a single int is the count along the longest axis.
    support : {"tent", "nearest"}
        ``tent`` splats each cell's tent support ``[c - w, c + w]``;
        ``nearest`` only the cell itself.
    chunk : int
        Macrocell entries expanded at once (bounds the build's temporaries).
    memory_limit : float, optional
        Bytes; a grid that would need more raises `MemoryLimitError` before
        anything is allocated.
    """

    def __init__(self, cells: AMRCells, resolution=None, support: str = "tent",
                 chunk: int = 1 << 20, memory_limit: float | None = None):
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
        require(BYTES_PER_MACROCELL * float(np.prod(res)),
                f"a macrocell grid of {'x'.join(str(int(r)) for r in res)} cells", memory_limit,
                "choose a smaller grid_resolution")
        self.res = res
        self.lo, self.extent = lo, ext
        n = int(np.prod(res))
        vmin = np.full(n, np.inf, dtype=np.float32)
        vmax = np.full(n, -np.inf, dtype=np.float32)
        bits = np.zeros(n, dtype=np.uint32)
        # the macrocell box of each cell's support
        scale = res / ext
        pos = cells.pos.astype(np.float64) - lo
        w = cells.width.astype(np.float64)[:, None]
        a, b = (pos - 0.5 * w, pos + 1.5 * w) if support == "tent" else (pos, pos + w)
        i0 = np.clip(np.floor(a * scale), 0, res - 1).astype(np.int64)
        i1 = np.clip(np.floor(b * scale), 0, res - 1).astype(np.int64)
        del pos, w, a, b
        volume = (i1 - i0 + 1).prod(axis=1)
        value = cells.value
        level_bit = np.uint32(1) << cells.level.astype(np.uint32)
        # Large boxes (coarse cells over many macrocells) are written as
        # slices of the 3D arrays; they are few, since each level's cells
        # are disjoint. The rest are expanded in chunks of bounded size.
        large = np.nonzero(volume > LARGE_BOX)[0]
        shape = (int(res[2]), int(res[1]), int(res[0]))
        vmin3, vmax3, bits3 = vmin.reshape(shape), vmax.reshape(shape), bits.reshape(shape)
        for i in large:
            sl = (slice(i0[i, 2], i1[i, 2] + 1), slice(i0[i, 1], i1[i, 1] + 1), slice(i0[i, 0], i1[i, 0] + 1))
            np.minimum(vmin3[sl], value[i], out=vmin3[sl])
            np.maximum(vmax3[sl], value[i], out=vmax3[sl])
            np.bitwise_or(bits3[sl], level_bit[i], out=bits3[sl])
        small = np.nonzero(volume <= LARGE_BOX)[0]
        ends = np.cumsum(volume[small])
        start = 0
        while start < len(small):
            stop = max(start + 1, int(np.searchsorted(ends, ends[start] - volume[small[start]] + chunk,
                                                      side="right")))
            sel = small[start:stop]
            idx, owner = expand_boxes(i0[sel], i1[sel], res)
            owner = sel[owner]
            np.minimum.at(vmin, idx, value[owner])
            np.maximum.at(vmax, idx, value[owner])
            np.bitwise_or.at(bits, idx, level_bit[owner])
            start = stop
        self.vmin, self.vmax, self.level_bits = vmin, vmax, bits

    @property
    def nbytes(self) -> int:
        return self.vmin.nbytes + self.vmax.nbytes + self.level_bits.nbytes + 4 * self.vmin.size
