"""The uniform macrocell grid: per-macrocell value ranges and level masks.

The grid covers the AMR bounding box, which the medium maps to the unit
cube; macrocell ``(i, j, k)`` of a ``(rx, ry, rz)`` grid spans
``[i/rx, (i+1)/rx] x ...`` in that unit cube. Each macrocell keeps

* ``vmin, vmax``: the range of values of every cell whose *support*
  overlaps it (inclusive), so that any value the reconstruction can produce
  inside the macrocell lies in the range (DESIGN.md section 4);
* ``level_bits``: bit L set when a level-L cell's support overlaps it; the
  reconstruction only visits those levels.

Majorants are derived from the ranges through the transfer function (see
`mi_amr.transfer_jit`), so a TF change needs no rebuild.
"""

from __future__ import annotations

import numpy as np

from .cells import AMRCells


def default_resolution(cells: AMRCells) -> np.ndarray:
    """Grid resolution chosen from the data: about 8 cells per macrocell on
    average, a power of two along the longest axis between 8 and 128, never
    finer than the finest level, other axes in proportion. (Measured on the
    bundled scenes: 16-32 macrocells per axis for 20k cells beat 8 and 64.)"""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    longest = 2 ** round(np.log2(max(len(cells) / 8.0, 1.0)) / 3)
    longest = int(np.clip(longest, 8, 128))
    res = np.maximum(1, np.round(longest * ext / ext.max())).astype(np.int64)
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
    """

    def __init__(self, cells: AMRCells, resolution=None, support: str = "tent",
                 chunk: int = 1 << 20):
        lo, hi = cells.bounds
        ext = (hi - lo).astype(np.float64)
        if resolution is None:
            res = default_resolution(cells)
        elif np.ndim(resolution) == 0:
            r = int(resolution)
            if r < 1:
                raise ValueError(f"grid_resolution must be >= 1, got {r}")
            res = np.maximum(1, np.round(r * ext / ext.max())).astype(np.int64)
        else:
            res = np.asarray(resolution, dtype=np.int64)
            if res.shape != (3,) or np.any(res < 1):
                raise ValueError(f"grid_resolution must be 3 positive ints, got {resolution}")
        if int(np.prod(res)) > 2**27:
            raise ValueError(f"grid resolution {res.tolist()} has too many macrocells")
        self.res = res
        self.lo, self.extent = lo, ext
        n = int(np.prod(res))
        vmin = np.full(n, np.inf, dtype=np.float32)
        vmax = np.full(n, -np.inf, dtype=np.float32)
        bits = np.zeros(n, dtype=np.uint32)
        scale = res / ext
        for s in range(0, len(cells), chunk):
            pos = cells.pos[s:s + chunk].astype(np.float64) - lo
            w = cells.width[s:s + chunk].astype(np.float64)[:, None]
            if support == "tent":
                a, b = pos - 0.5 * w, pos + 1.5 * w
            else:
                a, b = pos, pos + w
            i0 = np.clip(np.floor(a * scale), 0, res - 1).astype(np.int64)
            i1 = np.clip(np.floor(b * scale), 0, res - 1).astype(np.int64)
            idx, owner = _expand_boxes(i0, i1, res)
            np.minimum.at(vmin, idx, cells.value[s:s + chunk][owner])
            np.maximum.at(vmax, idx, cells.value[s:s + chunk][owner])
            np.bitwise_or.at(bits, idx, (np.uint32(1) << cells.level[s:s + chunk][owner].astype(np.uint32)))
        self.vmin, self.vmax, self.level_bits = vmin, vmax, bits

    @property
    def nbytes(self) -> int:
        return self.vmin.nbytes + self.vmax.nbytes + self.level_bits.nbytes + 4 * self.vmin.size


def _expand_boxes(i0: np.ndarray, i1: np.ndarray, res: np.ndarray):
    """Flat macrocell indices (x fastest) of every box ``i0..i1`` (inclusive),
    with the index of the box each entry came from."""
    counts = i1 - i0 + 1
    total = counts.prod(axis=1)
    owner = np.repeat(np.arange(len(total)), total)
    local = np.arange(int(total.sum())) - np.repeat(np.cumsum(total) - total, total)
    cx, cy = counts[owner, 0], counts[owner, 1]
    x = i0[owner, 0] + local % cx
    y = i0[owner, 1] + (local // cx) % cy
    z = i0[owner, 2] + local // (cx * cy)
    return x + res[0] * (y + res[1] * z), owner
