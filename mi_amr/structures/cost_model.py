"""Cost model that picks the macrocell grid resolution for the data and the TF.

See `auto_resolution`. Lengths are in the medium's local space (the data
bounds are the unit cube); majorants in inverse world units.
"""

from __future__ import annotations

import numpy as np

from ..data.cells import AMRCells
from ..transfer.function import range_majorants_host
from .macrocell_grid import MacrocellGrid
from .value_masks import mask_max_alpha_host


#: Cost of one DDA step relative to one density look-up (tent/nearest hash
#: sampling on llvm_ad_rgb), used by `auto_resolution`; calibrated with the
#: grid-resolution sweep of ``python -m mi_amr.bench``.
STEP_COST = 0.08
CANDIDATES = (8, 16, 32, 64, 128)


def auto_resolution(cells: AMRCells, tf, density_scale: float, world_scale: float = 1.0,
                    support: str = "tent", candidates=CANDIDATES, grids: dict | None = None,
                    masks: bool = False):
    """Grid resolution (longest axis) minimising the expected tracking cost
    per unit of ray length in the unit cube:

        cost(R) = STEP_COST * 1.5 R  +  (E[mu_bar] + E[mu_bar^2] / E[mu_bar]) / 2

    (a ray crosses about 1.5 R macrocells per unit length; delta/ratio
    tracking takes ``mu_bar`` tentative collisions per unit length, each a
    density look-up). Half the rays are taken as uniform through the volume
    (camera rays: the plain mean over macrocells), half as starting where
    collisions happen (scattered and shadow rays: the mean weighted by
    ``mu_bar``). ``world_scale`` converts local to world length. The
    value ranges are splatted once at the finest candidate and max/min-pooled
    by powers of two for the coarser ones. Returns ``(best, {R: cost})``;
    ``grids``, when given, receives the finest grid (``grids[R] = grid``),
    from which `MacrocellGrid.pooled` makes the chosen one. With ``masks``
    the grids carry value masks and the majorants use them."""
    lo, hi = cells.bounds
    ext = int((hi - lo).max())
    cands = sorted(c for c in candidates if c <= max(ext, min(candidates)))
    finest = cands[-1]
    g = MacrocellGrid(cells, finest, support=support, masks=masks)
    if grids is not None:
        grids[finest] = g
    r = g.res
    shape = (r[2], r[1], r[0])
    vmin, vmax = g.vmin.reshape(shape), g.vmax.reshape(shape)
    if masks:
        bin_alpha = range_majorants_host(tf, *g.bins.edges(), 1.0)
        mask = g.masks.reshape(shape)
    costs = {}
    for c in reversed(cands):
        f = max(1, finest // c)
        pmin, pmax = _pool(vmin, f, np.minimum, np.inf), _pool(vmax, f, np.maximum, -np.inf)
        mu = range_majorants_host(tf, pmin.ravel(), pmax.ravel(), density_scale)
        if masks:
            pmask = _pool(mask, f, np.bitwise_or, np.uint64(0)).ravel()
            mu = np.minimum(mu, density_scale * mask_max_alpha_host(bin_alpha, pmask))
        mu = mu.astype(np.float64) * world_scale
        m1 = float(mu.mean())
        m2 = float((mu * mu).mean()) / m1 if m1 > 0 else 0.0
        costs[c] = STEP_COST * 1.5 * c + 0.5 * (m1 + m2)
    best = min(costs, key=costs.get)
    return best, costs


def _pool(a: np.ndarray, f: int, op, fill) -> np.ndarray:
    """Reduce blocks of f^3 cells (padding with ``fill``)."""
    if f == 1:
        return a
    pad = [(0, (-n) % f) for n in a.shape]
    a = np.pad(a, pad, constant_values=fill)
    z, y, x = (n // f for n in a.shape)
    return op.reduce(op.reduce(op.reduce(a.reshape(z, f, y, f, x, f), axis=5), axis=3), axis=1)
