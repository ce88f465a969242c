"""``nearest``: the value of the finest cell whose box contains ``x``.

Piecewise constant; no value where no cell contains ``x`` (docs/design.md
section 3). A cell's support is its own box (``r = 1/2``), so it reaches no
other cell or brick, and the field takes only cell values: value masks of
the cells' bins tighten the majorants. Resampled at the voxel centres of a
finest-resolution dense grid it is exactly ``gridvolume`` with
``filter_type="nearest"``.

Hash: levels are probed coarsest first and the loop stops at the first
cell present. Leaf cells do not overlap, so the order does not change the
cell found; look-ups fall uniformly in the volume of a macrocell, most of
which coarse cells fill, so coarsest first probes fewer levels per look-up
than finest first (measured in docs/performance/frame-cost.md section 7).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .base import Reconstruction


class Nearest(Reconstruction):
    name = "nearest"
    support_radius = 0.5
    needs_ghosts = False
    value_masks_tighten = True
    hash_bytes_per_block = 250.0
    grid_filter = "nearest"
    dense_exact = True

    # ---- Host ----------------------------------------------------------
    def brute_force_chunk(self, lo, w, value, x):
        inside = np.all((x >= lo) & (x < lo + w[:, None]), axis=2)
        # finest containing cell: smallest width among those that contain x
        wm = np.where(inside, w, np.inf)
        j = np.argmin(wm, axis=1)
        hit = inside[np.arange(len(j)), j]
        return np.where(hit, value[j], 0.0), hit

    def host_eval(self, volume, x):
        val = np.zeros(len(x))
        found = np.zeros(len(x), dtype=bool)
        for L in [int(L) for L in volume.levels]:           # finest first
            q = np.floor(x / (1 << L)).astype(np.int64)
            v, hit = volume.lookup(L, q)
            new = hit & ~found
            val[new] = v[new]
            found |= hit
        return val, found

    # ---- Value masks: the bin of every cell, over its box ----------------
    def mask_items(self, volume, bins):
        def work(values):
            present = ~np.isnan(values)
            bit = np.uint64(1) << bins.index(np.where(present, values, bins.lo)).astype(np.uint64)
            return np.where(present, bit, np.uint64(0)), int(np.count_nonzero(present))
        for level, coord, values in volume.block_chunks():
            yield level, coord, (lambda v=values: work(v))

    def mask_item_box(self, q, w):
        return self.support_box(q * w, w)                # the cell's box

    # ---- Device: hash of blocks ----------------------------------------
    def hash_state(self, cells):
        return mi.Bool(False), cells.zero()              # found, value

    def hash_level(self, remaining):
        return 31 - dr.lzcnt(remaining)                  # coarsest first: see the module docstring

    def hash_step(self, table, cells, L, xl, fl, limit, probe, state):
        found, value = state
        in_range = dr.all((fl >= 0.0) & (fl < limit))
        qi = mi.Vector3u(dr.select(in_range, fl, 0.0))
        hit, level_done, blk = table.probe_block(qi >> table.log2_block, L, probe, in_range)
        v = cells.gather(blk * table.block ** 3 + table.cell_slot(qi), hit)
        present = hit & ~dr.isnan(cells.main(v))
        found = found | present
        value = dr.select(present, v, value)
        probe = dr.select(level_done, 0, probe + 1)
        return level_done, probe, (found, value)

    def hash_stop(self, remaining, state):
        return dr.select(state[0], 0, remaining)         # the first cell found is the finest

    def hash_result(self, state):
        found, value = state
        return dr.select(found, value, 0.0), found

    # ---- Device: bricks: the finest brick that contains the point --------
    def brick_state(self, cells):
        return mi.Float(dr.inf), cells.zero()            # cell width of the best brick, its value

    def brick_step(self, bricks, cells, b, x, active, state, over_bounds, in_domain):
        best_w, value = state
        xb, dims, w, off, inside = bricks.locate(b, x, active)
        # the nearest cell of the brick (clamped into it); ``inside`` says whether it contains x
        i = dr.clip(mi.Vector3i(dr.floor(xb)), 0, dims - 1)
        v = cells.gather(bricks.cell_slot(off, i), active)
        if over_bounds:                    # the leaf lies in its brick
            inside = active & in_domain
        finer = inside & (w < best_w)      # finest containing brick wins
        return dr.select(finer, w, best_w), dr.select(finer, v, value)

    def brick_result(self, state):
        best_w, value = state
        found = best_w < dr.inf
        return dr.select(found, value, 0.0), found
