"""Dense volume -> AMR by block coarsening.

Any dense scalar volume becomes AMR by merging complete 2x2x2 blocks of
same-level cells whose value spread (max - min over the original voxels they
cover) is at most ``threshold``, repeatedly, up to ``max_level``.
"""

from __future__ import annotations

import numpy as np

from .cells import AMRCells


def dense_to_amr(volume, threshold: float = 0.0, max_level: int = 4,
                 source: str = "dense volume") -> AMRCells:
    """Convert a dense volume indexed ``[z, y, x]`` (x fastest, the layout of
    raw files and of Mitsuba's ``gridvolume``) to `AMRCells`.

    A merged cell's value is the mean of its 8 children. Voxel ``[z, y, x]``
    becomes the level-0 cell at ``pos = (x, y, z)``.
    """
    vol = np.asarray(volume, dtype=np.float32)
    if vol.ndim != 3:
        raise ValueError(f"{source}: expected a 3D volume, got shape {vol.shape}")
    if not np.all(np.isfinite(vol)):
        raise ValueError(f"{source}: contains NaN or Inf values")
    if threshold < 0 or max_level < 0:
        raise ValueError(f"{source}: threshold and max_level must be non-negative")
    vol = vol.transpose(2, 1, 0)  # -> [x, y, z]

    out_pos, out_lvl, out_val = [], [], []
    val, vmin, vmax = vol, vol, vol
    alive = np.ones(vol.shape, dtype=bool)    # cell exists at this level
    level = 0
    for L in range(1, max_level + 1):
        n = tuple(s // 2 for s in val.shape)
        if min(n) == 0:
            break
        crop = tuple(slice(0, 2 * s) for s in n)

        def blocks(a):
            a = a[crop].reshape(n[0], 2, n[1], 2, n[2], 2)
            return a.transpose(0, 2, 4, 1, 3, 5).reshape(*n, 8)

        b_alive = blocks(alive).all(axis=-1)
        b_min = blocks(vmin).min(axis=-1)
        b_max = blocks(vmax).max(axis=-1)
        merge = b_alive & (b_max - b_min <= threshold)
        # Cells of level L-1 not absorbed by a merge are emitted now.
        absorbed = np.zeros_like(alive)
        absorbed[crop] = np.repeat(np.repeat(np.repeat(merge, 2, 0), 2, 1), 2, 2)
        _emit(out_pos, out_lvl, out_val, alive & ~absorbed, val, L - 1)
        val = np.where(merge, blocks(val).mean(axis=-1, dtype=np.float64), 0).astype(np.float32)
        vmin, vmax, alive, level = b_min, b_max, merge, L
    _emit(out_pos, out_lvl, out_val, alive, val, level)
    return AMRCells(np.concatenate(out_pos), np.concatenate(out_lvl),
                    np.concatenate(out_val), source=source, validate=False)


def _emit(out_pos, out_lvl, out_val, mask, val, level):
    idx = np.argwhere(mask)
    out_pos.append(idx.astype(np.int64) << level)
    out_lvl.append(np.full(len(idx), level, dtype=np.int32))
    out_val.append(val[mask])
