"""Per-macrocell value masks: which of 64 value bins the field can take there.

A macrocell's value range ``[vmin, vmax]`` bounds every reconstructed value in
it, but it is the hull of many cells: a TF peak between two cell values
raises the majorant although no point of the macrocell takes a value near the
peak. The mask keeps one bit per value bin that the reconstruction can reach
inside the macrocell (docs/design.md section 4); what an item is and which
bins it holds is the reconstruction method's (`Reconstruction.mask_items`):

* ``nearest``: the bin of every cell whose box overlaps the macrocell (the
  field takes only cell values);
* ``tent``: for every level-L *stencil* (the 2x2x2 cells of level L around a
  point, box from the centre of its base cell to the centre of the opposite
  corner) the bins from the min to the max of its present corners, over the
  stencils whose box overlaps the macrocell. Where only level L reaches a
  point, its value is a convex combination of that stencil's corners. Where
  cells of several levels reach one macrocell (more than one bit in its
  ``level_bits``), values of different levels mix and the mask is not used
  there: the range alone gives the majorant.

The bins are uniform in value over the data's ``[min, max]`` and fixed at
build time, so a TF or TF-domain change only recomputes 64 per-bin maxima
(`mi_amr.device.grid.DeviceMacrocellGrid.update_majorants`) and one table
look-up per mask byte.
"""

from __future__ import annotations

import threading

import numpy as np

from ..data.blocks import BlockVolume
from ..parallel import ordered_map
from ..progress import progress
from ..reconstruction import Reconstruction
from .block_windows import block_windows
from .cache import HOST_CACHE

N_BINS = 64
ALL_BITS = np.uint64(0xFFFFFFFFFFFFFFFF)


class ValueBins:
    """``N_BINS`` bins uniform in value over ``[lo, hi]`` (the data's range);
    values outside clamp to the end bins."""

    def __init__(self, lo: float, hi: float):
        self.lo, self.hi = float(lo), float(hi)
        self.width = (self.hi - self.lo) / N_BINS if self.hi > self.lo else 1.0

    @classmethod
    def of(cls, volume: BlockVolume) -> "ValueBins":
        """The bins of a data set (made once per data object: `HOST_CACHE`)."""
        return HOST_CACHE.get(volume, "value_bins", lambda: cls(*volume.value_range))

    def index(self, v) -> np.ndarray:
        """Bin of each finite value ``v`` (int64)."""
        return np.clip(np.floor((np.asarray(v, np.float64) - self.lo) / self.width), 0, N_BINS - 1).astype(np.int64)

    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper value of each bin as float32, widened by one ulp
        so that every float32 value of a bin lies inside its edges."""
        k = np.arange(N_BINS, dtype=np.float64)
        lo = np.nextafter((self.lo + k * self.width).astype(np.float32), np.float32(-np.inf))
        hi = np.nextafter((self.lo + (k + 1) * self.width).astype(np.float32), np.float32(np.inf))
        lo[0] = min(lo[0], np.nextafter(np.float32(self.lo), np.float32(-np.inf)))
        hi[-1] = max(hi[-1], np.nextafter(np.float32(self.hi), np.float32(np.inf)))
        return lo, hi

    def bits(self, vmin, vmax) -> np.ndarray:
        """Mask of the bins from ``vmin``'s to ``vmax``'s (uint64); 0 where
        ``vmin > vmax`` (nothing there)."""
        vmin, vmax = np.asarray(vmin), np.asarray(vmax)
        ok = vmin <= vmax
        b0 = self.index(np.where(ok, vmin, self.lo))
        b1 = self.index(np.where(ok, vmax, self.lo))
        upto = np.where(b1 >= N_BINS - 1, ALL_BITS,
                        (np.uint64(1) << (b1 + 1).astype(np.uint64)) - np.uint64(1))
        below = (np.uint64(1) << b0.astype(np.uint64)) - np.uint64(1)
        return np.where(ok, upto & ~below, np.uint64(0))


def value_masks(volume: BlockVolume, grid, method: Reconstruction,
                bins: ValueBins | None = None) -> np.ndarray:
    """The value mask (uint64) of every macrocell of ``grid`` (a
    `MacrocellGrid`: ``res``, ``lo``, ``extent``), for ``method`` (see the
    module docstring): the bins of the method's items (`Reconstruction.mask_items`,
    read block by block) folded into the macrocells their boxes
    (`Reconstruction.mask_item_box`) overlap."""
    bins = bins or ValueBins.of(volume)
    res = np.asarray(grid.res, dtype=np.int64)
    masks = np.zeros(int(np.prod(res)), dtype=np.uint64)
    scale = res / np.asarray(grid.extent, dtype=np.float64)
    rel = volume.origin - np.asarray(grid.lo, dtype=np.int64)
    B = volume.block

    lock = threading.Lock()

    def fold(item):                                   # in threads; the fold into masks one at a time
        level, coord, work = item
        bits, n = work()
        for L in np.unique(level):
            L = int(L)
            sel = np.nonzero(level == L)[0]
            w = float(1 << L)

            def span(q, axis):
                a, b = method.mask_item_box(q, w)
                a, b = a + rel[axis], (b + rel[axis]) * scale[axis]
                top = res[axis] - 1
                return (np.clip(np.floor(a * scale[axis]), 0, top).astype(np.int64),
                        np.clip(np.floor(b), 0, top).astype(np.int64))
            q0 = coord[sel].astype(np.int64) << volume.log2_block
            idx, (m,), ok = block_windows(q0, B, span, res, [(bits[sel], np.bitwise_or, np.uint64(0))])
            ok &= m != 0
            idx, m = idx[ok], m[ok]
            with lock:
                np.bitwise_or.at(masks, idx, m)
        return n

    with progress(len(volume), f"value masks {'x'.join(str(int(r)) for r in res)}") as bar:
        for n in ordered_map(fold, method.mask_items(volume, bins)):
            bar.update(n)
    return masks


def mask_max_alpha_host(bin_alpha: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Max of ``bin_alpha`` (64,) over the set bits of each mask (0 for an
    empty mask), through one 256-entry table per mask byte."""
    table = byte_tables(bin_alpha)
    out = np.zeros(masks.shape, dtype=np.float32)
    for j in range(8):
        byte = ((masks >> np.uint64(8 * j)) & np.uint64(0xFF)).astype(np.int64)
        np.maximum(out, table[j, byte], out=out)
    return out


def byte_tables(bin_alpha: np.ndarray) -> np.ndarray:
    """(8, 256): entry ``[j, b]`` is the max of ``bin_alpha[8 j + i]`` over
    the bits ``i`` set in ``b`` (0 for ``b = 0``)."""
    bits = (np.arange(256)[:, None] >> np.arange(8)[None]) & 1          # (256, 8)
    a = np.asarray(bin_alpha, np.float32).reshape(8, 1, 8)
    return np.where(bits[None].astype(bool), a, 0.0).max(axis=2).astype(np.float32)
