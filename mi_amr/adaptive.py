"""Adaptive sampling: samples where the picture is still noisy, none where
it has converged (docs/manual/adaptive.md).

A render is a series of *passes*, each of ``pass_spp`` samples in every
pixel of the tiles still active; passes alternate between two half
buffers ``A`` and ``B`` (raw weighted film sums, as `mi_amr.distributed`
keeps them). After every pair of passes, each tile's error is estimated
from the two halves: with ``a`` and ``b`` the pixel means of ``A`` and
``B``, ``((a - b) / 2)^2`` is an unbiased estimate of the squared error
of their mean ``(a + b) / 2`` (when both halves hold as many samples, as
here); its mean over the tile's pixels and colour channels is the tile's
mean squared error, and its root over the picture's mean brightness the
tile's *relative error*, the measure the benchmark's "within 2% RMSE of
converged" uses. A tile whose relative error is below ``noise`` stops; the
next pair renders only the pixels of the tiles still active. The render
ends when no tile is active, at the ``max_spp`` cap, or at the ``seconds``
limit (a pair is not started when it would end past it).

A pass renders its pixels as one Dr.Jit launch through the scene's own
sensor, sampler, integrator and film (`render_pixels`: the pixel indices
are gathered from a list, so a pass over a tenth of the tiles costs about
a tenth, and the kernel is the same for every pass: nothing recompiles).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .distributed import chunk_seeds

#: Relative error at which a tile stops (RMS error over the picture's mean
#: brightness) when none is asked for.
DEFAULT_NOISE = 0.02
#: The same, for a picture that is denoised afterwards: the denoiser takes a
#: picture at this noise to about `DEFAULT_NOISE` from the converged one
#: (measured in docs/performance/adaptive.md).
DENOISED_NOISE = 0.1
#: Samples per pixel at most, when no cap is asked for.
DEFAULT_MAX_SPP = 1024
#: Samples per pixel of each pass (a pair of them, one per half buffer, is
#: the least any pixel gets).
DEFAULT_PASS_SPP = 4
#: Width and height of a tile, pixels.
DEFAULT_TILE = 16


@dataclass
class AdaptiveResult:
    """An adaptive render: ``image`` float32 (H, W, C) linear (the mean of
    every sample each pixel took: the film's sums over their weight),
    ``spp`` float32 (H, W) samples each pixel took, ``tile_error`` (tile
    rows, tile columns) the last relative error estimate of each tile,
    ``noise`` the threshold, ``max_spp`` the cap, ``converged`` whether every tile went below
    it, ``stopped`` why the render ended (``noise``, ``spp`` or ``time``),
    ``passes`` and ``seconds`` of rendering."""
    image: np.ndarray
    spp: np.ndarray
    tile_error: np.ndarray
    tile: int
    noise: float
    max_spp: int
    converged: bool
    stopped: str
    passes: int
    seconds: float

    @property
    def samples(self) -> float:
        """Samples taken in all, per pixel of the picture (the mean)."""
        return float(self.spp.mean())

    def summary(self) -> str:
        """One line: how many samples the picture took and where."""
        tiles = self.spp[::self.tile, ::self.tile]
        low = float(tiles.min())
        below = f"{100 * float(np.mean(self.tile_error < self.noise)):.0f}% of tiles below {100 * self.noise:g}% noise"
        why = {"noise": f"every tile below {100 * self.noise:g}% noise", "spp": f"the spp cap reached ({below})",
               "time": f"the time limit reached ({below})"}[self.stopped]
        return (f"adaptive: {self.samples:.1f} spp mean ({low:.0f} to {tiles.max():.0f} per pixel, cap "
                f"{self.max_spp} spp; "
                f"{100 * float(np.mean(tiles == low)):.0f}% of tiles stopped at {low:.0f}), {self.passes} passes, "
                f"{why}; estimated error {100 * estimated_picture_error(self.tile_error):.2f}%")


def estimated_picture_error(tile_error: np.ndarray) -> float:
    """The picture's relative RMS error estimated from its tiles' (all tiles
    the same size)."""
    return float(np.sqrt(np.mean(np.square(tile_error))))


def tile_errors(a_sums: np.ndarray, b_sums: np.ndarray, tile: int, scale: float | None = None) -> np.ndarray:
    """Relative error estimate of each ``tile`` x ``tile`` tile of the mean
    of two half buffers of raw film sums (H, W, C + 1; weight last; colour
    the first three channels): the root of the tile's mean of ``((a - b) /
    2)^2`` over ``scale`` (default the picture's mean colour). Pixels without
    samples in either half count as no error. Returns (tile rows, tile
    columns); tiles at the right and bottom edge may be smaller."""
    return half_errors(_mean(a_sums), _mean(b_sums), tile, scale)


def half_errors(a: np.ndarray, b: np.ndarray, tile: int, scale: float | None = None) -> np.ndarray:
    """`tile_errors` of two half pictures' means ``a`` and ``b`` (H, W, 3+;
    colour the first three channels), each of as many samples."""
    a, b = np.asarray(a, np.float64)[..., :3], np.asarray(b, np.float64)[..., :3]
    sq = np.square(0.5 * (a - b)).mean(axis=-1)
    h, w = sq.shape
    th, tw = -(-h // tile), -(-w // tile)
    padded = np.zeros((th * tile, tw * tile))
    count = np.zeros_like(padded)
    padded[:h, :w], count[:h, :w] = sq, 1.0
    per_tile = (padded.reshape(th, tile, tw, tile).sum(axis=(1, 3))
                / count.reshape(th, tile, tw, tile).sum(axis=(1, 3)))
    if scale is None:
        scale = float(0.5 * (a + b).mean())
    return np.sqrt(per_tile) / max(scale, 1e-12)


def _mean(sums: np.ndarray) -> np.ndarray:
    """Pixel means (H, W, 3) of raw film sums (weight last)."""
    w = sums[..., -1:]
    return np.where(w > 0, sums[..., :3] / np.where(w > 0, w, 1.0), 0.0)


def tile_pixels(active: np.ndarray, tile: int, width: int, height: int) -> np.ndarray:
    """Indices (``y * width + x``, uint32, ascending) of the pixels of the
    active tiles (``active``: bool, tile rows x tile columns)."""
    mask = np.kron(active, np.ones((tile, tile), dtype=bool))[:height, :width]
    return np.flatnonzero(mask).astype(np.uint32)


def render_pixels(scene: mi.Scene, pixels: np.ndarray, spp: int, seed: int, sensor: int = 0,
                  integrator: mi.Integrator | None = None) -> np.ndarray:
    """Render ``spp`` samples in each of ``pixels`` (indices ``y * width +
    x`` in the film's crop) as one launch, as ``mi.render`` renders a pixel
    (the sensor's ray through a random point of the pixel, drawn by an
    ``independent`` sampler whatever the scene's; the scene's integrator
    unless ``integrator``; splatted into the film with its filter), and return the film's raw weighted sums (H, W, C + 1) float32,
    weight last. The pixel list and ``spp`` are data of the kernel, not
    constants: another list or count compiles nothing."""
    sensor_ = scene.sensors()[sensor]
    film = sensor_.film()
    integrator = integrator or scene.integrator()
    size = film.crop_size()
    width = int(size[0])
    with dr.suspend_grad():
        pix = mi.UInt32(np.ascontiguousarray(pixels, dtype=np.uint32))
        n = int(len(pixels)) * int(spp)
        sampler = mi.load_dict({"type": "independent"})   # whatever the scene's: any count of samples
        sampler.seed(seed, n)
        idx = dr.arange(mi.UInt32, n) // dr.opaque(mi.UInt32, int(spp))
        p = dr.gather(mi.UInt32, pix, idx)
        w = dr.opaque(mi.UInt32, width)          # another film size compiles nothing either
        row = p // w
        pos = mi.Vector2u(p - row * w, row) + mi.Vector2u(film.crop_offset())
        pos_f = mi.Vector2f(pos) + sampler.next_2d()
        scale = dr.rcp(mi.ScalarVector2f(size))
        offset = -mi.ScalarVector2f(film.crop_offset()) * scale
        aperture = sampler.next_2d() if sensor_.needs_aperture_sample() else mi.Vector2f(0.0)
        t = sensor_.shutter_open()
        if sensor_.shutter_open_time() > 0:
            t += sampler.next_1d() * sensor_.shutter_open_time()
        wavelength = sampler.next_1d() if mi.is_spectral else 0.0
        ray, weight = sensor_.sample_ray_differential(t, wavelength, dr.fma(pos_f, scale, offset), aperture)
        L, valid, _ = integrator.sample(scene, sampler, ray, sensor_.get_medium(), mi.Bool(True))
        rgb = L * weight
        film.prepare([])
        block = film.create_block()
        splat = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
        alpha = dr.select(valid, mi.Float(1.0), mi.Float(0.0))
        channels = [rgb[0], rgb[1], rgb[2]]
        if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
            channels.append(alpha)
        block.put(splat, channels + [mi.Float(1.0)])
        film.put_block(block)
        return np.array(film.bitmap(raw=True), dtype=np.float32, copy=True)


def render_adaptive(scene: mi.Scene, noise: float = DEFAULT_NOISE, max_spp: int = DEFAULT_MAX_SPP,
                    seconds: float | None = None, seed: int = 0, sensor: int = 0,
                    pass_spp: int = DEFAULT_PASS_SPP, tile: int = DEFAULT_TILE,
                    progress=None) -> AdaptiveResult:
    """Render ``scene`` (loaded) adaptively (module docstring): tiles of
    ``tile`` pixels stop at relative error ``noise``; at most ``max_spp``
    samples per pixel, at most about ``seconds`` of rendering (None: no
    limit; the first pair of passes always runs). ``progress``: called with
    the picture's mean samples per pixel so far after each pair of passes.
    Seeds: the chunk seeds of ``seed`` (`mi_amr.distributed.chunk_seeds`),
    one per pass."""
    if not noise > 0:
        raise ValueError(f"noise: a relative error above 0, got {noise!r}")
    if not max_spp >= 1:
        raise ValueError(f"max_spp: at least 1, got {max_spp!r}")
    if seconds is not None and not seconds > 0:
        raise ValueError(f"seconds: a time limit above 0, got {seconds!r}")
    size = scene.sensors()[sensor].film().crop_size()
    width, height = int(size[0]), int(size[1])
    th, tw = -(-height // tile), -(-width // tile)
    active = np.ones((th, tw), dtype=bool)
    halves = [None, None]
    spp_map = np.zeros((height, width), dtype=np.float32)
    error = np.full((th, tw), np.inf)
    seeds = iter(chunk_seeds(seed, 1 << 16))
    t0 = time.perf_counter()
    passes, stopped, pair_seconds = 0, "noise", 0.0
    # a pixel's count is even (both halves hold as many samples): the cap
    # rounded down to one, but a cap of 1 renders one pass of 1 sample (no estimate)
    max_pair = max_spp // 2
    if max_pair == 0:
        sums = render_pixels(scene, tile_pixels(active, tile, width, height), 1, next(seeds), sensor)
        spp_map[:] = 1
        image = (sums[..., :-1] / np.where(sums[..., -1:] > 0, sums[..., -1:], 1.0)).astype(np.float32)
        return AdaptiveResult(image=image, spp=spp_map, tile_error=error, tile=tile, noise=float(noise),
                              max_spp=int(max_spp), converged=False, stopped="spp", passes=1,
                              seconds=time.perf_counter() - t0)
    taken = 0                               # samples per pixel of the active tiles, each half
    while active.any():
        # passes grow as the picture converges (each pair half again as many samples)
        per_half = min(max(pass_spp, taken // 2), max_pair - taken)
        if per_half < 1:
            stopped = "spp"
            break
        if seconds is not None and passes and time.perf_counter() - t0 + pair_seconds > seconds:
            stopped = "time"
            break
        t_pair, before = time.perf_counter(), float(active.mean())
        pixels = tile_pixels(active, tile, width, height)
        for half in (0, 1):
            sums = render_pixels(scene, pixels, per_half, next(seeds), sensor)
            halves[half] = sums if halves[half] is None else halves[half] + sums
            passes += 1
        taken += per_half
        spp_map.reshape(-1)[pixels] += 2 * per_half
        if progress is not None:
            progress(float(spp_map.mean()))
        error[active] = tile_errors(halves[0], halves[1], tile)[active]
        active &= ~(error < noise)
        # the next pair renders the active tiles only: its cost scales with them
        pair_seconds = (time.perf_counter() - t_pair) * float(active.mean()) / before * 1.5
    if active.any() and stopped == "noise":
        stopped = "spp"
    total = halves[0] + halves[1]
    w = total[..., -1:]
    image = np.where(w > 0, total[..., :-1] / np.where(w > 0, w, 1.0), 0.0).astype(np.float32)
    return AdaptiveResult(image=image, spp=spp_map, tile_error=error, tile=tile, noise=float(noise),
                          max_spp=int(max_spp), converged=not active.any(), stopped=stopped, passes=passes,
                          seconds=time.perf_counter() - t0)
