"""The viewer's annotations and slices (docs/manual/viewer.md "Annotations",
"Clip plane and slice"): what the engine answers to a page's
``annotations`` and ``slice`` requests, and a snapshot's PNG with the
annotations burnt in. The geometry is `mi_amr.annotations`' (the page
projects it with the view's camera, ``static/annotations.js``, as
`mi_amr.annotations.PinholeCamera` does); the slice is `mi_amr.slicing`'s,
of the values the medium holds, through its reconstruction, coloured by
the view's TF.
"""

from __future__ import annotations

import base64

import mitsuba as mi
import numpy as np

from ..annotations import (Annotations, PinholeCamera, Placement, axes, burn_in, legend_image, level_boxes,
                           level_colour, look_at)
from ..images import srgb8
from ..slicing import Slicer, axis_index
from .protocol import AnnotateChange, AnnotationsReply, SliceReply, SliceRequest

#: Significant digits of the world coordinates sent to the page.
DIGITS = 7


def png_data_url(pixels) -> str:
    """uint8 (H, W, 3) or (H, W, 4) pixels as a ``data:image/png;base64,`` URL."""
    a = np.ascontiguousarray(np.asarray(pixels, np.uint8))
    fmt = mi.Bitmap.PixelFormat.RGBA if a.shape[2] == 4 else mi.Bitmap.PixelFormat.RGB
    stream = mi.MemoryStream()
    mi.Bitmap(a, fmt).write(stream, mi.Bitmap.FileFormat.PNG)
    return "data:image/png;base64," + base64.b64encode(bytes(stream.raw_buffer())).decode("ascii")


def placement(loaded) -> Placement:
    """Where the loaded scene's medium puts its data (its ``to_world``)."""
    medium = loaded.medium
    return Placement.of(medium.volume, medium.options.to_world)


def value_label(loaded, log: bool) -> str:
    """What the values are: the field and its units (a log scale where the medium holds their log10)."""
    meta = loaded.medium.volume.meta or {}
    name = str(loaded.field or meta.get("field") or "value")
    units = f" [{loaded.units}]" if loaded.units else ""
    return f"{name}{units}, log scale" if log else f"{name}{units}"


def _cached(loaded, key, make):
    """``make()`` once per loaded scene (a field switch loads another)."""
    cache = loaded.__dict__.setdefault("_annotation_cache", {})
    if key not in cache:
        cache[key] = make()
    return cache[key]


def _round(a) -> list:
    return [float(f"{x:.{DIGITS}g}") for x in np.asarray(a, np.float64).ravel()]


def _legend(loaded, tf, log: bool) -> str:
    """The TF's legend as a PNG data URL, the last few kept."""
    key = (tf.rgba.tobytes(), tuple(tf.domain), log)
    legends = loaded.__dict__.setdefault("_legends", {})
    if key not in legends:
        while len(legends) >= 8:
            legends.pop(next(iter(legends)))
        legends[key] = png_data_url(legend_image(tf, value_label(loaded, log), log, (300, 60)))
    return legends[key]


def annotations_reply(loaded, tf=None, log: bool = False) -> AnnotationsReply:
    """The geometry of the annotations in world units (computed once per
    loaded scene), and with ``tf`` its legend as a PNG (the page draws its
    own, from its TF: `static/annotations.js`)."""
    p = placement(loaded)

    def geometry():
        corners = p.unit_to_world(np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], np.float64))
        ax = tuple({"name": a.name, "colour": a.colour, "segment": _round(a.segment), "ticks": _round(a.ticks),
                    "labels": list(a.labels)} for a in axes(p))
        levels = tuple({"refinement": lb.refinement, "level": lb.level, "colour": level_colour(lb.refinement),
                        "boxes": _round(np.concatenate([p.finest_to_world(lb.lo), p.finest_to_world(lb.hi)], 1)),
                        "blocks": lb.blocks, "note": lb.note} for lb in level_boxes(loaded.medium.volume))
        box = (_round(p.unit_to_world(np.zeros(3))), _round(p.unit_to_world(np.ones(3))))
        return _round(corners), ax, levels, box
    corners, ax, levels, box = _cached(loaded, "geometry", geometry)
    legend = "" if tf is None else _legend(loaded, tf, log)
    return AnnotationsReply(tuple(corners), ax, levels, box, legend, p.unit)


def slice_reply(loaded, msg: SliceRequest, tf, log: bool) -> SliceReply:
    """The slice a page asked for, of the values the medium holds, through
    its reconstruction, coloured by ``tf`` (the view's table); a
    `ValueError` for a plane outside the data or a medium placed with a
    rotation (slices are of the data's own axes)."""
    p = placement(loaded)
    a = axis_index(msg.axis)
    m = p.to_world
    if np.count_nonzero(np.abs(m[:3, :3] - np.diag(np.diag(m[:3, :3]))) > 1e-12 * np.abs(m).max()):
        raise ValueError("slice: the medium's to_world rotates the data; slices follow the data's axes only "
                         "when to_world is a scale and a translation")
    lo, hi = sorted((m[a, 3], m[a, 3] + m[a, a]))
    if not lo <= msg.position <= hi:
        raise ValueError(f"slice position: {msg.axis} within the data, [{lo:.4g}, {hi:.4g}] (world), "
                         f"got {msg.position}")
    unit = (msg.position - m[a, 3]) / m[a, a]
    slicer = _cached(loaded, "slicer", lambda: Slicer(loaded.medium.volume))
    s = slicer.slice(a, float(np.clip(unit, 0.0, 1.0)), msg.res, loaded.medium.reconstruction)
    ha, va = s.image_axes
    window = (m[ha, 3], m[ha, 3] + m[ha, ha], m[va, 3], m[va, 3] + m[va, va])
    h, w = s.values.shape
    return SliceReply(msg.axis, float(msg.position), w, h, png_data_url(s.image(tf)),
                      base64.b64encode(s.values.astype("<f4").tobytes()).decode("ascii"),
                      base64.b64encode(s.refinement.astype(np.int8).tobytes()).decode("ascii"),
                      tuple(float(x) for x in window), ("xyz"[ha], "xyz"[va]), value_label(loaded, log), bool(log))


def burnt_in(loaded, shown, camera, tf, log: bool, annotate: AnnotateChange) -> np.ndarray:
    """``shown`` (linear RGB, what the page shows) as sRGB 8-bit pixels with
    the view's annotations (``annotate``) drawn with its ``camera``
    (`mi_amr.view.camera.OrbitCamera`)."""
    rgb8 = srgb8(shown)
    h, w = rgb8.shape[:2]
    cam = PinholeCamera(look_at(camera.origin, camera.target, camera.up), float(camera.fov), (w, h))
    what = Annotations(outline=annotate.outline, axes=annotate.axes, levels=annotate.levels,
                       level_filter=annotate.level_filter, legend=annotate.legend)
    return burn_in(rgb8, cam, placement(loaded), loaded.medium.volume, what, tf, value_label(loaded, log), log)
