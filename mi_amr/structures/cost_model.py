"""Cost model that picks the macrocell grid for the data and the TF: its
resolution and, where the data are refined in a small part of the domain,
a two-level layout (docs/design.md section 4).

See `auto_grid`. Lengths are in the medium's local space (the data bounds
are the unit cube); majorants in inverse world units unless said otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.blocks import BlockVolume
from ..reconstruction import DEFAULT_METHOD, METHODS, Reconstruction
from ..transfer.function import range_majorants_host
from .macrocell_grid import MacrocellGrid, axis_resolution
from .value_masks import mask_max_alpha_host


#: Cost of one DDA step of the uniform grid relative to one density look-up
#: (hash sampling, llvm_ad_rgb): a fit of ratio-tracking time against steps
#: and look-ups over uniform and two-level grids gave about 11 ns per step and
#: 50 ns per look-up (docs/performance/two-level-grid.md).
STEP_COST = 0.2
#: Cost of one step of the two-level grid (a point location, one or two
#: gathers and a slab exit instead of one DDA increment), same units: about
#: 1.2 DDA steps.
TWO_LEVEL_STEP_COST = 0.24
CANDIDATES = (8, 16, 32, 64, 128)
#: The finer majorants that thin tentative collisions have at most one
#: macrocell per this many cells (`thinning_candidate`): at 20 bytes a
#: macrocell, at most one byte per cell.
THINNING_CELLS_PER_MACROCELL = 20
#: Refinement factors tried for two-level grids (fine macrocells per coarse
#: one along each axis).
REFINEMENTS = (2, 4, 8, 16)
#: Steps per unit length of a ray through macrocells of width 1/R: about 1.5 R.
STEPS_PER_CELL = 1.5


@dataclass(frozen=True)
class GridPlan:
    """A macrocell grid: ``resolution`` macrocells along the longest axis
    (the fine level of a two-level grid) and ``refinement`` fine macrocells
    per coarse one along each axis (1: a uniform grid walked by DDA)."""
    resolution: int
    refinement: int = 1

    @property
    def coarse_resolution(self) -> int:
        return -(-self.resolution // self.refinement)

    def step_costs(self) -> tuple[float, float]:
        """Step cost per unit local length at the coarse and the fine spacing."""
        if self.refinement == 1:
            c = STEP_COST * STEPS_PER_CELL * self.resolution
            return c, c
        c = TWO_LEVEL_STEP_COST * STEPS_PER_CELL * self.resolution
        return c / self.refinement, c


def refine_gain(n, s1, mu_c, keep_step, refine_step, maximum):
    """Look-ups plus steps saved per unit of ray length inside each coarse
    macrocell by walking it through its fine macrocells (> 0: refine).

    ``n``: its fine macrocells inside the domain; ``s1``: the sum of their
    majorants and ``mu_c`` the coarse one (inverse local length);
    ``keep_step``/``refine_step``: step costs per unit length at the coarse
    and the fine spacing. A ray crossing the macrocell takes ``mu_c``
    look-ups per unit length when it is kept and the mean fine majorant
    when it is refined. The rule is local, so it does not depend on where
    the camera looks, only on the data and the TF. Plain arithmetic: the
    same code runs on numpy arrays (at build) and on Dr.Jit arrays (on each
    TF change); ``maximum`` is ``np.maximum`` or ``dr.maximum``."""
    return keep_step + mu_c - refine_step - s1 / maximum(n, 1.0)


def plan_cost(mu: np.ndarray, plan: GridPlan):
    """Expected tracking cost per unit local length of two-level ``plan``
    over its fine majorants ``mu`` ([z, y, x], inverse local length), as in
    `auto_grid`: each coarse macrocell costs ``keep_step + mu_c`` per unit
    length, or ``refine_step`` plus its mean fine majorant where
    `refine_gain` refines it; half the rays weigh the macrocells by volume,
    half by their share of collisions (the sum of their fine majorants).
    Returns ``(cost, refined)``, ``refined`` the refined coarse macrocells
    ([z, y, x])."""
    f = plan.refinement
    keep_step, refine_step = plan.step_costs()
    pad = [(0, (-s) % f) for s in mu.shape]
    inside = np.pad(np.ones(mu.shape, dtype=np.float64), pad)
    mu = np.pad(mu.astype(np.float64), pad)
    z, y, x = (s // f for s in mu.shape)

    def blocks(a, op):
        return op.reduce(op.reduce(op.reduce(a.reshape(z, f, y, f, x, f), axis=5), axis=3), axis=1)
    n, mu_c, s1 = blocks(inside, np.add), blocks(mu, np.maximum), blocks(mu, np.add)
    refined = refine_gain(n, s1, mu_c, keep_step, refine_step, np.maximum) > 0
    per_length = np.where(refined, refine_step + s1 / np.maximum(n, 1.0), keep_step + mu_c)
    total_s1 = float(s1.sum())
    cost = 0.5 * float((n * per_length).sum() / n.sum())
    cost += 0.5 * (float((s1 * per_length).sum()) / total_s1 if total_s1 > 0 else float(keep_step))
    return cost, refined


def auto_grid(cells: BlockVolume, tf, density_scale: float, world_scale: float = 1.0,
              support: Reconstruction = DEFAULT_METHOD, candidates=CANDIDATES, grids: dict | None = None,
              masks: bool = False, refinements=(1,) + REFINEMENTS):
    """The `GridPlan` of least expected tracking cost per unit of ray
    length in the unit cube, and ``{plan: cost}``.

    For a uniform grid of resolution R:

        cost(R) = STEP_COST * 1.5 R  +  (E[mu_bar] + E[mu_bar^2] / E[mu_bar]) / 2

    (a ray crosses about 1.5 R macrocells per unit length; delta/ratio
    tracking takes ``mu_bar`` tentative collisions per unit length, each a
    density look-up). Half the rays are taken as uniform through the volume
    (camera rays: the plain mean over macrocells), half as starting where
    collisions happen (scattered and shadow rays: the mean weighted by
    ``mu_bar``). A two-level plan keeps the best uniform grid R* as its
    coarse level and has fine macrocells f times smaller (f R* a candidate),
    priced by `plan_cost`. Refinement is decided per coarse
    macrocell by the look-ups and steps per unit length inside it, so it
    does not depend on how much of the domain is empty: a small refined
    object in a large coarse domain (where the view, unknown here, usually
    is) gets fine macrocells; and where nothing is refined the walk is as
    coarse as R*. ``refinements``: the factors allowed (``(1,)``: uniform
    grids only; one factor f > 1: that one, with the finest candidate as
    the fine level if f R* is not a candidate).

    ``world_scale`` converts local to world length; ``support``: the
    reconstruction method whose supports the value ranges
    cover (`MacrocellGrid`). The value ranges are
    splatted once at the finest candidate and pooled by powers of two for
    the coarser ones; ``grids``, when given, receives the finest grid
    (``grids[R] = grid``), from which `MacrocellGrid.pooled` makes the
    chosen one. With ``masks`` the grids carry value masks and the
    majorants use them."""
    cands = _candidates(cells, candidates)
    finest = cands[-1]
    g = MacrocellGrid(cells, finest, support=support, masks=masks)
    if grids is not None:
        grids[finest] = g
    r = g.res
    shape = (r[2], r[1], r[0])
    vmin, vmax = g.vmin.reshape(shape), g.vmax.reshape(shape)
    if constant_field(cells, g):
        # one value everywhere: the look-up term is the same at every
        # resolution (and with minorants equal to the majorants there are no
        # look-ups at all), so the fewest steps win: one macrocell
        cands = [1] + cands
    if masks:
        bin_alpha = range_majorants_host(tf, *g.bins.edges(), 1.0)
        mask = g.masks.reshape(shape)
    mus = {}
    # each candidate pooled from the next finer one where its factor divides
    # (min, max and or are associative and the padding is their identity:
    # the same arrays as pooled from the finest, in a fraction of the time)
    pooled = {1: (vmin, vmax, mask if masks else None)}
    for c in sorted(cands, reverse=True):
        f = max(1, finest // c)
        base = min((k for k in pooled if f % k == 0), key=lambda k: f // k)
        pmin, pmax, pm = pooled[base]
        pmin, pmax = _pool(pmin, f // base, np.minimum, np.inf), _pool(pmax, f // base, np.maximum, -np.inf)
        if masks:
            pm = _pool(pm, f // base, np.bitwise_or, np.uint64(0))
        pooled[f] = (pmin, pmax, pm)
        mu = range_majorants_host(tf, pmin.ravel(), pmax.ravel(), density_scale)
        if masks:
            mu = np.minimum(mu, density_scale * mask_max_alpha_host(bin_alpha, pm.ravel()))
        mus[c] = (mu.astype(np.float64) * world_scale).reshape(pmin.shape)
    costs = {GridPlan(c): _uniform_cost(mus[c], c) for c in cands}
    uniform = min(costs, key=lambda p: (costs[p], p.resolution))
    forced = len(refinements) == 1 and refinements[0] > 1
    for k in refinements:
        if k == 1:
            continue
        fine = uniform.resolution * k
        if fine not in mus:
            if not forced:
                continue
            fine = finest                    # a forced factor: the finest level, coarse = finest / k
        plan = GridPlan(fine, k)
        cost, refined = plan_cost(mus[fine], plan)
        if refined.any() or forced:          # else it is the uniform grid R*, with dearer steps
            costs[plan] = cost
    allowed = [p for p in costs if p.refinement in refinements]
    best = min(allowed, key=lambda p: (costs[p], p.refinement, p.resolution))
    return best, costs


def constant_field(cells: BlockVolume, grid: MacrocellGrid) -> bool:
    """Whether ``cells`` hold one value and fill their bounding box (so every
    point has that value): sigma_t is then the same everywhere for any TF and
    density scale, and one macrocell is the best grid for all of them
    (a uniform field, the cheapest AMR there is: docs/performance/modes.md)."""
    lo, hi = float(np.min(grid.vmin)), float(np.max(grid.vmax))
    return bool(cells.covers_bounds) and np.isfinite(lo) and lo == hi


def thinning_candidate(cells: BlockVolume) -> int:
    """The resolution (longest axis) of the finer majorants that thin the
    walks' tentative collisions (docs/design.md section 5d), for a medium
    whose walked grid is coarser: the finest that `auto_grid` weighs with
    at most one macrocell per `THINNING_CELLS_PER_MACROCELL` cells (finer
    majorants than the data's own structure thin little more, and cost
    memory); 0 where none is."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    fit = [c for c in _candidates(cells)
           if THINNING_CELLS_PER_MACROCELL * np.prod(axis_resolution(c, ext), dtype=np.float64) <= len(cells)]
    return max(fit, default=0)


def _candidates(cells, candidates=CANDIDATES) -> list:
    """The resolutions `auto_grid` weighs for ``cells``: none finer than
    the longest side of the data in finest cells (but at least the coarsest)."""
    lo, hi = cells.bounds
    ext = int((hi - lo).max())
    return sorted(c for c in candidates if c <= max(ext, min(candidates)))


def file_grids(volume, methods=None) -> dict:
    """The grids `auto_grid` builds first (its finest candidate, with value
    masks where a method's majorants use them), for each reconstruction
    method: what a native file stores so that a medium opened from it
    builds none (`mi_amr.data.amrb.write_amrb`)."""
    finest = _candidates(volume)[-1]
    out = {}
    for name in (methods or METHODS):
        method = METHODS[name]()
        out[method.name] = MacrocellGrid(volume, finest, support=method,
                                         masks=method.value_masks_tighten).to_file()
    return out


def _uniform_cost(mu: np.ndarray, resolution: int) -> float:
    """cost(R) of `auto_grid` for majorants ``mu`` (inverse local length)."""
    m1 = float(mu.mean())
    m2 = float((mu * mu).mean()) / m1 if m1 > 0 else 0.0
    return STEP_COST * STEPS_PER_CELL * resolution + 0.5 * (m1 + m2)


def _pool(a: np.ndarray, f: int, op, fill) -> np.ndarray:
    """Reduce blocks of f^3 cells (padding with ``fill``)."""
    if f == 1:
        return a
    pad = [(0, (-n) % f) for n in a.shape]
    a = np.pad(a, pad, constant_values=fill)
    z, y, x = (n // f for n in a.shape)
    return op.reduce(op.reduce(op.reduce(a.reshape(z, f, y, f, x, f), axis=5), axis=3), axis=1)


#: Stock ``volpath`` with the ``amr`` medium against Mitsuba's own
#: ``heterogeneous`` medium: the cost of one tentative collision (an AMR
#: look-up, the TF tables and the walk of `intersect_aabb` that finds the
#: majorant of the rest of the ray) over one of the reference (a baked
#: texture fetch): ``1 / (share x efficiency)`` over the benchmark's 256x256
#: frozen frames ranged 1.44-2.64 (3.4-4.7 on stadium, whose frames are
#: mostly fixed costs, far from parity); 2.6 is taken, so that the warning
#: errs towards warning near parity (docs/performance/protocol.md, "Stock
#: volpath").
VOLPATH_COLLISION_COST = 2.6


def volpath_collision_share(mu: np.ndarray, rays: int = 1024, samples: int = 96, seed: int = 0) -> float:
    """Tentative collisions of stock ``volpath`` with the ray-wise majorant
    over those of one global majorant (Mitsuba's ``heterogeneous``), on
    random chords of the unit cube: volpath restarts at every null collision
    and takes the largest macrocell majorant of the rest of the ray, so a
    chord costs ``integral of max_{s >= t} mu(s) dt`` against ``G x length``.
    ``mu``: macrocell majorants ``[z, y, x]``. 0 for an empty medium."""
    mu = np.asarray(mu, dtype=np.float64)
    G = float(mu.max()) if mu.size else 0.0
    if G <= 0.0:
        return 0.0
    rng = np.random.default_rng(seed)
    x0 = rng.random((rays, 3))
    d = rng.normal(size=(rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = -x0 / d, (1.0 - x0) / d
    t_in = np.nanmax(np.minimum(a, b), axis=1)
    t_out = np.nanmin(np.maximum(a, b), axis=1)
    t = t_in[:, None] + (t_out - t_in)[:, None] * ((np.arange(samples) + 0.5) / samples)[None]
    p = x0[:, None, :] + t[..., None] * d[:, None, :]
    shape = np.array(mu.shape[::-1])                       # x, y, z
    ijk = np.clip((p * shape).astype(np.int64), 0, shape - 1)
    m = mu[ijk[..., 2], ijk[..., 1], ijk[..., 0]]
    rest = np.maximum.accumulate(m[:, ::-1], axis=1)[:, ::-1]      # max over [t, exit]
    length = (t_out - t_in)[:, None]
    return float((rest * length).sum() / (G * length * samples).sum())


def volpath_speedup(mu: np.ndarray) -> float:
    """Predicted efficiency of stock ``volpath`` with the ``amr`` medium over
    Mitsuba's ``heterogeneous`` on the same field (`volpath_collision_share`,
    `VOLPATH_COLLISION_COST`); inf for an empty medium."""
    share = volpath_collision_share(mu)
    return float("inf") if share == 0.0 else 1.0 / (share * VOLPATH_COLLISION_COST)
