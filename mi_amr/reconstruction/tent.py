"""``tent`` (the default): normalised tent weights, continuous across levels.

``phi_i(x) = prod_k max(0, 1 - |x_k - c_ik| / w_i)`` and ``f(x) = sum_i
phi_i(x) v_i / sum_i phi_i(x)``; no value where ``sum phi <= WEIGHT_EPS``
(docs/design.md section 3). Inside a same-level region this is trilinear
interpolation of the 2x2x2 *stencil* of cells around ``x``; at a level or
data boundary the weights of missing cells are dropped and the rest
renormalised. A cell's support is ``[c - w, c + w]`` (``r = 1``): it reaches
half a cell past its box, into neighbouring cells and bricks. The field is
continuous, so inside a (connected) macrocell it takes every value between
its minimum and maximum there: value masks do not tighten its majorants
(docs/design.md section 4).

Hash: every level in the macrocell's level mask can contribute, so each is
visited (in any order; finest first here). Each loop iteration probes one
block of the level's stencil ``b + {0,1}^3``, ``b = floor(x / 2**L - 1/2)``,
and takes every corner in that block; ghost blocks and neighbour rows
(`mi_amr.data.blocks.BlockVolume.stencil_index`) make that one probe per
stencil where ``b`` is in the data.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..core.block_keys import UPPER_OFFSETS
from .base import WEIGHT_EPS, Reconstruction

#: Stencil corner c = dx + 2 dy + 4 dz.
CORNERS = [(c & 1, (c >> 1) & 1, (c >> 2) & 1) for c in range(8)]


class Tent(Reconstruction):
    name = "tent"
    support_radius = 1.0
    needs_ghosts = True
    value_masks_tighten = False
    hash_bytes_per_block = 600.0
    grid_filter = "trilinear"
    dense_exact = False                # on single-level data with opacity linear in value only

    # ---- Host ----------------------------------------------------------
    def brute_force_chunk(self, lo, w, value, x):
        c = lo + 0.5 * w[:, None]
        phi = np.prod(np.maximum(0.0, 1.0 - np.abs(x - c) / w[:, None]), axis=2)
        sw = phi.sum(axis=1)
        found = sw > WEIGHT_EPS
        return np.where(found, (phi * value).sum(axis=1) / np.maximum(sw, 1e-300), 0.0), found

    def host_eval(self, volume, x):
        val = np.zeros(len(x))
        sw = np.zeros(len(x))
        for L in [int(L) for L in volume.levels]:
            w = float(1 << L)
            base = np.floor(x / w - 0.5).astype(np.int64)
            for corner in range(8):
                off = np.array([(corner >> a) & 1 for a in range(3)])
                q = base + off
                phi = np.prod(np.maximum(0.0, 1.0 - np.abs(x / w - (q + 0.5))), axis=1)
                v, hit = volume.lookup(L, q)
                phi = np.where(hit, phi, 0.0)
                sw += phi
                val += phi * v
        found = sw > WEIGHT_EPS
        return np.where(found, val / np.maximum(sw, 1e-300), 0.0), found

    # ---- Value masks: per stencil, the bins from the min to the max of its corners
    def mask_items(self, volume, bins):
        """Where only level L reaches a point, its value is a convex
        combination of the corners of the level-L stencil around it. Kept
        for tests: ``value_masks_tighten`` is false (see the module docstring)."""
        for level, coord, smin, smax, n in stencil_ranges(volume):
            yield level, coord, (lambda a=smin, b=smax, n=n: (bins.bits(a, b), n))

    def mask_item_box(self, q, w):
        # the stencil based at cell q: from the centre of q to the centre of q + 1
        a = (q + 0.5) * w
        # stencils based at -1 (not stored) hold a subset of the corners of those based at 0
        return np.where(q == 0, a - w, a), a + w

    # ---- Device: hash of blocks ----------------------------------------
    def hash_state(self, cells):
        # stencil corners handled at this level, sum of weights, sum of weighted values
        return mi.UInt32(0), mi.Float(0.0), cells.zero()

    def hash_level(self, remaining):
        return dr.tzcnt(remaining)         # every level contributes: any order will do

    def hash_step(self, table, cells, L, xl, fl, limit, probe, state):
        done, sum_w, sum_wv = state
        frac = xl - fl
        # Stencil b + {0,1}^3 with b = floor(xl - 1/2); tent weights
        # (Eq. phi_i, docs/design.md section 3) from t1, the offset
        # of x from corner 0's centre
        upper = frac >= 0.5
        base = fl - dr.select(upper, 0.0, 1.0)
        t1 = dr.select(upper, frac - 0.5, frac + 0.5)
        t0 = 1.0 - t1
        ok_corner = []
        for c, (dx, dy, dz) in enumerate(CORNERS):
            qc = base + mi.Vector3f(dx, dy, dz)
            w = (t1.x if dx else t0.x) * (t1.y if dy else t0.y) * (t1.z if dz else t0.z)
            ok_corner.append(dr.all((qc >= 0.0) & (qc < limit)) & (w > 0.0))
            done = done | dr.select(ok_corner[c], 0, 1 << c)
        need = done != 0xFF
        # Probe the block of the base cell b (a ghost when it has no
        # cell but a neighbour does): its upper neighbours hold every
        # other corner, and no such block means no corner at this
        # level. At the data's lower edge (b < 0) probe the block of
        # the first corner not handled yet and take the corners in it.
        use_base = need & dr.all(base >= 0.0)
        c0 = dr.tzcnt(~done & 0xFF)
        q0 = base + mi.Vector3f(mi.Float(c0 & 1), mi.Float((c0 >> 1) & 1), mi.Float((c0 >> 2) & 1))
        target = dr.select(use_base, base, q0)
        qb = mi.Vector3u(dr.select(need, target, 0.0)) >> table.log2_block
        hit, finished, blk = table.probe_block(qb, L, probe, need)
        base_local = mi.Vector3u(dr.select(use_base, base, 0.0)) & (table.block - 1)
        b3 = table.block ** 3
        for c, (dx, dy, dz) in enumerate(CORNERS):
            qc = base + mi.Vector3f(dx, dy, dz)
            qi = mi.Vector3u(dr.select(ok_corner[c], qc, 0.0))
            open_c = finished & need & ok_corner[c] & ((done & (1 << c)) == 0)
            # from the base block: the neighbour direction of corner c
            d = (dr.select(base_local.x + 1 >= table.block, dx, 0)
                 | dr.select(base_local.y + 1 >= table.block, 2 * dy, 0)
                 | dr.select(base_local.z + 1 >= table.block, 4 * dz, 0))
            via_nb = open_c & use_base & hit & (d != 0)
            blk_c = dr.select(via_nb, dr.gather(mi.UInt32, table.neighbours, blk * 7 + d - 1, via_nb), blk)
            mine = open_c & (use_base | dr.all((qi >> table.log2_block) == qb))
            has = mine & hit & (blk_c < table.n_blocks)      # ghosts and "none" hold no values
            w = (t1.x if dx else t0.x) * (t1.y if dy else t0.y) * (t1.z if dz else t0.z)
            v = cells.gather(blk_c * b3 + table.cell_slot(qi), has)
            use = has & ~dr.isnan(cells.main(v))
            sum_w = sum_w + dr.select(use, w, 0.0)
            sum_wv = sum_wv + dr.select(use, w * v, 0.0)
            done = done | dr.select(mine, 1 << c, 0)
        probe = dr.select(finished, 0, probe + 1)
        level_done = done == 0xFF
        done = dr.select(level_done, 0, done)
        return level_done, probe, (done, sum_w, sum_wv)

    def hash_result(self, state):
        _, sum_w, sum_wv = state
        found = sum_w > WEIGHT_EPS
        return dr.select(found, sum_wv / dr.maximum(sum_w, WEIGHT_EPS), 0.0), found

    # ---- Device: bricks: the brick's stencil cells, summed over bricks ---
    def brick_state(self, cells):
        return mi.Float(0.0), cells.zero()               # sum of weights, of weighted values

    def brick_step(self, bricks, cells, b, x, active, state, over_bounds, in_domain):
        """Trilinear weights of the 2x2x2 cells around ``x`` without those
        outside the brick; ``over_bounds`` does not apply (tent lists hold
        every brick whose domain contains the point)."""
        xb, dims, _, off, _ = bricks.locate(b, x, active)
        xc = xb - 0.5
        base = mi.Vector3i(dr.floor(xc))
        w_b = mi.Float(0.0)
        wv_b = cells.zero()
        for c in range(8):
            i = base + mi.Vector3i(c & 1, (c >> 1) & 1, (c >> 2) & 1)
            ok = active & dr.all((i >= 0) & (i < dims))
            dd = dr.abs(xc - mi.Vector3f(i))
            wt = dr.maximum(0.0, 1.0 - dd.x) * dr.maximum(0.0, 1.0 - dd.y) * dr.maximum(0.0, 1.0 - dd.z)
            ok &= wt > 0.0
            v = cells.gather(bricks.cell_slot(off, i), ok)
            w_b += dr.select(ok, wt, 0.0)
            wv_b += dr.select(ok, wt * v, 0.0)
        sum_w, sum_wv = state
        return sum_w + w_b, sum_wv + wv_b

    def brick_result(self, state):
        sum_w, sum_wv = state
        found = sum_w > WEIGHT_EPS
        return dr.select(found, sum_wv / dr.maximum(sum_w, WEIGHT_EPS), 0.0), found


def stencil_ranges(volume, max_cells: int = 1 << 20):
    """Per chunk of blocks and ghost blocks of a `BlockVolume`: ``(level,
    coord, smin, smax, cells)`` with ``smin``/``smax`` (k, B, B, B) the
    min/max over the present corners of the stencil based at each cell
    ([block, z, y, x]; +inf/-inf where none is present) and ``cells`` the
    present cells of the chunk."""
    ghost_coord, ghost_level, neighbours = volume.stencil_index()
    K, B = len(volume.level), volume.block
    level = np.concatenate([volume.level, ghost_level])
    coord = np.concatenate([volume.coord.astype(np.int64), ghost_coord.astype(np.int64)])
    values = volume.values.reshape(K, B, B, B)
    step = max(1, max_cells // B ** 3)
    for s in range(0, len(level), step):
        ids = np.arange(s, min(s + step, len(level)))
        ext = np.full((len(ids), B + 1, B + 1, B + 1), np.nan, dtype=np.float32)    # [block, z, y, x]
        own = ids < K
        ext[own, :B, :B, :B] = values[ids[own]]
        for d, off in enumerate(UPPER_OFFSETS):
            nb = neighbours[ids, d].astype(np.int64)
            has = nb < K                                  # a block with values (ghosts have none)
            if not has.any():
                continue
            # the slab of the neighbour that the extended block takes: index 0
            # along each axis where the offset is 1, everything where it is 0
            src = tuple(slice(0, 1) if o else slice(0, B) for o in off[::-1])
            dst = tuple(slice(B, B + 1) if o else slice(0, B) for o in off[::-1])
            ext[(np.nonzero(has)[0],) + dst] = values[nb[has]][(slice(None),) + src]
        lo = np.where(np.isnan(ext), np.inf, ext)
        hi = np.where(np.isnan(ext), -np.inf, ext)
        smin = np.full((len(ids), B, B, B), np.inf, np.float32)
        smax = np.full((len(ids), B, B, B), -np.inf, np.float32)
        for c in range(8):
            dz, dy, dx = (c >> 2) & 1, (c >> 1) & 1, c & 1
            np.minimum(smin, lo[:, dz:dz + B, dy:dy + B, dx:dx + B], out=smin)
            np.maximum(smax, hi[:, dz:dz + B, dy:dy + B, dx:dx + B], out=smax)
        yield level[ids], coord[ids], smin, smax, int(np.count_nonzero(~np.isnan(ext[own, :B, :B, :B])))
