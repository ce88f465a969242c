"""Bricks: dense boxes of same-level cells (the ExaBricks decomposition).

Each level's cells are grouped into aligned blocks of at most ``max_width``
cells per side; a block's tight bounding box becomes a brick when the cells
fill it completely, otherwise it is split in two along its longest side and
both halves are treated the same way. All bricks of a level are processed at
once per round (vectorised). A brick's *domain* is its bounds grown by half a
cell width: the region where its cells' tent supports reach.
"""

from __future__ import annotations

import numpy as np

from ..data.blocks import BlockVolume, block_offsets
from ..data.cells import AMRCells
from ..progress import progress


class Bricks:
    """The bricks of an AMR data set.

    Attributes (numpy, finest-level units)
    --------------------------------------
    lo : int64 (B, 3)      lower corner of each brick
    dims : int64 (B, 3)    cells per axis
    level : int32 (B,)     cell level
    offset : int64 (B,)    start of the brick's values in ``values``
    values : float32 (V,)  cell values, x fastest within each brick
    vmin, vmax : float32 (B,)  value range of the brick's own cells
    """

    def __init__(self, data: AMRCells | BlockVolume, max_width: int = 8):
        if max_width < 1:
            raise ValueError(f"max_width must be >= 1, got {max_width}")
        los, dims, levels, values = [], [], [], []
        bar = progress(len(data), "bricks")
        for L, q, v in _levels(data, max_width):
            bar.update(len(v) if q is not None else len(v[2]))
            if q is None:                        # whole bricks already (full blocks): lower corners, values
                lo, dm, vals = v
            else:
                lo, dm, order = _bricks_of_level(q, max_width)
                vals = v[order]                  # x fastest within each brick, bricks in order
            los.append(lo << L)
            dims.append(dm)
            levels.append(np.full(len(lo), L, dtype=np.int32))
            values.append(vals)
        bar.close()
        self.lo = np.concatenate(los)
        self.dims = np.concatenate(dims)
        self.level = np.concatenate(levels)
        counts = self.dims.prod(axis=1)
        self.offset = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.values = np.concatenate(values).astype(np.float32)
        self.vmin = np.minimum.reduceat(self.values, self.offset)
        self.vmax = np.maximum.reduceat(self.values, self.offset)

    def __len__(self):
        return len(self.level)

    @property
    def width(self) -> np.ndarray:
        return np.int64(1) << self.level.astype(np.int64)

    @property
    def hi(self) -> np.ndarray:
        return self.lo + self.dims * self.width[:, None]

    def domains(self) -> tuple[np.ndarray, np.ndarray]:
        """Extended domains ``[lo - w/2, hi + w/2]`` (float64, finest units)."""
        h = 0.5 * self.width[:, None]
        return self.lo - h, self.hi + h

    @property
    def nbytes(self) -> int:
        return self.values.nbytes + len(self) * (3 * 8 + 3 * 8 + 4 + 8 + 8)


def _levels(data, max_width: int):
    """Per level present: ``(L, q, value)`` with ``q`` the cells' level
    coordinates (int64 (m, 3), absolute: ``pos >> L``). From a `BlockVolume`
    one level's blocks at a time, with no record of all cells; blocks that
    are full and split evenly into ``max_width^3`` bricks come as ``(L,
    None, (lower corners, dims, values))`` directly."""
    if isinstance(data, BlockVolume):
        B, b3 = data.block, data.block ** 3
        local = block_offsets(B)
        for L in np.unique(data.level):
            L = int(L)
            sel = np.nonzero(data.level == L)[0]
            v = data.values.reshape(-1, b3)[sel]
            full = ~np.isnan(v).any(axis=1) if B % max_width == 0 else np.zeros(len(sel), bool)
            if full.any():
                m, n = max_width, B // max_width
                vf = v[full].reshape(-1, n, m, n, m, n, m)          # [block, bz, z, by, y, bx, x]
                vals = vf.transpose(0, 1, 3, 5, 2, 4, 6).reshape(-1)  # brick after brick, x fastest
                sub = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"),
                               -1).reshape(-1, 3)[:, ::-1] * m          # (bz, by, bx) order -> x, y, z
                q0 = (data.coord[sel][full].astype(np.int64) << data.log2_block) + (data.origin >> L)
                lo = (q0[:, None, :] + sub[None]).reshape(-1, 3)
                yield L, None, (lo, np.full((len(lo), 3), m, np.int64), vals)
            rest = ~full
            if rest.any():
                bi, ci = np.nonzero(~np.isnan(v[rest]))
                q = (data.coord[sel][rest][bi].astype(np.int64) << data.log2_block) + local[ci] + (data.origin >> L)
                yield L, q, v[rest][bi, ci]
        return
    for L in data.levels:
        L = int(L)
        idx = np.nonzero(data.level == L)[0]
        yield L, data.pos[idx] >> L, data.value[idx]


def _bricks_of_level(q: np.ndarray, max_width: int):
    """Split the cells (level coordinates ``q``) of one level into complete
    boxes. Returns (lower corners, dims, member order): the indices of the
    cells, brick after brick, x fastest within each brick."""
    key = q // max_width
    _, node = np.unique(_row_keys(key), return_inverse=True)
    out_lo, out_dims, out_members = [], [], []
    cell = np.arange(len(q))
    while len(cell):
        n = int(node.max()) + 1
        qc = q[cell]
        lo = np.full((n, 3), np.iinfo(np.int64).max)
        hi = np.full((n, 3), np.iinfo(np.int64).min)
        for a in range(3):                      # 1-D reductions (ufunc.at is fast on those)
            np.minimum.at(lo[:, a], node, qc[:, a])
            np.maximum.at(hi[:, a], node, qc[:, a] + 1)
        cnt = np.bincount(node, minlength=n)
        ext = hi - lo
        full = cnt == ext.prod(axis=1)
        done = full[node]
        if done.any():
            # emit the full nodes: members sorted x fastest within each node
            dn = node[done]
            dc = cell[done]
            rel = q[dc] - lo[dn]
            lin = rel[:, 0] + ext[dn, 0] * (rel[:, 1] + ext[dn, 1] * rel[:, 2])
            order = np.lexsort((lin, dn))
            dn, dc = dn[order], dc[order]
            ids = np.unique(dn)
            out_lo.append(lo[ids])
            out_dims.append(ext[ids])
            out_members.append(dc)
        cell, node = cell[~done], node[~done]
        if not len(cell):
            break
        axis = np.argmax(ext, axis=1)
        mid = (lo[np.arange(n), axis] + hi[np.arange(n), axis]) // 2
        side = q[cell, axis[node]] >= mid[node]
        half = 2 * node + side                  # dense ids of the halves, in order (no sort)
        present = np.zeros(2 * n, dtype=bool)
        present[half] = True
        node = (np.cumsum(present) - 1)[half]
    return np.concatenate(out_lo), np.concatenate(out_dims), np.concatenate(out_members)


def _row_keys(a: np.ndarray) -> np.ndarray:
    a = a - a.min(axis=0)
    m = a.max(axis=0) + 1
    return a[:, 0] + m[0] * (a[:, 1] + m[1] * a[:, 2])
