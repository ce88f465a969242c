"""Oracles for tests: brute-force reconstruction and image statistics.

Slow by design (O(cells) per point, many render passes); never used while
rendering.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .data.cells import AMRCells
from .reconstruction import Reconstruction, reconstruction_method


def brute_force(cells: AMRCells, x, method: str | Reconstruction = "tent", chunk: int = 256):
    """Reconstruct at points ``x`` (M, 3), absolute finest units, by looping
    over all cells (vectorised; `Reconstruction.brute_force_chunk`).
    Returns ``(value, found)``."""
    method = reconstruction_method(method)
    x = np.asarray(x, dtype=np.float64)
    w = cells.width.astype(np.float64)
    lo = cells.pos.astype(np.float64)
    val = np.zeros(len(x))
    found = np.zeros(len(x), dtype=bool)
    for s in range(0, len(x), chunk):
        val[s:s + chunk], found[s:s + chunk] = method.brute_force_chunk(lo, w, cells.values, x[s:s + chunk, None, :])
    return val, found


def render_passes(scene, passes: int, spp: int, seed0: int = 0, sensor=0, frozen: bool = True) -> np.ndarray:
    """``passes`` independent renders (seeds ``seed0 ..``), shape (P, H, W, C).

    ``frozen``: the passes replay one ``dr.freeze`` recording of
    ``mi.render`` with each seed (the same images; tracing the integrator
    again is most of a small pass's time). A scene that cannot be recorded
    (Dr.Jit refuses some of Mitsuba's own plugins, and the spectral
    variants' colour upsampling) renders its passes plainly."""
    seeds = [seed0 + i for i in range(passes)]
    if frozen:
        record = dr.freeze(lambda scene, spp, seed, sensor: mi.render(scene, spp=spp, seed=seed, sensor=sensor))
        try:
            first = np.array(record(scene, spp=spp, seed=dr.opaque(mi.UInt32, seeds[0]), sensor=sensor), np.float64)
        except RuntimeError as e:
            if "frozen function" not in str(e):
                raise
        else:
            rest = [np.array(record(scene, spp=spp, seed=dr.opaque(mi.UInt32, s), sensor=sensor), np.float64)
                    for s in seeds[1:]]
            return np.stack([first] + rest)
    return np.stack([np.array(mi.render(scene, spp=spp, seed=s, sensor=sensor), np.float64) for s in seeds])


def block_z_scores(passes_a: np.ndarray, passes_b: np.ndarray, block: int = 8,
                   rel_floor: float = 1e-5) -> np.ndarray:
    """z-scores of the difference of per-block image means of two estimators.

    Each input holds independent passes (P, H, W, C). Per block (``block``
    pixels square, channels averaged) the mean over passes and its standard
    error (sample std / sqrt(P)) are formed; the result is
    ``(mean_a - mean_b) / sqrt(se_a^2 + se_b^2 + (rel_floor * mean)^2)``
    per block. The floor stands for float32 rounding: an estimator with zero
    variance (a block that sees only the background) still carries rounding
    noise of order 1e-7 relative per path vertex.
    """
    def block_means(p):
        P, H, W = p.shape[:3]
        hb, wb = H // block, W // block
        q = p[:, :hb * block, :wb * block].reshape(P, hb, block, wb, block, -1)
        return q.mean(axis=(2, 4, 5))

    ma, mb = block_means(passes_a), block_means(passes_b)
    mean_a, mean_b = ma.mean(axis=0), mb.mean(axis=0)
    se2 = ma.var(axis=0, ddof=1) / len(ma) + mb.var(axis=0, ddof=1) / len(mb)
    se2 = se2 + (rel_floor * 0.5 * (np.abs(mean_a) + np.abs(mean_b))) ** 2
    diff = mean_a - mean_b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(se2 > 0, diff / np.sqrt(se2), np.where(diff == 0, 0.0, np.inf))
