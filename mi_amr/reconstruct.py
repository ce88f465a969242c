"""Reconstruction of the scalar field f(x) from AMR cells.

Methods (DESIGN.md section 3), ``x`` in finest-level cell units:

* ``tent`` (default): ``f(x) = sum_i phi_i(x) v_i / sum_i phi_i(x)`` with
  ``phi_i(x) = prod_k max(0, 1 - |x_k - c_ik| / w_i)``; continuous across
  level boundaries, trilinear inside a same-level region. No value where
  ``sum phi <= 1e-20``. Cost: one stencil lookup (8 values) per level that can contribute.
* ``nearest``: the value of the finest cell containing ``x`` (piecewise
  constant). Cost: one hash lookup per level, finest first, stopping at the
  first hit.

Three implementations: `brute_force` (numpy, O(cells) per point, the test
oracle), `HostReconstruction` (numpy over the `CellHash`, used to resample
dense references) and `DeviceReconstruction` (Dr.Jit, used while rendering).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .cell_hash import CellHash, StencilHash, hash_u32, pack_key
from .cells import AMRCells

METHODS = ("tent", "nearest")
WEIGHT_EPS = 1e-20


def check_method(method: str) -> str:
    if method not in METHODS:
        raise ValueError(f"unknown reconstruction {method!r} (choose from {', '.join(METHODS)})")
    return method


# ---- numpy oracle --------------------------------------------------------
def brute_force(cells: AMRCells, x, method: str = "tent", chunk: int = 256):
    """Reconstruct at points ``x`` (M, 3), absolute finest units, by looping
    over all cells (vectorised). Returns ``(value, found)``."""
    check_method(method)
    x = np.asarray(x, dtype=np.float64)
    w = cells.width.astype(np.float64)
    lo = cells.pos.astype(np.float64)
    val = np.zeros(len(x))
    found = np.zeros(len(x), dtype=bool)
    for s in range(0, len(x), chunk):
        xs = x[s:s + chunk, None, :]
        if method == "tent":
            c = lo + 0.5 * w[:, None]
            phi = np.prod(np.maximum(0.0, 1.0 - np.abs(xs - c) / w[:, None]), axis=2)
            sw = phi.sum(axis=1)
            found[s:s + chunk] = sw > WEIGHT_EPS
            val[s:s + chunk] = np.where(sw > WEIGHT_EPS, (phi * cells.value).sum(axis=1) / np.maximum(sw, 1e-300), 0.0)
        else:
            inside = np.all((xs >= lo) & (xs < lo + w[:, None]), axis=2)
            # finest containing cell: smallest width among those that contain x
            wm = np.where(inside, w, np.inf)
            j = np.argmin(wm, axis=1)
            hit = inside[np.arange(len(j)), j]
            found[s:s + chunk] = hit
            val[s:s + chunk] = np.where(hit, cells.value[j], 0.0)
    return val, found


# ---- numpy over the hash -------------------------------------------------
class HostReconstruction:
    """Vectorised numpy reconstruction through a `CellHash`."""

    def __init__(self, cells: AMRCells, cell_hash: CellHash | None = None):
        self.cells = cells
        self.hash = cell_hash or CellHash(cells)

    def __call__(self, x, method: str = "tent"):
        """``(value, found)`` at points ``x`` (M, 3), absolute finest units."""
        check_method(method)
        x = np.asarray(x, dtype=np.float64) - self.hash.origin
        levels = [int(L) for L in self.cells.levels]
        val = np.zeros(len(x))
        found = np.zeros(len(x), dtype=bool)
        if method == "nearest":
            for L in levels:                       # finest first
                q = np.floor(x / (1 << L)).astype(np.int64)
                v, hit = self.hash.lookup(L, q)
                new = hit & ~found
                val[new] = v[new]
                found |= hit
            return val, found
        sw = np.zeros(len(x))
        for L in levels:
            w = float(1 << L)
            base = np.floor(x / w - 0.5).astype(np.int64)
            for corner in range(8):
                off = np.array([(corner >> a) & 1 for a in range(3)])
                q = base + off
                phi = np.prod(np.maximum(0.0, 1.0 - np.abs(x / w - (q + 0.5))), axis=1)
                v, hit = self.hash.lookup(L, q)
                phi = np.where(hit, phi, 0.0)
                sw += phi
                val += phi * v
        found = sw > WEIGHT_EPS
        return np.where(found, val / np.maximum(sw, 1e-300), 0.0), found


# ---- Dr.Jit ----------------------------------------------------------------
class DeviceReconstruction:
    """Per-sample reconstruction in Dr.Jit.

    ``nearest`` probes a `CellHash` level by level, finest first, and stops
    at the first cell that contains ``x``. ``tent`` probes a `StencilHash`
    once per level that can contribute: a hit yields the level's whole
    2x2x2 stencil (8 gathers from contiguous memory), so a sample costs
    about one probe plus 8 gathers per contributing level.
    """

    def __init__(self, cells: AMRCells, method: str):
        self.method = check_method(method)
        self.hash = StencilHash(cells) if method == "tent" else CellHash(cells)
        self.origin = self.hash.origin
        self.keys = mi.UInt64(self.hash.keys)
        self.keys_z = mi.UInt32(self.hash.keys_z)
        self.wide = self.hash.wide
        self.offset = mi.UInt32(self.hash.offset)
        self.mask = mi.UInt32(self.hash.mask)
        self.max_probe = mi.UInt32(self.hash.max_probe)
        if method == "tent":
            self.payload = mi.UInt32(self.hash.payload)
            self.values = mi.Float(self.hash.values)
        else:
            self.payload = mi.Float(self.hash.payload)
            self.values = mi.Float(0.0)
        dr.make_opaque(self.keys, self.keys_z, self.payload, self.values, self.offset, self.mask, self.max_probe)

    @property
    def nbytes(self) -> int:
        return self.hash.nbytes

    @dr.syntax
    def eval(self, x: mi.Vector3f, level_bits: mi.UInt32, active=True):
        """Reconstruct at ``x`` (finest units relative to ``origin``).

        ``level_bits``: the levels that may contribute at ``x`` (from the
        macrocell grid). Returns ``(value, found)``. The loop does one probe
        per iteration and runs at most ``levels x max_probe`` iterations.
        """
        tent = self.method == "tent"
        remaining = dr.select(active, level_bits, 0)
        probe = mi.UInt32(0)
        sum_w = mi.Float(0.0)
        sum_wv = mi.Float(0.0)
        found = mi.Bool(False)
        while dr.hint(remaining != 0, label="amr_reconstruct"):
            # ---- Key of the current level: the stencil base, or the cell ----
            L = dr.tzcnt(remaining)
            # x / 2^L is exact; fractions stay small numbers so that no
            # sub-cell offset is rounded away near 2^24 (float32 spacing 1)
            xl = x * dr.rcp(mi.Float(mi.UInt32(1) << L))
            fl = dr.floor(xl)
            frac = xl - fl
            if dr.hint(tent, mode="scalar"):
                upper = frac >= 0.5
                q = fl + dr.select(upper, 1.0, 0.0)           # stencil key s = b + 1
                t1 = dr.select(upper, frac - 0.5, frac + 0.5)  # offset from corner 0's centre
            else:
                q = fl
            in_range = dr.all((q >= 0.0) & (q < float(self.hash.coord_limit)))
            qi = mi.Vector3u(dr.select(in_range, q, 0.0))

            # ---- One linear-probing step in the level's table ----
            key = pack_key(mi.UInt64(qi.x), mi.UInt64(qi.y), mi.UInt64(qi.z), self.wide)
            h = hash_u32(qi.x, qi.y, qi.z)
            slot = dr.gather(mi.UInt32, self.offset, L) + ((h + probe) & dr.gather(mi.UInt32, self.mask, L))
            k = dr.gather(mi.UInt64, self.keys, slot, in_range)
            hit = in_range & (k == key)
            if dr.hint(self.wide, mode="scalar"):
                hit &= dr.gather(mi.UInt32, self.keys_z, slot, hit) == qi.z
            if dr.hint(tent, mode="scalar"):
                # Tent weights of the 8 stencil cells (Eq. phi_i, DESIGN.md section 3)
                idx = dr.gather(mi.UInt32, self.payload, slot, hit) * 8
                t0 = 1.0 - t1
                for c in range(8):
                    wx = t1.x if c & 1 else t0.x
                    wy = t1.y if (c >> 1) & 1 else t0.y
                    wz = t1.z if (c >> 2) & 1 else t0.z
                    w = wx * wy * wz
                    v = dr.gather(mi.Float, self.values, idx + c, hit & (w > 0.0))
                    ok = hit & (w > 0.0) & ~dr.isnan(v)
                    sum_w += dr.select(ok, w, 0.0)
                    sum_wv += dr.select(ok, w * v, 0.0)
            else:
                v = dr.gather(mi.Float, self.payload, slot, hit)
                sum_wv = dr.select(hit, v, sum_wv)
                found |= hit
            level_done = hit | ~in_range | (k == 0xFFFFFFFFFFFFFFFF) | (probe + 1 >= self.max_probe)

            # ---- Advance: next probe or next level ----
            probe = dr.select(level_done, 0, probe + 1)
            remaining = dr.select(level_done, remaining & (remaining - 1), remaining)
            if dr.hint(not tent, mode="scalar"):
                remaining = dr.select(found, 0, remaining)
        if dr.hint(tent, mode="scalar"):
            found = sum_w > WEIGHT_EPS
            value = dr.select(found, sum_wv / dr.maximum(sum_w, WEIGHT_EPS), 0.0)
        else:
            value = dr.select(found, sum_wv, 0.0)
        return value, found
