"""How much of the data a picture shows (docs/manual/data.md "Default
pictures").

Two measures of one thing, the share of the domain's footprint on the image
whose pixels show the medium:

* before rendering (`opacity_grid`, `projected_depth`,
  `visibility_of_depths`): the TF's opacity of a sample of the cells is
  averaged into a coarse voxel grid over the domain, and the planned
  camera's rays march through it on the host; a pixel shows the
  data where the medium takes at least `VISIBLE_OPACITY` of the light
  behind it. This is what the plan checks (`mi_amr.autoscene._checked`):
  cheap (a few million cells sampled at most), independent of the mode.
* `visibility_score` (`rendered_visibility`), after rendering: the planned picture against the same
  scene with the medium's density set to 0, two seeds each; a block of
  pixels shows the data where the two means differ by more than
  `SCORE_SIGMAS` noise standard deviations and by more than
  `SCORE_RELATIVE` of their brightness. This is what the tests measure.

World space is the plan's (the domain centred at the origin, its longest
side 1, +z up); the data's unit cube maps onto the domain box.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .core.block_keys import block_offsets

#: A pixel shows the data when the medium takes at least this share of the
#: light along its ray (predicted) ...
VISIBLE_OPACITY = 0.03
#: ... and is opaque above this share.
OPAQUE_OPACITY = 0.97
#: Voxels along the domain's longest side of the predicted opacity grid.
GRID = 64
#: Cells sampled at most for the prediction (strided within blocks).
MAX_SAMPLES = 1 << 21
#: Pixels per side of the predicted picture.
PREDICT_RES = 48
#: A rendered block shows the data where planned and empty means differ by
#: more than this many noise sigmas ...
SCORE_SIGMAS = 4.0
#: ... and by more than this share of the brighter of the two.
SCORE_RELATIVE = 0.03


@dataclass
class Visibility:
    """What a picture shows: shares of the footprint (the pixels whose rays
    meet the domain box) that show the data and that are opaque."""
    shown: float
    opaque: float
    footprint: int

    def __str__(self):
        return (f"{100 * self.shown:.3g}% of the domain's footprint shows the data "
                f"({100 * self.opaque:.3g}% opaque)")


def sampled_cells(data, max_cells: int = MAX_SAMPLES):
    """Yield ``(lo (m, 3) float64, size (m,) float64, values (m,) float64,
    weight (m,))`` of a strided sample of the present cells of ``data`` (a
    `BlockVolume` or `AMRCells`): lower corners and widths in finest-cell
    units, and how many cells each sample stands for."""
    if hasattr(data, "block"):                  # BlockVolume: a lattice of cells in every block
        b, b3 = data.block, data.block ** 3
        n_blocks = len(data.level)
        per_block = max(1, min(b3, max_cells // max(n_blocks, 1)))
        cell_step = b3 // per_block
        if cell_step > 1:                    # odd in x and in y (the block's sides are powers of two): the
            cell_step |= 1 | b               # lattice spreads over x, y and z of each block, not one column
        block_step = max(1, int(np.ceil(n_blocks / max_cells)))
        local = block_offsets(b)[::cell_step]
        chunk = max(1, (1 << 20) // len(local))
        values = data.values.reshape(-1, b3)
        for s in range(0, n_blocks, chunk * block_step):
            blocks = np.arange(s, min(n_blocks, s + chunk * block_step), block_step)
            v = values[s:s + chunk * block_step:block_step, ::cell_step]      # a view: nothing copied
            blk, cell = np.nonzero(~np.isnan(v))
            level = data.level[blocks][blk].astype(np.int64)
            q = (data.coord[blocks][blk].astype(np.int64) << data.log2_block) + local[cell]
            yield ((q << level[:, None]) + data.origin).astype(np.float64), np.exp2(level), \
                v[blk, cell].astype(np.float64), np.full(len(blk), float(cell_step * block_step))
        return
    step = max(1, int(np.ceil(len(data.values) / max_cells)))
    yield data.pos[::step].astype(np.float64), data.width[::step].astype(np.float64), \
        np.asarray(data.values[::step], np.float64), np.full(len(data.pos[::step]), float(step))


def opacity_grid(data, opacity, grid: int = GRID) -> np.ndarray:
    """The volume-weighted mean of ``opacity(values)`` (the TF's alpha of the
    stored values, unit density scale) per voxel of a grid over ``data``'s
    bounding box, ``grid`` voxels along its longest side (at least 2 on each
    side). Voxels no sampled cell reaches are 0 (no data: empty space)."""
    lo, hi = (np.asarray(b, np.float64) for b in data.bounds)
    size = hi - lo
    shape = np.maximum(2, np.round(grid * size / size.max())).astype(np.int64)
    voxel = size / shape
    num, den = np.zeros(int(np.prod(shape))), np.zeros(int(np.prod(shape)))
    for pos, width, v, weight in sampled_cells(data):
        a = opacity(v)
        w = weight * width ** 3
        i0 = np.clip(np.floor((pos - lo) / voxel + 1e-9), 0, shape - 1).astype(np.int64)
        i1 = np.clip(np.ceil((pos + width[:, None] - lo) / voxel - 1e-9), i0 + 1, shape).astype(np.int64)
        span = i1 - i0
        cover = span.prod(axis=1)
        one = cover == 1                        # cells within one voxel: the common case
        flat = np.ravel_multi_index(i0[one].T, shape)
        num += np.bincount(flat, weights=a[one] * w[one], minlength=num.size)
        den += np.bincount(flat, weights=w[one], minlength=den.size)
        big = np.flatnonzero(~one)              # cells larger than a voxel: spread over the ones they cover
        if big.size:
            counts = cover[big]
            owner = np.repeat(np.arange(big.size), counts)
            rank = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
            sx, sy = span[big][owner, 0], span[big][owner, 1]
            offset = np.stack([rank % sx, (rank // sx) % sy, rank // (sx * sy)], axis=1)
            flat = np.ravel_multi_index((i0[big][owner] + offset).T, shape)
            share = (w[big] / counts)[owner]
            num += np.bincount(flat, weights=a[big][owner] * share, minlength=num.size)
            den += np.bincount(flat, weights=share, minlength=den.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0).reshape(shape)


def camera_rays(origin, target, up, fov: float, res: int) -> tuple[np.ndarray, np.ndarray]:
    """``(origins (res*res, 3), unit directions (res*res, 3))`` through the
    pixel centres of a square perspective camera (``fov`` in degrees, along
    x, as Mitsuba's ``perspective``), rows top to bottom."""
    origin, target, up = (np.asarray(v, np.float64) for v in (origin, target, up))
    d = target - origin
    d /= np.linalg.norm(d)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    t = np.tan(np.radians(fov) / 2)
    u = (np.arange(res) + 0.5) / res * 2 - 1
    x, y = np.meshgrid(-u * t, -u * t, indexing="xy")      # image right = -left, image down = -up
    dirs = d + x.reshape(-1, 1) * left + y.reshape(-1, 1) * new_up
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.broadcast_to(origin, dirs.shape), dirs


def box_chords(origins, dirs, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """``(t0, t1)`` per ray (numpy, (n, 3) origins and directions): where
    ``origins + t dirs`` (``t >= 0``) enters and leaves the box ``[lo,
    hi]``; the ray meets it where ``t1 > t0`` (slab test; axis-parallel
    directions as the slabs they lie in)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a, t_b = (np.asarray(lo) - origins) / dirs, (np.asarray(hi) - origins) / dirs
    return np.nanmax(np.minimum(t_a, t_b), axis=1).clip(min=0.0), np.nanmin(np.maximum(t_a, t_b), axis=1)


def projected_depth(alpha_grid, extent, origins, dirs, steps: int | None = None) -> tuple:
    """``(optical depth (n,), hits (n,) bool)`` of rays through the domain box
    (world space: centred at the origin, sides ``extent``) at unit density
    scale: midpoint sums of ``alpha_grid`` (nearest voxel) along each ray's
    chord of the box; ``hits``: the rays that meet the box."""
    extent = np.asarray(extent, np.float64)
    half = 0.5 * extent
    t0, t1 = box_chords(origins, dirs, -half, half)
    hits = t1 > t0
    shape = np.asarray(alpha_grid.shape)
    steps = steps or int(2 * shape.max())
    tau = np.zeros(len(dirs))
    if not hits.any():
        return tau, hits
    o, d, a, b = origins[hits], dirs[hits], t0[hits], t1[hits]
    dt = (b - a) / steps
    s = (np.arange(steps) + 0.5)[None, :]
    p = o[:, None, :] + (a[:, None] + s * dt[:, None])[..., None] * d[:, None, :]
    idx = np.clip(((p + half) / extent * shape).astype(np.int64), 0, shape - 1)
    tau[hits] = alpha_grid[idx[..., 0], idx[..., 1], idx[..., 2]].sum(axis=1) * dt
    return tau, hits


def visibility_of_depths(tau, hits, density_scale: float) -> Visibility:
    """`Visibility` of a picture whose footprint pixels (``hits``) see the
    optical depths ``tau`` (unit density) times ``density_scale``."""
    n = int(hits.sum())
    if not n:
        return Visibility(0.0, 0.0, 0)
    opacity = 1.0 - np.exp(-density_scale * tau[hits])
    return Visibility(float((opacity > VISIBLE_OPACITY).mean()), float((opacity > OPAQUE_OPACITY).mean()), n)


def scale_for_opacity(tau, hits, share: float, opacity: float) -> float:
    """The density scale at which ``share`` of the footprint's pixels (those
    whose rays see any medium: ``tau > 0``) reach ``opacity``."""
    t = tau[hits & (tau > 0)]
    if not t.size:
        return 0.0
    q = float(np.quantile(t, 1.0 - share))
    return -np.log1p(-opacity) / q if q > 0 else 0.0


def visibility_score(planned, empty, footprint=None, block: int = 4) -> Visibility:
    """`Visibility` of rendered pictures: ``planned`` and ``empty`` are
    arrays ``(passes >= 2, H, W, C)`` of independent renders (different
    seeds) of the planned scene and of the same scene with the medium's
    density set to 0; ``footprint`` (H, W) bool: the domain's pixels (None:
    every pixel). A ``block`` x ``block`` pixel block shows the data where
    the means differ by more than `SCORE_SIGMAS` standard errors (estimated
    from the passes) and by more than `SCORE_RELATIVE` of the brighter
    mean (averaged over colour channels); ``opaque``: blocks whose
    difference exceeds 90% of the empty scene's brightness there."""
    planned, empty = np.asarray(planned, np.float64), np.asarray(empty, np.float64)
    if planned.ndim == 3:
        planned, empty = planned[..., None], empty[..., None]
    if planned.shape[0] < 2 or empty.shape[0] < 2:
        raise ValueError("visibility_score needs at least two passes of each picture")
    p, h, w = planned.shape[:3]
    hb, wb = h // block, w // block

    def blocks(x):          # (passes, hb, wb): the block means of the channel mean
        x = x[:, :hb * block, :wb * block].mean(axis=-1)
        return x.reshape(x.shape[0], hb, block, wb, block).mean(axis=(2, 4))
    a, b = blocks(planned), blocks(empty)
    diff = a.mean(0) - b.mean(0)
    se = np.sqrt(a.var(0, ddof=1) / a.shape[0] + b.var(0, ddof=1) / b.shape[0])
    bright = np.maximum(a.mean(0), b.mean(0))
    shown = (np.abs(diff) > SCORE_SIGMAS * se) & (np.abs(diff) > SCORE_RELATIVE * bright)
    opaque = np.abs(diff) > 0.9 * b.mean(0)
    if footprint is None:
        mask = np.ones((hb, wb), bool)
    else:
        f = np.asarray(footprint, bool)[:hb * block, :wb * block]
        mask = f.reshape(hb, block, wb, block).mean(axis=(1, 3)) >= 0.5
    n = int(mask.sum())
    if not n:
        return Visibility(0.0, 0.0, 0)
    return Visibility(float(shown[mask].mean()), float((opaque & shown)[mask].mean()), n)


def footprint_mask(scene, extent) -> np.ndarray:
    """(H, W) bool: the pixels of ``scene``'s first sensor whose rays
    through the pixel centres meet the domain box (world space: centred at
    the origin, sides ``extent``), from the sensor's own rays."""
    sensor = scene.sensors()[0]
    w, h = (int(x) for x in sensor.film().crop_size())
    idx = dr.arange(mi.UInt32, w * h)
    pos = mi.Point2f((mi.Float(idx % w) + 0.5) / w, (mi.Float(idx // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    origins, dirs = (np.stack([np.asarray(c, np.float64) for c in (v.x, v.y, v.z)], axis=1) for v in (ray.o, ray.d))
    half = 0.5 * np.asarray(extent, np.float64)
    t0, t1 = box_chords(origins, dirs, -half, half)
    return (t1 > t0).reshape(h, w)


def rendered_visibility(scene, extent, passes: int = 2, spp: int = 16, block: int = 4) -> Visibility:
    """`visibility_score` of ``scene`` (a loaded Mitsuba scene with one
    ``amr`` medium filling the domain box of sides ``extent``): ``passes``
    renders as it is and as many with the medium's ``density_scale`` set
    to 0 (restored afterwards), seeds 0, 1, ..."""
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith("density_scale")]
    if len(keys) != 1:
        raise ValueError(f"rendered_visibility needs one amr medium's density_scale, found {keys}")
    key = keys[0]
    scale = float(np.asarray(params[key]).ravel()[0])

    def render_all():
        return np.stack([np.array(mi.render(scene, spp=spp, seed=i), np.float64) for i in range(passes)])
    planned = render_all()
    try:
        params[key] = 0.0
        params.update()
        empty = render_all()
    finally:
        params[key] = scale
        params.update()
    return visibility_score(planned, empty, footprint_mask(scene, extent), block)
