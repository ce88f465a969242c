"""Bricks: dense boxes of same-level cells (the ExaBricks decomposition).

Bricks are cut from the blocks of a `BlockVolume` and never cross one, so a
brick's cells are read in place from the volume's values (no copy): cell
``(x, y, z)`` of a brick is ``values[offset + x + B (y + B z)]`` for blocks
of ``B^3``. Within each block, cells are grouped into aligned groups of at
most ``min(max_width, B)`` cells per side; a group's tight bounding box
becomes a brick when the cells fill it completely, otherwise it is split in
two along its longest side and both halves are treated the same way (all
groups of a level at once per round, vectorised). A brick's *domain* is its
bounds grown by half a cell width: the region where its cells' tent supports
reach.
"""

from __future__ import annotations

import weakref

import numpy as np

from ..data.blocks import BlockVolume
from ..progress import progress
from ..reconstruction import DEFAULT_METHOD, Reconstruction


class Bricks:
    """The bricks of an AMR data set.

    Attributes (numpy, finest-level units)
    --------------------------------------
    volume : BlockVolume   the data; bricks index its ``values`` in place
    lo : int64 (B, 3)      lower corner of each brick
    dims : int64 (B, 3)    cells per axis
    level : int32 (B,)     cell level
    offset : int64 (B,)    index of the brick's lower corner cell in ``values``
    vmin, vmax : float32 (B,)  value range of the brick's own cells
    stride : (1, B, B^2)   steps in ``values`` along x, y, z inside a brick
    """

    @property
    def volume(self) -> BlockVolume:
        """The blocks whose cells these bricks group."""
        volume = self._volume()
        if volume is None:
            raise RuntimeError("amr: the data of these bricks no longer exist")
        return volume

    def __init__(self, data: BlockVolume, max_width: int = 8):
        if max_width < 1:
            raise ValueError(f"max_width must be >= 1, got {max_width}")
        # bricks are cached per data object (`mi_amr.structures.cache`), so they
        # hold the data they were given weakly: a strong reference from the
        # cache entry would keep its own key alive.
        self._volume = weakref.ref(data)
        data = self.volume
        B = data.block
        self.stride = (1, B, B * B)
        los, dims, levels, offsets, vmins, vmaxs = [], [], [], [], [], []
        with progress(len(data), "bricks") as bar:
            for L in np.unique(data.level):
                sel = np.nonzero(data.level == L)[0]
                for lo, dm, off, vmin, vmax in _bricks_of_blocks(data, sel, min(int(max_width), B)):
                    los.append(lo << np.int64(L))
                    dims.append(dm)
                    levels.append(np.full(len(lo), L, dtype=np.int32))
                    offsets.append(off)
                    vmins.append(vmin)
                    vmaxs.append(vmax)
                    bar.update(int(dm.prod(axis=1).sum()))
        self.lo = np.concatenate(los) + data.origin
        self.dims = np.concatenate(dims)
        self.level = np.concatenate(levels)
        self.offset = np.concatenate(offsets)
        self.vmin = np.concatenate(vmins).astype(np.float32)
        self.vmax = np.concatenate(vmaxs).astype(np.float32)

    def __len__(self):
        return len(self.level)

    @property
    def values(self) -> np.ndarray:
        """The volume's cell values, which the bricks index (see ``offset``)."""
        return self.volume.values

    @property
    def width(self) -> np.ndarray:
        return np.int64(1) << self.level.astype(np.int64)

    @property
    def hi(self) -> np.ndarray:
        return self.lo + self.dims * self.width[:, None]

    def domains(self, method: Reconstruction = DEFAULT_METHOD) -> tuple[np.ndarray, np.ndarray]:
        """Extended domains: the union of the supports of each brick's cells
        under the reconstruction ``method`` (float64, finest units; tent's,
        ``[lo - w/2, hi + w/2]``, by default)."""
        m = method
        w = self.width[:, None].astype(np.float64)
        lo, _ = m.support_box(self.lo.astype(np.float64), w)
        _, hi = m.support_box(self.hi.astype(np.float64) - w, w)
        return lo, hi

    def cell_index(self, b, x, y, z):
        """Index in ``values`` of cell ``(x, y, z)`` (brick-local) of brick ``b``."""
        return np.take(self.offset, b) + x + self.stride[1] * y + self.stride[2] * z

    @property
    def nbytes(self) -> int:
        """Brick headers only: the values are the volume's."""
        return len(self) * (3 * 8 + 3 * 8 + 4 + 8 + 4 + 4)


def _bricks_of_blocks(data: BlockVolume, sel: np.ndarray, m: int):
    """Bricks of the blocks ``sel`` (one level), at most ``m`` cells per side:
    yields ``(lo, dims, offset, vmin, vmax)`` with ``lo`` in level coordinates
    relative to the volume's origin. Full blocks that ``m`` divides are cut
    evenly, with no per-cell work but their min/max."""
    B, b3 = data.block, data.block ** 3
    v = data.values.reshape(-1, b3)[sel]
    q0 = data.coord[sel].astype(np.int64) << data.log2_block          # block corners, level coordinates
    full = ~np.isnan(v).any(axis=1) if B % m == 0 else np.zeros(len(sel), bool)
    if full.any():
        n = B // m
        vf = v[full].reshape(-1, n, m, n, m, n, m)                     # [block, bz, z, by, y, bx, x]
        sub = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"),
                       -1).reshape(-1, 3)[:, ::-1] * m                  # (bz, by, bx) order -> x, y, z
        lo = (q0[full][:, None, :] + sub[None]).reshape(-1, 3)
        local = sub[:, 0] + B * (sub[:, 1] + B * sub[:, 2])
        off = (sel[full].astype(np.int64)[:, None] * b3 + local[None]).reshape(-1)
        yield (lo, np.full((len(lo), 3), m, np.int64), off,
               vf.min(axis=(2, 4, 6)).reshape(-1), vf.max(axis=(2, 4, 6)).reshape(-1))
    rest = np.nonzero(~full)[0]
    if len(rest):
        bi, ci = np.nonzero(~np.isnan(v[rest]))
        local = np.stack([ci % B, (ci // B) % B, ci // (B * B)], axis=1)
        groups_per_axis = -(-B // m)
        g = local // m
        group = rest[bi].astype(np.int64) * groups_per_axis ** 3 + g[:, 0] + groups_per_axis * (
            g[:, 1] + groups_per_axis * g[:, 2])
        lo, dims, order, starts = _complete_boxes(local, group)
        blk = rest[bi[order[starts]]]
        off = sel[blk].astype(np.int64) * b3 + lo[:, 0] + B * (lo[:, 1] + B * lo[:, 2])
        vals = v[rest][bi[order], ci[order]]
        yield (q0[blk] + lo, dims, off, np.minimum.reduceat(vals, starts), np.maximum.reduceat(vals, starts))


def _complete_boxes(q: np.ndarray, group: np.ndarray):
    """Split cells (coordinates ``q`` (m, 3), int) into complete boxes, each
    inside one ``group``. Returns ``(lower corners, dims, member order,
    starts)``: the cell indices brick after brick (x fastest within each)
    and where each brick's run starts in that order."""
    _, node = np.unique(group, return_inverse=True)
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
    dims = np.concatenate(out_dims)
    counts = dims.prod(axis=1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return np.concatenate(out_lo), dims, np.concatenate(out_members), starts
