"""What an ``amr`` medium will take in memory, from its blocks alone.

`medium_bytes` answers before anything is built (``mi-amr info``): the data,
the point-location hash (exact) and the macrocell grid (between the cost
model's coarsest and finest candidates); `mi_amr.memory` holds the per-item
constants and the limit the builds check.
"""

from __future__ import annotations

import numpy as np

from ..core.block_keys import ghost_blocks
from ..memory import hash_bytes
from ..reconstruction import DEFAULT_METHOD, Reconstruction
from .cost_model import _candidates, thinning_candidate
from .level_hash import SLOT_BYTES
from .macrocell_grid import axis_resolution


#: Host bytes per macrocell of the grid an ``amr`` medium keeps: value range
#: (2 x 4 B), level bits (4 B) and majorant (4 B); value masks add 8 B.
GRID_BYTES_PER_MACROCELL = 16
#: Device bytes per macrocell of the finer majorants that thin tentative
#: collisions (`mi_amr.device.grid.DeviceThinningGrid`): value range (2 x 4
#: B), value mask (8 B) and majorant (4 B).
THINNING_BYTES_PER_MACROCELL = 20


def thinning_bytes_per_macrocell(masks: bool) -> int:
    """`THINNING_BYTES_PER_MACROCELL`, less the value mask where the grid
    has none."""
    return THINNING_BYTES_PER_MACROCELL - (0 if masks else 8)


def medium_bytes(volume, method: Reconstruction = DEFAULT_METHOD) -> dict:
    """Host bytes of an ``amr`` medium with the default structures (traversal
    ``grid``, sampling ``hash``) over ``volume`` (a `BlockVolume`), from its
    blocks: ``data`` (`BlockVolume.nbytes`), ``hash`` (the point-location
    tables, sized as `mi_amr.structures.level_hash.LevelHash` sizes them, with
    the ghost blocks and neighbour rows of ``tent``: exact), ``grid``: ``[low,
    high]``, the macrocell grid at the coarsest and the finest resolution
    the medium's cost model weighs (``grid_resolution``, macrocells per axis;
    which it keeps depends on the TF and the density scale: an estimate),
    ``thinning``: the finer majorants built where the kept grid is coarser
    (``thinning_resolution``; 0 bytes where none can be), their ``total``
    (``[low, high]``: the coarsest grid without thinning, the finest with
    it) and ``build_peak``: the peak the medium checks against the memory
    limit before building the hash (`hash_bytes` plus the values). On the CUDA backend the values and structures are
    copied to the GPU as well."""
    coord, level = volume.coord.astype(np.int64), np.asarray(volume.level)
    neighbour_bytes = 4
    if method.needs_ghosts:
        ghost_coord, ghost_level = ghost_blocks(volume.coord, volume.level)
        coord = np.concatenate([coord, np.asarray(ghost_coord, np.int64).reshape(-1, 3)])
        level = np.concatenate([level, np.asarray(ghost_level)])
        neighbour_bytes = 4 * 7 * len(level)
    # per level a table of a power of two >= 16 slots at load factor <= 0.35 (LevelHash)
    slots = sum(1 << max(4, int(np.ceil(np.log2(n / 0.35)))) for n in np.unique(level, return_counts=True)[1])
    hash_ = slots * SLOT_BYTES + neighbour_bytes
    lo, hi = volume.bounds
    ext = (hi - lo).astype(np.float64)
    per = GRID_BYTES_PER_MACROCELL + 8 * method.value_masks_tighten
    cands = _candidates(volume)
    grid = [per * int(np.prod(axis_resolution(c, ext))) for c in (cands[0], cands[-1])]
    thin_res = thinning_candidate(volume)
    thinning = thinning_bytes_per_macrocell(method.value_masks_tighten) \
        * int(np.prod(axis_resolution(thin_res, ext))) if thin_res else 0
    data = int(volume.nbytes)
    return {"data": data, "hash": int(hash_), "grid": grid, "grid_resolution": [int(cands[0]), int(cands[-1])],
            "thinning": int(thinning), "thinning_resolution": int(thin_res),
            "total": [int(data + hash_ + grid[0]), int(data + hash_ + grid[1] + thinning)],
            "build_peak": int(hash_bytes(len(volume.level), method) + volume.values.nbytes),
            "reconstruction": method.name}
