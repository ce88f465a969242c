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
from .memory import BYTES_PER_MACROCELL, require

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
            idx, owner = _expand_boxes(i0[sel], i1[sel], res)
            owner = sel[owner]
            np.minimum.at(vmin, idx, value[owner])
            np.maximum.at(vmax, idx, value[owner])
            np.bitwise_or.at(bits, idx, level_bit[owner])
            start = stop
        self.vmin, self.vmax, self.level_bits = vmin, vmax, bits

    @property
    def nbytes(self) -> int:
        return self.vmin.nbytes + self.vmax.nbytes + self.level_bits.nbytes + 4 * self.vmin.size


def enumerate_boxes(i0: np.ndarray, i1: np.ndarray):
    """Every integer point of the boxes ``i0..i1`` (inclusive, (B, 3)), x
    fastest: ``(x, y, z, owner)`` with the index of the box of each point."""
    counts = i1 - i0 + 1
    total = counts.prod(axis=1)
    owner = np.repeat(np.arange(len(total)), total)
    local = np.arange(int(total.sum())) - np.repeat(np.cumsum(total) - total, total)
    cx, cy = counts[owner, 0], counts[owner, 1]
    x = i0[owner, 0] + local % cx
    y = i0[owner, 1] + (local // cx) % cy
    z = i0[owner, 2] + local // (cx * cy)
    return x, y, z, owner


def _expand_boxes(i0: np.ndarray, i1: np.ndarray, res: np.ndarray):
    """Flat macrocell indices (x fastest) of every box ``i0..i1`` (inclusive),
    with the index of the box each entry came from."""
    x, y, z, owner = enumerate_boxes(i0, i1)
    return x + res[0] * (y + res[1] * z), owner


#: Cost of one DDA step relative to one density look-up (tent/nearest hash
#: sampling on llvm_ad_rgb), used by `auto_resolution`; calibrated with the
#: grid-resolution sweep of ``python -m mi_amr.bench``.
STEP_COST = 0.08
CANDIDATES = (8, 16, 32, 64, 128)


def range_majorants_host(tf, vmin, vmax, density_scale: float) -> np.ndarray:
    """``density_scale * max alpha`` over the TF entries covering each value
    range (numpy; 0 for empty ranges). Same rule as the Dr.Jit kernel."""
    finite = vmin <= vmax
    lo, hi = tf.range_entries(np.where(finite, vmin, 0.0), np.where(finite, vmax, 0.0))
    st = tf.sparse_table()
    k = np.floor(np.log2(hi - lo + 1)).astype(np.int64)
    m = np.maximum(st[k, lo], st[k, hi + 1 - (np.int64(1) << k)])
    return np.where(finite, density_scale * m, 0.0)


def auto_resolution(cells: AMRCells, tf, density_scale: float, world_scale: float = 1.0,
                    support: str = "tent", candidates=CANDIDATES):
    """Grid resolution (longest axis) minimising the expected tracking cost
    per unit of ray length in the unit cube:

        cost(R) = STEP_COST * 1.5 R  +  (E[mu_bar] + E[mu_bar^2] / E[mu_bar]) / 2

    (a ray crosses about 1.5 R macrocells per unit length; delta/ratio
    tracking takes ``mu_bar`` tentative collisions per unit length, each a
    density look-up). Half the rays are taken as uniform through the volume
    (camera rays: the plain mean over macrocells), half as starting where
    collisions happen (scattered and shadow rays: the mean weighted by
    ``mu_bar``). ``world_scale`` converts local to world length. The
    value ranges are splatted once at the finest candidate and max/min-pooled
    by powers of two for the coarser ones. Returns ``(best, {R: cost})``."""
    lo, hi = cells.bounds
    ext = int((hi - lo).max())
    cands = sorted(c for c in candidates if c <= max(ext, min(candidates)))
    finest = cands[-1]
    g = MacrocellGrid(cells, finest, support=support)
    r = g.res
    vmin = g.vmin.reshape(r[2], r[1], r[0])
    vmax = g.vmax.reshape(r[2], r[1], r[0])
    costs = {}
    for c in reversed(cands):
        f = max(1, finest // c)
        pmin, pmax = _pool(vmin, f, np.minimum, np.inf), _pool(vmax, f, np.maximum, -np.inf)
        mu = range_majorants_host(tf, pmin.ravel(), pmax.ravel(), density_scale).astype(np.float64) * world_scale
        m1 = float(mu.mean())
        m2 = float((mu * mu).mean()) / m1 if m1 > 0 else 0.0
        costs[c] = STEP_COST * 1.5 * c + 0.5 * (m1 + m2)
    best = min(costs, key=costs.get)
    return best, costs


def _pool(a: np.ndarray, f: int, op, fill) -> np.ndarray:
    """Reduce blocks of f^3 cells (padding with ``fill``)."""
    if f == 1:
        return a
    pad = [(0, (-n) % f) for n in a.shape]
    a = np.pad(a, pad, constant_values=fill)
    z, y, x = (n // f for n in a.shape)
    return op.reduce(op.reduce(op.reduce(a.reshape(z, f, y, f, x, f), axis=5), axis=3), axis=1)
