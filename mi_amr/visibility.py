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

And what a picture says (docs/manual/transfer-functions.md "Layers"):

* `colour_layers`: the number of colour layers an eye can tell apart in a
  picture (hue clusters of the pixels that carry colour, CIELAB a*, b*),
  what the tests and the gallery count, for our pictures and yt's alike;
* before rendering, for a layered TF (`mi_amr.transfer.layers`):
  `layer_weights` and `layers_seen` predict the share of each pixel's
  light each layer gives, from the layers' profiles averaged into the
  voxel grid (`opacity_grid` with one channel a layer, `ray_samples`):
  which layers the planned picture shows (`mi_amr.autoscene._planned_layers`).

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


def _grid_shape(data, grid: int):
    """``(lo, voxel size, shape)`` of a grid over ``data``'s bounding box
    with ``grid`` voxels along its longest side (at least 2 on each side)."""
    lo, hi = (np.asarray(b, np.float64) for b in data.bounds)
    size = hi - lo
    shape = np.maximum(2, np.round(grid * size / size.max())).astype(np.int64)
    return lo, size / shape, shape


def _voxel_cover(data, lo, voxel, shape):
    """Yield ``(flat voxel index (k,), values (k,), volume weight (k,))``
    for a sample of the cells of ``data`` (`sampled_cells`) on the grid
    ``lo, voxel, shape`` (`_grid_shape`): a cell within one voxel once, a
    cell larger than a voxel once per voxel it covers, its weight shared
    among them."""
    for pos, width, v, weight in sampled_cells(data):
        w = weight * width ** 3
        i0 = np.clip(np.floor((pos - lo) / voxel + 1e-9), 0, shape - 1).astype(np.int64)
        i1 = np.clip(np.ceil((pos + width[:, None] - lo) / voxel - 1e-9), i0 + 1, shape).astype(np.int64)
        span = i1 - i0
        cover = span.prod(axis=1)
        one = cover == 1                        # cells within one voxel: the common case
        yield np.ravel_multi_index(i0[one].T, shape), v[one], w[one]
        big = np.flatnonzero(~one)              # cells larger than a voxel: spread over the ones they cover
        if big.size:
            counts = cover[big]
            owner = np.repeat(np.arange(big.size), counts)
            rank = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
            sx, sy = span[big][owner, 0], span[big][owner, 1]
            offset = np.stack([rank % sx, (rank // sx) % sy, rank // (sx * sy)], axis=1)
            yield (np.ravel_multi_index((i0[big][owner] + offset).T, shape), v[big][owner],
                   (w[big] / counts)[owner])


def opacity_grid(data, opacity, grid: int = GRID) -> np.ndarray:
    """The volume-weighted mean of ``opacity(values)`` (the TF's alpha of the
    stored values, unit density scale) per voxel of a grid over ``data``'s
    bounding box, ``grid`` voxels along its longest side (at least 2 on each
    side). Voxels no sampled cell reaches are 0 (no data: empty space).
    ``opacity`` may give several channels per value ((m, c): each layer's
    opacity of a layered TF); the grid then has them as its last axis."""
    lo, voxel, shape = _grid_shape(data, grid)
    size = int(np.prod(shape))
    num, den, channels = None, np.zeros(size), ()
    for flat, v, w in _voxel_cover(data, lo, voxel, shape):
        a = np.asarray(opacity(v), np.float64)
        channels = a.shape[1:]
        a = a.reshape(a.shape[0], int(np.prod(a.shape[1:])))
        if num is None:
            num = np.zeros((size, a.shape[1]))
        for c in range(a.shape[1]):             # a few channels at most
            num[:, c] += np.bincount(flat, weights=a[:, c] * w, minlength=size)
        den += np.bincount(flat, weights=w, minlength=size)
    if num is None:
        return np.zeros(tuple(shape))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den[:, None] > 0, num / np.where(den > 0, den, 1.0)[:, None], 0.0)
    return out.reshape(tuple(shape) + tuple(channels))


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


def ray_samples(alpha_grid, extent, origins, dirs, steps: int | None = None) -> tuple:
    """``(samples (h, steps, ...), dt (h,), hits (n,) bool)``: ``alpha_grid``
    (nearest voxel; any channels after the first three axes) at the
    midpoints of ``steps`` equal steps of length ``dt`` along the chords of
    the ``h`` rays that meet the domain box (world space: centred at the
    origin, sides ``extent``), front to back."""
    extent = np.asarray(extent, np.float64)
    half = 0.5 * extent
    t0, t1 = box_chords(origins, dirs, -half, half)
    hits = t1 > t0
    shape = np.asarray(alpha_grid.shape[:3])
    steps = steps or int(2 * shape.max())
    o, d, a, b = origins[hits], dirs[hits], t0[hits], t1[hits]
    dt = (b - a) / steps
    s = (np.arange(steps) + 0.5)[None, :]
    p = o[:, None, :] + (a[:, None] + s * dt[:, None])[..., None] * d[:, None, :]
    idx = np.clip(((p + half) / extent * shape).astype(np.int64), 0, shape - 1)
    return alpha_grid[idx[..., 0], idx[..., 1], idx[..., 2]], dt, hits


def projected_depth(alpha_grid, extent, origins, dirs, steps: int | None = None) -> tuple:
    """``(optical depth (n,), hits (n,) bool)`` of rays through the domain box
    (world space: centred at the origin, sides ``extent``) at unit density
    scale: midpoint sums of ``alpha_grid`` (nearest voxel) along each ray's
    chord of the box; ``hits``: the rays that meet the box."""
    samples, dt, hits = ray_samples(alpha_grid, extent, origins, dirs, steps)
    tau = np.zeros(len(dirs))
    tau[hits] = samples.sum(axis=1) * dt
    return tau, hits


def visibility_of_depths(tau, hits, density_scale: float) -> Visibility:
    """`Visibility` of a picture whose footprint pixels (``hits``) see the
    optical depths ``tau`` (unit density) times ``density_scale``."""
    n = int(hits.sum())
    if not n:
        return Visibility(0.0, 0.0, 0)
    opacity = 1.0 - np.exp(-density_scale * tau[hits])
    return Visibility(float((opacity > VISIBLE_OPACITY).mean()), float((opacity > OPAQUE_OPACITY).mean()), n)


#: A layer tints a pixel when it gives at least this share of the pixel's
#: light (its colour then shows through the rest; predicted) ...
TINT_WEIGHT = 0.3
#: ... and a layer is seen when it tints most at least this share of the
#: tinted pixels (the colour-layer measure's `MIN_LAYER_SHARE`).
SEEN_SHARE = 0.03


@dataclass
class LayersSeen:
    """Which layers of a layered TF a picture is predicted to show:
    ``seen`` (indices, 0 the lowest values), ``shares`` (n,): the share of
    the tinted pixels that each layer tints most, ``tinted``: the share of
    the footprint that some layer tints."""
    seen: tuple
    shares: np.ndarray
    tinted: float

    def __str__(self):
        n = len(self.shares)
        return (f"{len(self.seen)} of {n} layers seen ({', '.join(str(k + 1) for k in self.seen) or 'none'}; "
                f"1 = the lowest values), tinting {100 * self.tinted:.3g}% of the footprint")


def layer_weights(samples, dt, opacities, scale: float) -> np.ndarray:
    """``(h, n)``: the share of each ray's light that each layer gives
    (emission-absorption weights ``integral T sigma_k ds``, front to back)
    from ``samples`` (h, steps, n) of the layers' unit-peak profiles along
    the rays (`ray_samples`), steps ``dt`` (h,), layer opacities
    ``opacities`` (n,) and the density scale."""
    sig_k = samples * (scale * np.asarray(opacities, samples.dtype))[None, None, :]
    sig = sig_k.sum(axis=2)
    depth = sig * dt[:, None]
    before = np.exp(-(np.cumsum(depth, axis=1) - depth))
    absorbed = before * -np.expm1(-depth)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(sig[..., None] > 0, sig_k / np.where(sig > 0, sig, 1.0)[..., None], 0.0)
    return (absorbed[..., None] * frac).sum(axis=1)


def layers_opacity(weights) -> Visibility:
    """`Visibility` of per-ray layer weights (h, n) (`layer_weights`; a
    ray's opacity is their sum, ``1 - T``), the footprint being the rays."""
    opacity = np.asarray(weights).sum(axis=1)
    if not len(opacity):
        return Visibility(0.0, 0.0, 0)
    return Visibility(float((opacity > VISIBLE_OPACITY).mean()), float((opacity > OPAQUE_OPACITY).mean()),
                      len(opacity))


def layers_seen(weights, footprint: int) -> LayersSeen:
    """`LayersSeen` of per-ray layer weights (h, n) (`layer_weights`) on a
    footprint of ``footprint`` pixels: a pixel is tinted by its strongest
    layer where that gives at least `TINT_WEIGHT` of its light."""
    n = weights.shape[1]
    if not len(weights):
        return LayersSeen((), np.zeros(n), 0.0)
    top = weights.argmax(axis=1)
    tinted = weights.max(axis=1) >= TINT_WEIGHT
    counts = np.bincount(top[tinted], minlength=n).astype(np.float64)
    shares = counts / max(tinted.sum(), 1)
    seen = tuple(int(k) for k in np.flatnonzero(shares >= SEEN_SHARE))
    return LayersSeen(seen, shares, float(tinted.sum() / max(footprint, 1)))


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


# ---- Colour layers: what a picture says ------------------------------------

#: A pixel carries colour when its CIELAB chroma ``C* = |(a*, b*)|`` is at
#: least this (the grey ground, tinted blue-grey by the sky, the white-grey
#: sky near the horizon and a black background have less) ...
MIN_CHROMA = 12.0
#: ... and its lightness ``L*`` lies in this range (a black background and
#: the palest sky lie outside).
LIGHTNESS_RANGE = (5.0, 95.0)
#: Two colour layers an eye tells apart at a glance differ in hue (the angle
#: of (a*, b*)) by at least this many degrees: the half width of a layer.
HUE_RADIUS = 15.0
#: A colour layer holds at least this share of the pixels that carry colour.
MIN_LAYER_SHARE = 0.03
#: Pixels a side of the box the picture is averaged over first.
SMOOTH = 3
#: Bin width (degrees) of the hue histogram the layers are made from.
HUE_BIN = 1.0


def srgb_to_lab(rgb) -> np.ndarray:
    """``(..., 3)`` CIELAB (D65 white) of sRGB-encoded colours: floats in [0,
    1] or uint8 (the picture as displayed)."""
    rgb = np.asarray(rgb)
    c = rgb.astype(np.float64) / 255.0 if rgb.dtype == np.uint8 else np.clip(np.asarray(rgb, np.float64), 0, 1)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]])
    xyz = lin @ m.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


@dataclass
class ColourLayers:
    """What a picture says: ``count`` colour layers an eye can tell apart,
    their hues (degrees, the angle of (a*, b*)) and shares of the
    ``coloured`` pixels (those that carry colour, of ``pixels`` looked
    at), most populous first."""
    count: int
    hues: np.ndarray
    shares: np.ndarray
    coloured: int
    pixels: int

    def __str__(self):
        return (f"{self.count} colour layer{'s' if self.count != 1 else ''} "
                f"({100 * self.coloured / max(self.pixels, 1):.3g}% of the pixels carry colour)")


def _box_mean(img, size: int) -> np.ndarray:
    """``img`` (H, W, C) averaged over ``size`` x ``size`` pixels (edges
    repeated)."""
    if size <= 1:
        return img
    r = size // 2
    pad = np.pad(img, ((r, size - 1 - r), (r, size - 1 - r), (0, 0)), mode="edge")
    h, w = img.shape[:2]
    return sum(pad[i:i + h, j:j + w] for i in range(size) for j in range(size)) / size ** 2


def colour_layers(image, mask=None, *, radius: float = HUE_RADIUS, min_share: float = MIN_LAYER_SHARE,
                  min_chroma: float = MIN_CHROMA, lightness=LIGHTNESS_RANGE, smooth: int = SMOOTH) -> ColourLayers:
    """The number of colour layers an eye can tell apart in ``image`` (H, W,
    3+; sRGB uint8 or floats in [0, 1] as displayed: `mi_amr.images.srgb8`
    of a rendered one; docs/manual/transfer-functions.md "Layers").

    The picture is first averaged over ``smooth`` x ``smooth`` pixels (as
    an eye averages a Monte Carlo picture's grain: the noise of a grey
    ground is no colour). The pixels that carry colour (within ``mask``
    (H, W) bool when given;
    CIELAB chroma at least ``min_chroma`` and lightness within
    ``lightness``: the grey ground, the pale sky and a black background are
    left out) are clustered by their chromaticity's direction in the (a*,
    b*) plane, the hue: lightness is shading, and a lower chroma of the same
    hue is the same layer seen through less of it. The most populous hue
    seeds a layer that takes the hues within ``radius`` degrees, the most
    populous hue left the next one, and so on; then every hue joins its
    nearest seed. A colour layer is one holding at least ``min_share`` of
    the coloured pixels."""
    img = np.asarray(image)[..., :3]
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"colour_layers needs an (H, W, 3) image, got shape {np.shape(image)}")
    lab = srgb_to_lab(_box_mean(img.astype(np.float64) / (255.0 if img.dtype == np.uint8 else 1.0),
                                smooth)).reshape(-1, 3)
    keep = np.ones(len(lab), bool) if mask is None else np.asarray(mask, bool).reshape(-1).copy()
    if keep.size != len(lab):
        raise ValueError(f"colour_layers: the mask's shape {np.shape(mask)} is not the image's {img.shape[:2]}")
    pixels = int(keep.sum())
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    keep &= (chroma >= min_chroma) & (lab[:, 0] >= lightness[0]) & (lab[:, 0] <= lightness[1])
    n = int(keep.sum())
    if not n:
        return ColourLayers(0, np.zeros(0), np.zeros(0), 0, pixels)
    hue = np.degrees(np.arctan2(lab[keep, 2], lab[keep, 1])) % 360.0
    nbins = int(round(360.0 / HUE_BIN))
    counts = np.bincount(np.minimum((hue / HUE_BIN).astype(np.int64), nbins - 1), minlength=nbins)
    centre = (np.arange(nbins) + 0.5) * HUE_BIN

    def apart(h, ref):                                   # circular distance in degrees
        d = np.abs(h - ref) % 360.0
        return np.minimum(d, 360.0 - d)
    seeds = []
    free = counts > 0
    for i in np.argsort(-counts, kind="stable"):        # 360 bins: a short host loop
        if free[i]:
            seeds.append(i)
            free &= apart(centre, centre[i]) > radius
    seed_hue = centre[seeds]
    nearest = np.argmin(apart(centre[:, None], seed_hue[None, :]), axis=1)
    share = np.bincount(nearest, weights=counts, minlength=len(seeds)) / n
    layer = share >= min_share
    order = np.argsort(-share[layer], kind="stable")
    return ColourLayers(int(layer.sum()), seed_hue[layer][order], share[layer][order], n, pixels)
