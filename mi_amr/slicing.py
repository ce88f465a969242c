"""A slice: the field on an axis-aligned plane through the data, as the
medium reconstructs it (``tent`` or ``nearest``, `mi_amr.reconstruction`),
with the AMR level of the cell under each pixel (yt's ``SlicePlot`` with
``annotate_grids``; docs/manual/viewer.md "Slice").

It reads cells, never the whole volume: each pixel centre is located in the
blocks of each level (a sorted key index per level, built once per
`Slicer`), and the method's own numpy evaluation (`Reconstruction.host_eval`,
the oracle the device samplers are tested against) combines the cells
found. Cost: per pixel a binary search per level (and per stencil corner
for ``tent``).

Image axes follow yt: a slice normal to x shows (y, z), to y (z, x), to z
(x, y); row 0 is the top (the largest vertical coordinate). The plane's
``position`` is a unit-cube coordinate along the axis (0: the data's lower
bound, 1: the upper); `mi_amr.annotations.Placement` turns world or
physical positions into it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .annotations import level_colour
from .core.block_keys import block_keys, slot_index
from .data.blocks import BlockVolume
from .data.transform import log10_values, positive_floor
from .reconstruction import Reconstruction, reconstruction_method

#: Horizontal and vertical data axes of a slice normal to axis 0, 1, 2 (yt's).
IMAGE_AXES = {0: (1, 2), 1: (2, 0), 2: (0, 1)}
#: Most pixels a slice may have.
MAX_PIXELS = 4096 * 4096


def axis_index(axis) -> int:
    """0, 1 or 2 for ``axis`` given as that or as "x", "y", "z"; a
    `ValueError` otherwise."""
    names = {"x": 0, "y": 1, "z": 2}
    if isinstance(axis, str) and axis.lower() in names:
        return names[axis.lower()]
    if isinstance(axis, (int, np.integer)) and not isinstance(axis, bool) and 0 <= int(axis) <= 2:
        return int(axis)
    raise ValueError(f"slice axis: x, y, z or 0, 1, 2, got {axis!r}")


class Slicer:
    """Point location of one field of a `BlockVolume` for slices: per level
    the block keys sorted once. ``values``: the field in block layout
    (default ``volume.values``); ``transform``: applied to the cell values
    read: ``"log10"`` as a medium with ``value_transform="log10"`` holds
    them (`mi_amr.data.transform`: the floor is the field's least positive
    value), a function of an array, or None."""

    def __init__(self, volume: BlockVolume, values: np.ndarray | None = None, transform=None):
        self.volume = volume
        self.values = volume.values if values is None else values
        if transform == "log10":
            floor = positive_floor(self.values, volume.source)
            transform = lambda v: log10_values(np.asarray(v, np.float32), floor)   # noqa: E731
        elif transform in (None, "none"):
            transform = None
        elif not callable(transform):
            raise ValueError(f"slice transform: 'none', 'log10' or a function, got {transform!r}")
        self.transform = transform
        self.levels = volume.levels
        self._index = {}
        for L in self.levels.tolist():
            sel = np.nonzero(volume.level == L)[0]
            keys = block_keys(volume.coord[sel], np.full(len(sel), L), False)
            order = np.argsort(keys)
            self._index[L] = (sel[order], keys[order])

    def lookup(self, level: int, q: np.ndarray):
        """``(value, found)`` of the level-``level`` cells at level
        coordinates ``q`` (int (M, 3), relative to the volume's origin), as
        `BlockVolume.lookup` (what `Reconstruction.host_eval` calls)."""
        q = np.asarray(q, np.int64)
        found = np.zeros(len(q), bool)
        value = np.zeros(len(q), np.float32)
        if level not in self._index:
            return value, found
        blocks, keys = self._index[level]
        ok = np.all(q >= 0, axis=1)
        qk = block_keys(np.where(ok[:, None], q, 0) >> self.volume.log2_block, np.full(len(q), level), False)
        i = np.minimum(np.searchsorted(keys, qk), len(keys) - 1)
        hit = ok & (keys[i] == qk)
        slot = slot_index(blocks[i], np.where(hit[:, None], q, 0), self.volume.block)
        v = self.values[np.where(hit, slot, 0)]
        found = hit & ~np.isnan(v)
        if self.transform is not None and found.any():
            v = np.where(found, self.transform(np.where(found, v, 1.0)), v)
        value[found] = v[found]
        return value, found

    def level_at(self, x: np.ndarray) -> np.ndarray:
        """The level of the cell containing each point ``x`` (M, 3), float
        finest units relative to the origin (-1: none)."""
        out = np.full(len(x), -1, np.int32)
        for L in sorted(self.levels.tolist(), reverse=True):       # finest first: the finest cell wins
            todo = out < 0
            if not todo.any():
                break
            q = np.floor(x[todo] / float(1 << L)).astype(np.int64)
            _, hit = self.lookup(L, q)
            out[np.nonzero(todo)[0][hit]] = L
        return out

    def slice(self, axis, position: float, res=256, method: str | Reconstruction = "tent",
              window=None) -> "Slice":
        """The field on the plane at unit-cube ``position`` along ``axis``,
        ``res`` pixels along the longer side (or ``(width, height)``), over
        the data bounds or ``window`` ``((u0, u1), (v0, v1))`` (unit-cube
        coordinates along the image axes)."""
        a = axis_index(axis)
        if not (np.isfinite(position) and 0.0 <= float(position) <= 1.0):
            raise ValueError(f"slice position: a unit-cube coordinate in [0, 1], got {position}")
        method = reconstruction_method(method)
        vol = self.volume
        h_ax, v_ax = IMAGE_AXES[a]
        lo, hi = (np.asarray(b, np.float64) for b in vol.bounds)
        ext = hi - lo
        (u0, u1), (v0, v1) = window if window is not None else ((0.0, 1.0), (0.0, 1.0))
        if np.ndim(res) == 0:
            r = int(res)
            aspect = (ext[h_ax] * (u1 - u0)) / (ext[v_ax] * (v1 - v0))
            w, h = (r, max(1, round(r / aspect))) if aspect >= 1 else (max(1, round(r * aspect)), r)
        else:
            w, h = (int(s) for s in res)
        if not (1 <= w and 1 <= h and w * h <= MAX_PIXELS):
            raise ValueError(f"slice resolution: 1 to {MAX_PIXELS} pixels, got {w}x{h}")
        uu = u0 + (np.arange(w) + 0.5) / w * (u1 - u0)
        vv = v1 - (np.arange(h) + 0.5) / h * (v1 - v0)            # row 0 at the top
        unit = np.empty((h, w, 3))
        unit[..., a] = float(position)
        unit[..., h_ax] = uu[None, :]
        unit[..., v_ax] = vv[:, None]
        # the plane at the upper bound lies on the last cells' far faces: take those cells
        x = lo + unit.reshape(-1, 3) * ext - vol.origin
        x[:, a] = np.minimum(x[:, a], hi[a] - vol.origin[a] - 1e-9 * ext[a])
        value, found = method.host_eval(self, x)
        level = self.level_at(x)
        value = np.where(found, value, np.nan).reshape(h, w)
        coarsest = int(self.levels.max()) if len(self.levels) else 0
        return Slice(a, float(position), value, level.reshape(h, w), (u0, u1, v0, v1), method.name, coarsest)


@dataclass
class Slice:
    """A slice: ``values`` (H, W) float64 in the field's units as the
    medium holds them (NaN: no value), ``level`` (H, W) int32 (the level
    of the cell under each pixel centre, mi-amr's count: cells ``2**level``
    finest cells wide; -1: none), the ``window`` (u0, u1, v0, v1) it spans
    in unit-cube coordinates of the image axes; ``coarsest``: the data's
    coarsest level."""
    axis: int
    position: float
    values: np.ndarray
    level: np.ndarray
    window: tuple
    method: str
    coarsest: int = 0

    @property
    def refinement(self) -> np.ndarray:
        """(H, W) int32: the level as yt counts it (0 the coarsest; -1: none)."""
        return np.where(self.level >= 0, self.coarsest - self.level, -1).astype(np.int32)

    @property
    def image_axes(self) -> tuple[int, int]:
        return IMAGE_AXES[self.axis]

    def boundaries(self) -> np.ndarray:
        """(H, W) bool: pixels whose level differs from their right or lower neighbour's."""
        lv = self.level
        edge = np.zeros(lv.shape, bool)
        edge[:, :-1] |= lv[:, :-1] != lv[:, 1:]
        edge[:-1, :] |= lv[:-1, :] != lv[1:, :]
        return edge

    def colours(self, tf, background=(0.0, 0.0, 0.0)) -> np.ndarray:
        """(H, W, 3) float in [0, 1]: the TF's colours (``tf``: a
        `TransferFunction` over the values' units) at full opacity;
        ``background`` where there is no value."""
        v = np.nan_to_num(self.values, nan=tf.domain[0])
        rgb = tf(v)[..., :3].astype(np.float64)
        return np.where(np.isnan(self.values)[..., None], np.asarray(background, np.float64), rgb)

    def image(self, tf, boundaries: bool = True) -> np.ndarray:
        """The slice as sRGB uint8 (H, W, 3): `colours` (the TF's colours are
        display colours, taken as sRGB), level boundaries drawn in the
        colour of the finer level there (`mi_amr.annotations.level_colour`
        of its refinement)."""
        rgb = (self.colours(tf) * 255 + 0.5).astype(np.uint8)
        if boundaries:
            edge = self.boundaries()
            r = self.refinement
            finer = np.maximum(np.maximum(r, np.roll(r, -1, axis=1)), np.roll(r, -1, axis=0))
            for k in np.unique(finer[edge]).tolist():
                c = level_colour(k)
                rgb[edge & (finer == k)] = [int(c[i:i + 2], 16) for i in (1, 3, 5)]
        return rgb


def slice_volume(volume: BlockVolume, axis, position: float, res=256, method: str | Reconstruction = "tent",
                 field: str | None = None, transform=None, window=None) -> Slice:
    """One slice of ``volume`` (`Slicer.slice`); ``field``: a further field
    (`BlockVolume.field`), ``transform``: applied to the values read."""
    return Slicer(volume, volume.field(field), transform).slice(axis, position, res, method, window)
