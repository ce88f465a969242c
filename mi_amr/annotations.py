"""What tells a viewer what a picture shows: the domain's outline, axes in
physical units, the boxes of each AMR level's blocks, a colour legend of the
TF, all drawn with the picture's own camera (docs/manual/viewer.md
"Annotations").

Spaces: *finest* units are the data's finest-level cells (absolute, as
`BlockVolume.lo`/``hi``); the medium's *unit cube* spans the data bounds
``[lo, hi]``; *world* units are where ``to_world`` (the medium's, by default
the planned one: the domain centred at 0, its longest side 1) puts that
cube; *physical* units are the data's own (``meta["length_unit"]``, from
the metadata's domain; finest cells when there is none). `Placement` maps
between them.

`PinholeCamera` projects world points to pixels exactly as Mitsuba's
``perspective`` sensor sees them (pixel ``(0, 0)`` the film's upper left
corner, x right, y down; ``fov`` along ``fov_axis``, the camera's
``to_world`` a look-at: local +z forward, +y up, +x left), and its `rays`
are the inverse. The page draws the same lines with the same formulas
(``static/annotations.js``).

`burn_in` draws outline, axes, level boxes and the legend onto an sRGB
8-bit picture (a PNG's pixels; never onto the linear EXR).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np

from .data.blocks import BlockVolume
from .data.metadata import cell_size

#: Boxes drawn per AMR level at most: more are merged into covering boxes
#: of coarser granularity (`level_boxes` says so in its note).
MAX_BOXES_PER_LEVEL = 4000
#: Colours of the AMR levels, coarsest first (wraps around): matplotlib's tab10.
LEVEL_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                 "#bcbd22", "#17becf")
#: Colour of the domain outline and the axes.
OUTLINE_COLOUR = "#ffffff"
#: The 12 edges of a box, as pairs of its corners ``(x, y, z)`` bits (corner ``c = x + 2 y + 4 z``).
BOX_EDGES = np.array([(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6),
                      (3, 7)])
#: The 8 corners of the unit box, corner ``c = x + 2 y + 4 z``.
CORNERS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], np.float64)


def level_colour(refinement: int) -> str:
    """The colour of refinement level ``refinement`` (0: the coarsest, as
    yt counts; `LEVEL_COLOURS`, wrapping)."""
    return LEVEL_COLOURS[int(refinement) % len(LEVEL_COLOURS)]


# ---- Where the data sit ----------------------------------------------------------------------------
def planned_to_world(volume: BlockVolume) -> np.ndarray:
    """The planned ``to_world`` of ``volume``'s medium (4x4): the unit cube
    onto the domain box centred at 0, its longest side 1, in the data's
    physical proportions (`mi_amr.autoscene.ScenePlan.to_world_matrix`)."""
    extent = Placement.of(volume).phys_extent
    world = extent / extent.max()
    m = np.diag([*world, 1.0])
    m[:3, 3] = -0.5 * world
    return m


@dataclass(frozen=True)
class Placement:
    """A `BlockVolume`'s data bounds ``lo``, ``hi`` (finest units), the
    medium's ``to_world`` (4x4, unit cube -> world) and the physical box
    (``phys_lo``, ``phys_extent`` in ``unit``) of the same bounds."""
    lo: np.ndarray
    hi: np.ndarray
    to_world: np.ndarray
    phys_lo: np.ndarray
    phys_extent: np.ndarray
    unit: str

    @classmethod
    def of(cls, volume: BlockVolume, to_world=None) -> "Placement":
        """``volume`` placed by ``to_world`` (a 4x4 array or a Mitsuba
        transform; None: `planned_to_world`)."""
        lo, hi = (np.asarray(b, np.float64) for b in volume.bounds)
        meta = getattr(volume, "meta", {}) or {}
        dx = cell_size(meta)
        if dx is None:
            phys_lo, extent, unit = lo, hi - lo, "cells"
        else:
            phys_lo = np.asarray(meta["domain_left_edge"], np.float64) + lo * dx
            extent, unit = (hi - lo) * dx, str(meta.get("length_unit") or "")
        if to_world is None:
            world = extent / extent.max()
            m = np.diag([*world, 1.0])
            m[:3, 3] = -0.5 * world
        else:
            m = np.asarray(getattr(to_world, "matrix", to_world), np.float64).reshape(4, 4)
        return cls(lo, hi, m, phys_lo, extent, unit)

    def unit_to_world(self, u) -> np.ndarray:
        u = np.asarray(u, np.float64)
        return u @ self.to_world[:3, :3].T + self.to_world[:3, 3]

    def finest_to_world(self, q) -> np.ndarray:
        """World points of absolute finest-unit points ``q`` (..., 3)."""
        return self.unit_to_world((np.asarray(q, np.float64) - self.lo) / (self.hi - self.lo))

    def world_to_finest(self, x) -> np.ndarray:
        u = (np.asarray(x, np.float64) - self.to_world[:3, 3]) @ np.linalg.inv(self.to_world[:3, :3]).T
        return self.lo + u * (self.hi - self.lo)

    def physical_to_world(self, p) -> np.ndarray:
        return self.unit_to_world((np.asarray(p, np.float64) - self.phys_lo) / self.phys_extent)

    def world_to_physical(self, x) -> np.ndarray:
        return self.phys_lo + (self.world_to_finest(x) - self.lo) / (self.hi - self.lo) * self.phys_extent


def box_edges(lo, hi) -> np.ndarray:
    """The 12 edges of each box ``[lo, hi]`` ((n, 3) each): (n * 12, 2, 3)."""
    lo, hi = np.atleast_2d(np.asarray(lo, np.float64)), np.atleast_2d(np.asarray(hi, np.float64))
    corners = lo[:, None, :] + CORNERS[None] * (hi - lo)[:, None, :]           # (n, 8, 3)
    return corners[:, BOX_EDGES].reshape(-1, 2, 3)


def outline(placement: Placement) -> np.ndarray:
    """The domain's 12 edges in world units, (12, 2, 3)."""
    return placement.unit_to_world(box_edges(np.zeros(3), np.ones(3)))


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round values (1, 2, 5 x 10^k steps) in ``[lo, hi]``, about ``n`` of them."""
    span = hi - lo
    if not span > 0:
        return np.array([lo])
    raw = span / max(n, 1)
    k = 10.0 ** math.floor(math.log10(raw))
    step = min((s * k for s in (1, 2, 5, 10)), key=lambda s: abs(s - raw))
    first = math.ceil(lo / step - 1e-9) * step
    return np.array([t for t in np.arange(first, hi + 0.5 * step, step) if lo - 1e-9 * span <= t <= hi + 1e-9 * span])


@dataclass
class Axis:
    """One axis drawn along a domain edge: ``segment`` (2, 3) world,
    ``ticks`` (m, 3) world points with their ``labels``, ``name`` (x, y or
    z with the unit)."""
    name: str
    colour: str
    segment: np.ndarray
    ticks: np.ndarray
    labels: list


def axes(placement: Placement, n_ticks: int = 4) -> list[Axis]:
    """The x, y and z axes along the domain's edges from its lower corner,
    with round ticks in physical units (``placement.unit``)."""
    out = []
    unit = f" [{placement.unit}]" if placement.unit else ""
    for a, (name, colour) in enumerate((("x", "#ff6060"), ("y", "#70e070"), ("z", "#70a0ff"))):
        lo, ext = placement.phys_lo[a], placement.phys_extent[a]
        values = nice_ticks(lo, lo + ext, n_ticks)
        p = np.tile(placement.phys_lo, (len(values), 1))
        p[:, a] = values
        end = placement.phys_lo.copy()
        end[a] += ext
        out.append(Axis(name + unit, colour, placement.physical_to_world(np.stack([placement.phys_lo, end])),
                        placement.physical_to_world(p), [f"{v:.3g}" for v in values]))
    return out


# ---- The boxes of the AMR levels ---------------------------------------------------------------------
@dataclass
class LevelBoxes:
    """The boxes of one AMR level in absolute finest units (``lo``, ``hi``,
    (n, 3) each), its ``blocks`` count and a ``note`` when boxes were
    merged beyond exact (over `MAX_BOXES_PER_LEVEL`). ``level``: mi-amr's
    (cells ``2**level`` finest cells wide), ``refinement``: yt's (0 the
    coarsest level of the data)."""
    level: int
    lo: np.ndarray
    hi: np.ndarray
    blocks: int
    note: str = ""
    exact: bool = True
    refinement: int = 0


def _merge_runs(lo: np.ndarray, hi: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint integer boxes ``[lo, hi)`` (n, 3) with those that touch
    along ``axis`` and match on the other two axes merged into one."""
    others = [a for a in range(3) if a != axis]
    key = np.concatenate([lo[:, others], hi[:, others]], axis=1)
    order = np.lexsort((lo[:, axis],) + tuple(key[:, k] for k in range(key.shape[1] - 1, -1, -1)))
    lo, hi, key = lo[order], hi[order], key[order]
    same = np.all(key[1:] == key[:-1], axis=1) & (lo[1:, axis] == hi[:-1, axis])
    start = np.concatenate([[True], ~same])
    first = np.nonzero(start)[0]
    last = np.concatenate([first[1:] - 1, [len(lo) - 1]])
    out_lo, out_hi = lo[first].copy(), hi[first].copy()
    out_hi[:, axis] = hi[last, axis]
    return out_lo, out_hi


def merged_boxes(coord: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes ``[lo, hi)`` in block units whose union is that of the unit
    cubes at ``coord`` (n, 3): runs along x merged, then along y, then z
    (one box for a cuboid of blocks)."""
    lo = np.unique(np.asarray(coord, np.int64).reshape(-1, 3), axis=0)
    hi = lo + 1
    for axis in range(3):
        lo, hi = _merge_runs(lo, hi, axis)
    return lo, hi


def level_boxes(volume: BlockVolume, max_boxes: int = MAX_BOXES_PER_LEVEL) -> list[LevelBoxes]:
    """Per AMR level, the boxes its blocks fill: runs of blocks merged along
    x, y and z (exact: the union of the boxes is that of the blocks; a
    grid of the simulation is one box). A level left with more than
    ``max_boxes`` is drawn as the boxes of coarser block units (2, 4, ...
    blocks: larger than its blocks, which the ``note`` says)."""
    out = []
    B = volume.block
    coarsest = int(volume.levels.max()) if len(volume.level) else 0
    for L in volume.levels.tolist():
        coord = volume.coord[volume.level == L].astype(np.int64)
        n, k = len(coord), 0
        lo, hi = merged_boxes(coord)
        while len(lo) > max_boxes:
            k += 1
            lo, hi = merged_boxes(coord >> k)
        note = "" if k == 0 else (f"level {coarsest - L}: {n} blocks in more than {max_boxes} boxes: drawn as "
                                  f"{len(lo)} covering boxes of {2 ** k}^3 blocks")
        width = B << L                                        # finest units per block
        blo = volume.origin + (lo << k) * width
        bhi = volume.origin + (hi << k) * width
        out.append(LevelBoxes(int(L), np.maximum(blo, volume.lo), np.minimum(bhi, volume.hi), n, note, k == 0,
                              coarsest - int(L)))
    return out


# ---- The camera ------------------------------------------------------------------------------------------
def x_fov(fov: float, fov_axis: str, aspect: float) -> float:
    """The horizontal field of view (degrees) of Mitsuba's ``perspective``
    sensor given ``fov`` along ``fov_axis`` (x, y, diagonal, smaller,
    larger) and ``aspect`` = width / height."""
    t = math.tan(math.radians(fov) / 2)
    if fov_axis == "smaller":
        fov_axis = "y" if aspect > 1 else "x"
    elif fov_axis == "larger":
        fov_axis = "x" if aspect > 1 else "y"
    if fov_axis == "x":
        return float(fov)
    if fov_axis == "y":
        return math.degrees(2 * math.atan(t * aspect))
    if fov_axis == "diagonal":
        return math.degrees(2 * math.atan(t * aspect / math.sqrt(1 + aspect * aspect)))
    raise ValueError(f"fov_axis: one of x, y, diagonal, smaller, larger, got {fov_axis!r}")


def look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's ``look_at`` camera-to-world matrix (4x4): columns left, up, forward, origin."""
    o, t, u = (np.asarray(v, np.float64) for v in (origin, target, up))
    d = t - o
    if not np.linalg.norm(d) > 0:
        raise ValueError("camera: the origin sits on the target")
    d /= np.linalg.norm(d)
    left = np.cross(u, d)
    if not np.linalg.norm(left) > 0:
        raise ValueError("camera: up is parallel to the view direction")
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, o
    return m


@dataclass(frozen=True)
class PinholeCamera:
    """Mitsuba's ``perspective`` sensor: ``to_world`` (4x4), ``fov`` (degrees
    along x) and the film ``size`` (width, height) in pixels."""
    to_world: np.ndarray
    fov: float
    size: tuple

    @classmethod
    def looking(cls, origin, target, up, fov: float, size, fov_axis: str = "x") -> "PinholeCamera":
        w, h = (int(s) for s in size)
        return cls(look_at(origin, target, up), x_fov(fov, fov_axis, w / h), (w, h))

    @classmethod
    def of_sensor(cls, sensor) -> "PinholeCamera":
        """The camera of a loaded Mitsuba ``perspective`` sensor (any variant)."""
        params = mi.traverse(sensor)
        m = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
        size = tuple(int(s) for s in sensor.film().size())
        return cls(m, float(np.ravel(params["x_fov"])[0]), size)

    def _tan(self):
        w, h = self.size
        t = math.tan(math.radians(self.fov) / 2)
        return t, t / (w / h)                          # half-extents at depth 1 along x and y

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (..., 2), depth (...,))`` of world ``points`` (..., 3):
        continuous pixel coordinates (0 at the film's left/top edge), and
        the depth along the view direction (> 0: in front)."""
        p = np.asarray(points, np.float64)
        inv = np.linalg.inv(self.to_world)
        local = p @ inv[:3, :3].T + inv[:3, 3]
        tx, ty = self._tan()
        z = local[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px = 0.5 * self.size[0] * (1 - local[..., 0] / (z * tx))
            py = 0.5 * self.size[1] * (1 - local[..., 1] / (z * ty))
        return np.stack([px, py], axis=-1), z

    def rays(self, pixels) -> tuple[np.ndarray, np.ndarray]:
        """``(origin (3,), unit directions (..., 3))``, world, of the rays
        through continuous ``pixels`` (..., 2): the inverse of `project`."""
        q = np.asarray(pixels, np.float64)
        tx, ty = self._tan()
        local = np.stack([(1 - 2 * q[..., 0] / self.size[0]) * tx, (1 - 2 * q[..., 1] / self.size[1]) * ty,
                          np.ones(q.shape[:-1])], axis=-1)
        d = local @ self.to_world[:3, :3].T
        return self.to_world[:3, 3].copy(), d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project_segments(self, segments, near: float = 1e-6) -> np.ndarray:
        """World segments (n, 2, 3) as pixel segments (m, 2, 2), each
        clipped to the part in front of the camera (depth >= ``near``)."""
        s = np.asarray(segments, np.float64).reshape(-1, 2, 3)
        inv = np.linalg.inv(self.to_world)
        z = s @ inv[2, :3] + inv[2, 3]                                  # (n, 2) depths
        keep = (z >= near).any(axis=1)
        s, z = s[keep], z[keep]
        a, b = s[:, 0].copy(), s[:, 1].copy()
        za, zb = z[:, 0], z[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip((near - za) / (zb - za), 0, 1)[:, None]
        a = np.where((za < near)[:, None], a + t * (b - a), a)
        b = np.where((zb < near)[:, None], s[:, 0] + t * (s[:, 1] - s[:, 0]), b)
        return self.project(np.stack([a, b], axis=1))[0]


# ---- What to draw ----------------------------------------------------------------------------------
@dataclass
class Annotations:
    """What `burn_in` draws: the ``outline``, the ``axes``, the level boxes
    (``levels``; ``level_filter``: the refinement levels drawn, None all),
    the ``legend``."""
    outline: bool = True
    axes: bool = False
    levels: bool = False
    level_filter: tuple | None = None
    legend: bool = True
    notes: list = field(default_factory=list)

    @classmethod
    def parse(cls, annotate) -> "Annotations":
        """``annotate``: True (outline and legend), False/None (nothing), an
        `Annotations`, or names among outline, axes, levels, legend (a
        comma-separated string or a list)."""
        if isinstance(annotate, Annotations):
            return annotate
        if annotate is True:
            return cls()
        if annotate is None or annotate is False:
            return cls(outline=False, legend=False)
        names = [s.strip() for s in annotate.split(",")] if isinstance(annotate, str) else list(annotate)
        known = ("outline", "axes", "levels", "legend")
        bad = [n for n in names if n not in known]
        if bad:
            raise ValueError(f"annotate: names among {', '.join(known)}, got {bad}")
        return cls(**{k: k in names for k in known})


def segments_of(placement: Placement, volume: BlockVolume, what: Annotations) -> list[tuple[np.ndarray, str, float]]:
    """World segments to draw: ``(segments (n, 2, 3), colour, line width)``
    per group (level boxes first, the outline last, on top)."""
    groups = []
    if what.levels and volume is not None:
        for lb in level_boxes(volume):
            if what.level_filter is not None and lb.refinement not in what.level_filter:
                continue
            if lb.note:
                what.notes.append(lb.note)
            groups.append((placement.finest_to_world(box_edges(lb.lo, lb.hi)), level_colour(lb.refinement), 0.8))
    if what.outline:
        groups.append((outline(placement), OUTLINE_COLOUR, 1.2))
    return groups


def legend_image(tf, label: str = "", log: bool = False, size=(300, 60), dpi: int = 100) -> np.ndarray:
    """The TF's colour legend, sRGB uint8 (H, W, 4): its colours over the
    domain with the opacity as a curve, ticks in the values' units (when
    ``log``, the TF's domain is log10 of the values: ticks at decades,
    10^k, or at round values on the log scale)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    lo, hi = tf.domain
    w, h = size
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.patch.set_alpha(0.0)
    ax = fig.add_axes([0.04, 0.48, 0.92, 0.44])
    u = np.linspace(0, 1, 256)
    rgba = tf(lo + u * (hi - lo))
    ax.imshow(rgba[None, :, :3].clip(0, 1), aspect="auto", extent=(lo, hi, 0, 1))
    ax.plot(lo + u * (hi - lo), rgba[:, 3], color="white", lw=1.0)
    ax.plot(lo + u * (hi - lo), rgba[:, 3], color="black", lw=0.5)
    ax.set_xlim(lo, hi)
    ax.set_ylim(0, 1.02)
    ax.set_yticks([])
    ticks = nice_ticks(lo, hi, 4)
    if log:                                  # the values' log10: ticks at decades, labelled with the values
        ints = np.arange(math.ceil(lo), math.floor(hi) + 1)
        if 2 <= len(ints) <= 8:
            ax.set_xticks(ints, [f"$10^{{{t:g}}}$" for t in ints])
        else:
            ticks = np.log10(nice_ticks(10.0 ** lo, 10.0 ** hi, 4).clip(10.0 ** lo, None))
            ax.set_xticks(ticks, [f"{10.0 ** t:.3g}" for t in ticks])
    else:
        ax.set_xticks(ticks, [f"{t:.3g}" for t in ticks])
    for item in ax.get_xticklabels():
        item.set_fontsize(7)
        item.set_color("white")
    ax.tick_params(colors="white", length=2, pad=1)
    for spine in ax.spines.values():
        spine.set_color("white")
    if label:
        fig.text(0.5, 0.02, label, ha="center", va="bottom", fontsize=7, color="white")
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba()).copy()


def burn_in(srgb: np.ndarray, camera: PinholeCamera, placement: Placement, volume: BlockVolume | None = None,
            what: Annotations | None = None, tf=None, label: str = "", log: bool = False) -> np.ndarray:
    """``srgb`` (H, W, 3) uint8 with the annotations drawn on it: the
    camera's film must be the picture's size. Lines are antialiased,
    exact to the pixel (continuous pixel coordinates as `PinholeCamera.project`)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    img = np.asarray(srgb)
    h, w = img.shape[:2]
    if (w, h) != tuple(camera.size):
        raise ValueError(f"burn_in: the camera's film is {camera.size[0]}x{camera.size[1]}, the picture {w}x{h}")
    what = Annotations() if what is None else what
    dpi = 100
    fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.imshow(img[..., :3], extent=(0, w, h, 0), interpolation="nearest")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.axis("off")
    for segs, colour, lw in segments_of(placement, volume, what):
        ax.add_collection(LineCollection(camera.project_segments(segs), colors=colour, linewidths=lw, alpha=0.9))
    if what.axes:
        for a in axes(placement):
            ax.add_collection(LineCollection(camera.project_segments(a.segment[None]), colors=a.colour,
                                             linewidths=1.5))
            px, z = camera.project(a.ticks)
            for (x, y), d, text in zip(px, z, a.labels):
                if d > 0:
                    ax.text(x, y, text, color=a.colour, fontsize=6, ha="center", va="bottom")
            end, z = camera.project(a.segment[1])
            if z > 0:
                ax.text(end[0], end[1], a.name, color=a.colour, fontsize=7, ha="left", va="top")
    if what.legend and tf is not None:
        lw_, lh = min(300, max(160, 2 * w // 3)), min(60, max(40, h // 6))
        legend = legend_image(tf, label, log, (lw_, lh))
        ax.imshow(legend, extent=(w - lw_, w, h, h - lh), interpolation="nearest", zorder=5)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _bitmap8(rgb8) -> mi.Bitmap:
    a = np.ascontiguousarray(np.asarray(rgb8, np.uint8)[..., :3])
    if a.ndim != 3:
        raise ValueError(f"an sRGB picture is (H, W, 3) uint8, got shape {a.shape}")
    return mi.Bitmap(a, mi.Bitmap.PixelFormat.RGB)


def write_srgb_png(path, rgb8):
    """Write sRGB 8-bit pixels (H, W, 3) as a PNG, as they are."""
    _bitmap8(rgb8).write(str(path))
    return path


def srgb_png_bytes(rgb8) -> bytes:
    """sRGB 8-bit pixels (H, W, 3) as PNG bytes."""
    stream = mi.MemoryStream()
    _bitmap8(rgb8).write(stream, mi.Bitmap.FileFormat.PNG)
    return bytes(stream.raw_buffer())
