"""A gallery of simulation outputs at the variety of real ones, written in the
codes' own formats (tests/amr_formats.py) and scaled as those codes write
them: what a default picture must show (docs/manual/data.md "Default
pictures").

Each case is a function ``case(directory) -> (path, field)`` that writes one
output and returns what ``mi-amr render PATH --field FIELD`` takes:

* ``cosmology`` (Enzo, cgs): a cosmic web. The density spans five decades
  (1e-30 to 3e-26 g/cm^3), but its volume lies within 15x (1st to 99.9th
  volume percentile) around the mean 1e-29: voids and sheets fill the
  volume, filaments and haloes hold the mass. Refined around the haloes.
* ``collapse`` (AMReX, code units): a collapsing core, density ~ r^-4,
  seven decades (2e-4 to 3e3), refined in the centre.
* ``deep`` (AMReX, code units): a collapse eight levels deep, a 16^3 root
  grid refined seven times around the centre (finest cells 2^-7 of the
  root's), density 1 / (1 + (r / 10^-3)^2): nested shells over six
  decades (1.5e-6 to 0.85).
* ``waves`` (Athena++): a smooth field within one decade (1 to 10).
* ``velocity`` (AMReX): a signed field (a velocity component), negative in
  half the volume, zero mean.
* ``sheet`` (RAMSES): a thin curved sheet of gas (a few finest cells thick)
  in an otherwise empty domain: zeros in 98% of the volume.
* ``embedded`` (AMReX): an embedded boundary, as AMReX's EB codes write it:
  a pressure within 1% of 1e5 in the fluid and zeros in the covered cells
  of a solid sphere.
* ``core`` (Enzo): a uniform background (1.0) with a small dense core
  (up to 1e4), refined around it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from amr_formats import write_amrex_plotfile, write_athena_pp, write_enzo, write_ramses


def _centres(n, lo=0.0, hi=1.0, start=(0, 0, 0), shape=None):
    """Cell centres ``(x, y, z)`` (each shaped ``shape``) of an ``n``-cell
    grid over [lo, hi]^3 (``n`` per axis, or three), from cell ``start`` on."""
    n = np.broadcast_to(np.asarray(n), 3)
    shape = tuple(n) if shape is None else shape
    h = (hi - lo) / n
    axes = [lo + (start[k] + np.arange(shape[k]) + 0.5) * h[k] for k in range(3)]
    return np.meshgrid(*axes, indexing="ij")


def _gaussian_field(n, slope=-3.0, seed=0):
    """A periodic Gaussian random field on ``n^3`` cells with power ~ k^slope,
    zero mean and unit variance."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n) * n
    kk = np.sqrt(k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2)
    amp = np.where(kk > 0, np.maximum(kk, 1e-9) ** (slope / 2), 0.0)
    g = np.fft.ifftn(np.fft.fftn(rng.standard_normal((n, n, n))) * amp).real
    return (g - g.mean()) / g.std()


def _trilinear_periodic(grid, x, y, z):
    """Periodic trilinear interpolation of ``grid`` (cell-centred over the
    unit cube) at points ``x, y, z`` in [0, 1)."""
    n = grid.shape[0]
    u = [np.asarray(c) * n - 0.5 for c in (x, y, z)]
    i0 = [np.floor(c).astype(int) for c in u]
    f = [c - i for c, i in zip(u, i0)]
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                out = out + w * grid[(i0[0] + dx) % n, (i0[1] + dy) % n, (i0[2] + dz) % n]
    return out


_HALOES = np.array([[0.30, 0.35, 0.40], [0.70, 0.62, 0.55], [0.52, 0.25, 0.70],
                    [0.25, 0.72, 0.30], [0.75, 0.30, 0.28]])
_HALO_PEAKS = np.array([3000.0, 1500.0, 800.0, 400.0, 250.0])


def cosmology_density(x, y, z, g):
    """The cosmic web's density in g/cm^3 at ``x, y, z`` (unit box): a
    lognormal web from the Gaussian field ``g`` (voids to sheets, sigma 0.5
    in ln), filaments between the haloes, and haloes with cuspy profiles."""
    mean = 1e-29
    rho = np.exp(0.5 * _trilinear_periodic(g, x, y, z) - 0.125)
    p = np.stack([x, y, z], axis=-1)
    for a, b in zip(_HALOES[:-1], _HALOES[1:]):          # filaments along the chain of haloes
        ab = b - a
        t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
        d = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)
        rho = rho + 12.0 * np.exp(-(d / 0.018) ** 2)
    for c, peak in zip(_HALOES, _HALO_PEAKS):
        r = np.linalg.norm(p - c, axis=-1)
        rho = rho + peak / (1.0 + (r / 0.012) ** 2) ** 1.5
    return mean * rho


def cosmology(directory):
    """An Enzo cosmology-like output, 32^3 root cells, one level-1 grid of
    16^3 cells around each halo (see the module docstring)."""
    n = 32
    g = _gaussian_field(n, seed=7)
    root = cosmology_density(*_centres(n), g)
    children = []
    for c in _HALOES:
        start = np.clip((c * 2 * n).astype(int) - 8, 0, 2 * n - 16)
        children.append((start, cosmology_density(*_centres(2 * n, start=start, shape=(16, 16, 16)), g)))
    return write_enzo(Path(directory), "DD0046", root, children), "density"


def collapse(directory):
    """An AMReX plotfile of a collapsing core: density (r/r0)^-4 (r0 = 0.1),
    seven decades over the cells (2e-4 in the corners, 3e3 at the centre):
    16^3 root cells, the central 8^3 refined twice."""
    def rho(x, y, z):
        r = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2)
        return (np.maximum(r, 1e-6) / 0.1) ** -4
    levels = [[((0, 0, 0), rho(*_centres(16)))],
              [((8, 8, 8), rho(*_centres(32, start=(8, 8, 8), shape=(16, 16, 16))))],
              [((24, 24, 24), rho(*_centres(64, start=(24, 24, 24), shape=(16, 16, 16))))]]
    path = Path(directory) / "plt00100"
    write_amrex_plotfile(path, levels, [0, 0, 0], [1, 1, 1])
    return path, "density"


def deep(directory, levels: int = 8):
    """An AMReX plotfile of a collapse ``levels`` levels deep: a 16^3 root
    grid over the unit cube and, on each finer level, one 16^3 box at the
    centre (see the module docstring)."""
    def rho(x, y, z):
        r = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2)
        return 1.0 / (1.0 + (r / 1e-3) ** 2)
    boxes = [[((0, 0, 0), rho(*_centres(16)))]]
    for level in range(1, levels):
        n = 16 * 2 ** level
        start = (n // 2 - 8,) * 3
        boxes.append([(start, rho(*_centres(n, start=start, shape=(16, 16, 16))))])
    path = Path(directory) / "plt_deep"
    write_amrex_plotfile(path, boxes, [0, 0, 0], [1, 1, 1])
    return path, "density"


def waves(directory):
    """An Athena++ output of smooth waves between 1 and 10 (16^3 root cells in
    8^3 mesh blocks, one block refined)."""
    def f(x, y, z):
        return 5.5 + 4.5 * np.sin(2 * np.pi * x) * np.cos(2 * np.pi * y) * np.sin(np.pi * z)
    levels = [[], []]
    for lo in np.argwhere(np.ones((2, 2, 2), bool)) * 8:
        if tuple(lo) == (8, 0, 0):
            continue
        levels[0].append((lo, f(*_centres(16, start=lo, shape=(8, 8, 8)))))
    for lo in (np.argwhere(np.ones((2, 2, 2), bool)) * 8 + [16, 0, 0]):
        levels[1].append((lo, f(*_centres(32, start=lo, shape=(8, 8, 8)))))
    Path(directory).mkdir(parents=True, exist_ok=True)
    path = Path(directory) / "waves.out2.00010.athdf"
    write_athena_pp(path, levels, [16, 16, 16])
    return path, "rho"


def _centre_refined_plotfile(path, f, field):
    """An AMReX plotfile at ``path`` of ``f(x, y, z)`` on 16^3 root cells over
    the unit cube, the central 8^3 refined once (16^3 level-1 cells)."""
    levels = [[((0, 0, 0), f(*_centres(16)))],
              [((8, 8, 8), f(*_centres(32, start=(8, 8, 8), shape=(16, 16, 16))))]]
    write_amrex_plotfile(path, levels, [0, 0, 0], [1, 1, 1], field=field)
    return path, field


def velocity(directory):
    """An AMReX plotfile of a velocity component: a pair of counter-rotating
    vortices, negative in half the volume (km/s-like scale, up to 30)."""
    def v(x, y, z):
        return 30.0 * (np.sin(2 * np.pi * y) * np.cos(np.pi * (x - 0.5)) * np.exp(-((z - 0.5) / 0.3) ** 2))
    return _centre_refined_plotfile(Path(directory) / "plt_vel", v, "x_velocity")


def sheet(directory):
    """A RAMSES output (levels 3-5, 32^3 finest cells) with gas only in a thin
    curved sheet z ~ 0.5 + 0.15 sin(2 pi x), refined along it: zeros elsewhere."""
    def surface(x, y):
        return 0.5 + 0.15 * np.sin(2 * np.pi * x)

    def dist(level, ijk):
        c = (ijk + 0.5) / 2 ** level
        return np.abs(c[:, 2] - surface(c[:, 0], c[:, 1]))

    refined, cells = [], np.argwhere(np.ones((8, 8, 8), bool))
    child = np.array([(i & 1, i >> 1 & 1, i >> 2 & 1) for i in range(8)])
    for level in (3, 4):
        r = cells[dist(level, cells) < 1.5 / 2 ** level]
        refined.append(r)
        cells = (2 * r[:, None, :] + child[None]).reshape(-1, 3)

    def value(level, ijk):
        rho = np.where(dist(level, ijk) < 0.6 / 32, 1.0, 0.0)
        out = np.zeros((len(ijk), 5))
        out[:, 0], out[:, 4] = rho, rho
        return out
    return write_ramses(Path(directory), 3, refined, value), "density"


def embedded(directory):
    """An AMReX plotfile with an embedded boundary: pressure 1e5 (1 + 0.01
    sin) in the fluid around a solid sphere (radius 0.2) whose covered cells
    hold 0, as AMReX writes them."""
    def p(x, y, z):
        r = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2)
        fluid = 1e5 * (1 + 0.01 * np.cos(3 * np.pi * x) * np.cos(2 * np.pi * z))
        return np.where(r < 0.2, 0.0, fluid)
    return _centre_refined_plotfile(Path(directory) / "plt_eb", p, "pressure")


def core(directory):
    """An Enzo output: a uniform background of 1.0 and a dense core of 1e4
    (Gaussian, radius 0.03) at (0.55, 0.45, 0.5), 16^3 root cells and one
    level-1 grid of 16^3 cells around the core."""
    def rho(x, y, z):
        r2 = (x - 0.55) ** 2 + (y - 0.45) ** 2 + (z - 0.5) ** 2
        return 1.0 + 1e4 * np.exp(-r2 / 0.03 ** 2)
    children = [((10, 6, 8), rho(*_centres(32, start=(10, 6, 8), shape=(16, 16, 16))))]
    return write_enzo(Path(directory), "DD0010", rho(*_centres(16)), children), "density"


#: Every case, by name.
CASES = {f.__name__: f for f in (cosmology, collapse, deep, waves, velocity, sheet, embedded, core)}
