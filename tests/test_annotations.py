"""Annotations drawn with the picture's own camera (mi_amr/annotations.py):
the projection is Mitsuba's ``perspective`` sensor's (a point projects to
the pixel whose sensor ray passes through it, for non-square films, every
``fov_axis`` and tilted up vectors; a path-traced image has its corner
markers where the projection says), level boxes cover exactly the blocks,
axes carry physical units, and the burn-in draws where it projects."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr import AMRCells
from mi_amr.annotations import (Annotations, PinholeCamera, Placement, axes, box_edges, burn_in, legend_image,
                                level_boxes, nice_ticks, outline)
from mi_amr.data.blocks import BlockVolume
from mi_amr.transfer.function import TransferFunction

from conftest import random_amr

#: (origin, target, up, fov, fov_axis, film width, height)
CAMERAS = [
    ((1.8, 1.3, 2.6), (0.0, 0.0, 0.0), (0, 0, 1), 40.0, "x", 64, 32),
    ((-2.0, 0.5, 0.7), (0.1, -0.1, 0.0), (0.3, 0.2, 1.0), 25.0, "y", 40, 56),
    ((0.4, -2.5, -1.0), (0.0, 0.0, 0.1), (0, 1, 0), 70.0, "diagonal", 48, 48),
    ((1.1, 1.2, -1.9), (0.0, 0.1, 0.0), (1, 0, 0.2), 55.0, "smaller", 72, 30),
    ((0.3, 2.2, 0.9), (0.0, 0.0, 0.0), (0, 0, -1), 35.0, "larger", 30, 50),
]


def sensor_of(origin, target, up, fov, fov_axis, w, h):
    return mi.load_dict({"type": "perspective", "fov": fov, "fov_axis": fov_axis,
                         "to_world": mi.ScalarTransform4f().look_at(origin, target, up),
                         "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}}})


def test01_projected_points_lie_on_the_sensors_rays(llvm):
    """For each camera: the sensor's ray through the pixel a point projects
    to passes within 1e-5 (relative to its distance) of the point, and
    `PinholeCamera.rays` gives the sensor's directions (1e-5); the camera
    read from the loaded sensor is the one built from the same look-at."""
    rng = np.random.default_rng(1)
    points = np.concatenate([box_edges([-0.5, -0.5, -0.4], [0.5, 0.5, 0.4]).reshape(-1, 3),
                             rng.uniform(-0.5, 0.5, (40, 3))])
    for origin, target, up, fov, axis, w, h in CAMERAS:
        cam = PinholeCamera.looking(origin, target, up, fov, (w, h), axis)
        sensor = sensor_of(origin, target, up, fov, axis, w, h)
        read = PinholeCamera.of_sensor(sensor)
        np.testing.assert_allclose(read.to_world, cam.to_world, atol=1e-6)
        assert abs(read.fov - cam.fov) < 1e-4 and read.size == cam.size
        px, depth = cam.project(points)
        assert np.all(depth > 0)
        rays, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px[:, 0] / w, px[:, 1] / h), mi.Point2f(0.5, 0.5))
        o = np.array([np.asarray(c) for c in rays.o], np.float64).T
        d = np.array([np.asarray(c) for c in rays.d], np.float64).T
        to_point = points - o
        off = np.linalg.norm(to_point - (to_point * d).sum(1, keepdims=True) * d, axis=1)
        assert np.all(off < 1e-5 * np.linalg.norm(to_point, axis=1)), (axis, off.max())
        o2, d2 = cam.rays(px)
        start = o - o2                                    # the sensor's rays start at the near clip plane
        assert np.abs(start - (start * d).sum(1, keepdims=True) * d).max() < 1e-5
        np.testing.assert_allclose(d2, d, atol=1e-5)


def test02_corners_land_where_the_path_traced_image_has_them(llvm):
    """Small glowing spheres at the domain's 8 corners, path traced under a
    non-square camera with a tilted up and the fov along y: each sphere's
    image (the brightness-weighted centre of its pixels) lies within 0.2
    pixels of its centre's projection."""
    w, h = 96, 64
    origin, target, up, fov = (2.2, -1.4, 1.3), (0.05, 0.0, -0.05), (0.15, 0.1, 1.0), 32.0
    placement = Placement.of(BlockVolume.from_dense(np.ones((4, 8, 8), np.float32), block=4))
    corners = placement.unit_to_world(np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], float))
    scene = {"type": "scene", "integrator": {"type": "direct"},
             "sensor": {"type": "perspective", "fov": fov, "fov_axis": "y",
                 "to_world": mi.ScalarTransform4f().look_at(origin, target, up),
                 "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}},
                 "sampler": {"type": "stratified", "sample_count": 64}}}
    for k, c in enumerate(corners):
        scene[f"s{k}"] = {"type": "sphere", "center": c.tolist(), "radius": 0.03,
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
    img = np.array(mi.render(mi.load_dict(scene), seed=0), np.float64)[..., 0]
    cam = PinholeCamera.looking(origin, target, up, fov, (w, h), "y")
    px, _ = cam.project(corners)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    for p in px:
        near = (np.abs(xx - p[0]) < 4) & (np.abs(yy - p[1]) < 4)
        wgt = img * near
        assert wgt.sum() > 1.0, (p, wgt.sum())
        centre = np.array([(wgt * xx).sum(), (wgt * yy).sum()]) / wgt.sum()
        assert np.linalg.norm(centre - p) < 0.2, (centre, p)      # measured: at most 0.04 px


def test03_level_boxes_cover_exactly_the_blocks():
    """Per level the merged boxes are disjoint, hold every block's centre,
    and their volume is the blocks' (clipped to the data bounds); merging
    draws fewer boxes than blocks, one for a cuboid of blocks. Over the cap the covering boxes still
    hold every block, number at most the cap, and a note says so."""
    vol = BlockVolume.from_cells(random_amr(3, n=32, levels=3), block=2)
    for lb in level_boxes(vol):
        sel = vol.level == lb.level
        B = vol.block << lb.level
        blo = vol.origin + vol.coord[sel].astype(np.int64) * B
        bhi = np.minimum(blo + B, vol.hi)
        blo = np.maximum(blo, vol.lo)
        assert lb.exact and not lb.note
        assert np.prod(lb.hi - lb.lo, axis=1).sum() == np.prod(bhi - blo, axis=1).sum()
        centre = 0.5 * (blo + bhi)
        inside = np.all((centre[:, None] >= lb.lo[None]) & (centre[:, None] < lb.hi[None]), axis=2)
        assert np.all(inside.sum(axis=1) == 1)
        assert len(lb.lo) <= lb.blocks
    merged = {lb.level: len(lb.lo) for lb in level_boxes(vol)}
    blocks = {lb.level: lb.blocks for lb in level_boxes(vol)}
    assert sum(merged.values()) < sum(blocks.values()), (merged, blocks)
    cuboid = level_boxes(BlockVolume.from_dense(np.ones((6, 10, 12), np.float32), block=2))
    assert len(cuboid) == 1 and len(cuboid[0].lo) == 1                    # a grid of blocks: one box
    assert cuboid[0].lo[0].tolist() == [0, 0, 0] and cuboid[0].hi[0].tolist() == [12, 10, 6]
    capped = level_boxes(vol, max_boxes=3)
    for lb in capped:
        sel = vol.level == lb.level
        centre = vol.origin + (vol.coord[sel].astype(np.int64) + 0.5) * (vol.block << lb.level)
        inside = np.all((centre[:, None] >= lb.lo[None]) & (centre[:, None] <= lb.hi[None]), axis=2)
        assert inside.any(axis=1).all() and len(lb.lo) <= 3
        assert lb.exact == (lb.blocks <= 3 or merged[lb.level] <= 3)
        assert lb.exact or "covering boxes" in lb.note


def test04_outline_and_axes_in_physical_units():
    """The outline is the world box of the planned placement (longest side
    1, centred); axis ticks sit at round physical values that map back to
    themselves, labelled with the length unit."""
    cells = AMRCells(np.array([[0, 0, 0], [2, 0, 0]]), np.array([1, 1]), np.array([1.0, 2.0]))
    cells.meta = {"domain_left_edge": [10.0, 0.0, 0.0], "domain_right_edge": [18.0, 2.0, 2.0],
                  "domain_cells": [4, 2, 2], "length_unit": "kpc"}
    vol = BlockVolume.from_cells(cells, block=2)
    p = Placement.of(vol)
    np.testing.assert_allclose(p.phys_extent, [8.0, 2.0, 2.0])
    edges = outline(p)
    assert edges.shape == (12, 2, 3)
    np.testing.assert_allclose(edges.reshape(-1, 3).min(0), [-0.5, -0.125, -0.125])
    np.testing.assert_allclose(edges.reshape(-1, 3).max(0), [0.5, 0.125, 0.125])
    ax = axes(p)
    assert [a.name for a in ax] == ["x [kpc]", "y [kpc]", "z [kpc]"]
    np.testing.assert_allclose(p.world_to_physical(ax[0].ticks)[:, 0], [float(t) for t in ax[0].labels])
    assert list(nice_ticks(10.0, 18.0, 4)) == [10.0, 12.0, 14.0, 16.0, 18.0]


def legend_colours(leg: np.ndarray, tf, values, tol: float = 6.0):
    """The legend image ``leg`` (`legend_image`, its colour bar on the axes
    at [0.04, 0.48, 0.92, 0.44] of the figure) shows ``tf``'s colour at
    each of ``values``: the median over the bar's rows of the pixel column
    where the value lies (the opacity curve crosses a row or two) within
    ``tol`` of 255 x the TF's colour there (8-bit units)."""
    h, w = leg.shape[:2]
    lo, hi = tf.domain
    rows = slice(int(h * (1 - 0.92)) + 2, int(h * (1 - 0.48)) - 2)
    for v in values:
        x = int(0.04 * w + (v - lo) / (hi - lo) * 0.92 * w)
        u = (x + 0.5 - 0.04 * w) / (0.92 * w)                 # the value at the pixel's centre
        shown = np.median(leg[rows, x, :3].astype(np.float64), axis=0)
        want = 255 * np.asarray(tf(np.array([lo + u * (hi - lo)]))[0, :3], np.float64)
        assert np.abs(shown - want).max() <= tol, (v, shown, want)


def _line_points(camera, segs, n=50):
    """Points along the projected segments, n per segment (pixel coordinates)."""
    px = camera.project_segments(segs)
    t = np.linspace(0, 1, n)
    return (px[:, None, 0] * (1 - t[:, None]) + px[:, None, 1] * t[:, None]).reshape(-1, 2)


def _distance(points, h, w) -> np.ndarray:
    """(h, w): each pixel centre's distance to the nearest of ``points``."""
    from scipy.spatial import cKDTree
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    return cKDTree(np.asarray(points, np.float64)).query(np.stack([xx.ravel(), yy.ravel()], axis=1))[0].reshape(h, w)


def levels_drawn(with_levels, without, camera, p, vol, legend_box):
    """``with_levels`` has the level boxes burnt in where only they can be:
    at points of the projected level edges more than 3 px from the outline
    and outside the legend's box (x0, y0), 90% are lit where ``without`` is
    black; more than 3 px from any level edge the two pictures agree."""
    h, w = with_levels.shape[:2]
    edges = np.concatenate([_line_points(camera, p.finest_to_world(box_edges(lb.lo, lb.hi)))
                            for lb in level_boxes(vol)])
    d_outline = _distance(_line_points(camera, outline(p)), h, w)
    q = edges[(edges[:, 0] >= 1) & (edges[:, 0] < w - 1) & (edges[:, 1] >= 1) & (edges[:, 1] < h - 1)].astype(int)
    x0, y0 = legend_box
    q = q[(d_outline[q[:, 1], q[:, 0]] > 3) & ~((q[:, 0] >= x0 - 1) & (q[:, 1] >= y0 - 1))]
    assert len(q) > 100
    assert np.mean(with_levels[q[:, 1], q[:, 0]].max(axis=1) > 30) > 0.9
    assert without[q[:, 1], q[:, 0]].max() == 0
    far = _distance(edges, h, w) > 3
    assert np.array_equal(with_levels[far], without[far])


def test05_legend_and_burn_in():
    """The legend shows the TF's colours (at three values, its colour
    there); the burn-in changes the pixels along the projected outline and
    leaves those far from it; the level boxes are drawn where only they can
    be (away from the outline and the legend), nothing else changed; bad
    input is one clear error. Both checks fail on a wrong input (another
    TF's legend, a picture without the levels)."""
    tf = TransferFunction.load("viridis", (-2.0, 3.0))
    leg = legend_image(tf, "log10 density", log=True, size=(300, 60))
    assert leg.shape == (60, 300, 4)
    legend_colours(leg, tf, (-1.5, 0.5, 2.5))
    with pytest.raises(AssertionError):                         # the check tells another TF's colours
        legend_colours(legend_image(TransferFunction.load("plasma", (-2.0, 3.0)), log=True, size=(300, 60)),
                       tf, (-1.5, 0.5, 2.5))
    vol = BlockVolume.from_dense(np.ones((8, 8, 8), np.float32), block=4)
    p = Placement.of(vol)
    cam = PinholeCamera.looking((1.5, -1.8, 1.2), (0, 0, 0), (0, 0, 1), 40.0, (64, 48))
    black = np.zeros((48, 64, 3), np.uint8)
    out = burn_in(black, cam, p, vol, Annotations(outline=True, legend=False))
    line = _line_points(cam, outline(p))
    on = line[(line[:, 0] >= 1) & (line[:, 0] < 63) & (line[:, 1] >= 1) & (line[:, 1] < 47)]
    assert np.mean(out[on[:, 1].astype(int), on[:, 0].astype(int)].max(axis=1) > 60) > 0.9
    assert out[_distance(line, 48, 64) > 3].max() == 0
    # the level boxes of three levels, with the outline and the legend drawn too
    vol = BlockVolume.from_cells(random_amr(2, 16, 3), block=2)
    assert len(level_boxes(vol)) == 3
    p = Placement.of(vol)
    w, h = 240, 180
    cam = PinholeCamera.looking((1.5, -1.8, 1.2), (0, 0, 0), (0, 0, 1), 40.0, (w, h))
    black = np.zeros((h, w, 3), np.uint8)
    levels = burn_in(black, cam, p, vol, Annotations(outline=True, levels=True, legend=True), tf=tf)
    plain = burn_in(black, cam, p, vol, Annotations(outline=True, levels=False, legend=True), tf=tf)
    legend_box = (w - min(300, max(160, 2 * w // 3)), h - min(60, max(40, h // 6)))     # burn_in's legend size
    assert plain[legend_box[1]:, legend_box[0]:].max() > 0                              # the legend is there
    levels_drawn(levels, plain, cam, p, vol, legend_box)
    with pytest.raises(AssertionError):                          # the check tells a picture without them
        levels_drawn(plain, plain, cam, p, vol, legend_box)
    with pytest.raises(ValueError, match="film is 64x48"):
        burn_in(np.zeros((10, 10, 3), np.uint8), PinholeCamera.looking((1.5, -1.8, 1.2), (0, 0, 0), (0, 0, 1),
                                                                        40.0, (64, 48)), p, vol)
    with pytest.raises(ValueError, match="annotate"):
        Annotations.parse("outline,grid")
    assert Annotations.parse("levels,legend").levels and not Annotations.parse("levels").outline


def png_is_exr_with_lines(png, exr, distance):
    """The 8-bit PNG is the EXR tone-mapped (`srgb8`) more than 3 px from
    the burnt-in lines (``distance``: each pixel's, (H, W)), and differs
    from it on them (within half a pixel)."""
    from mi_amr.images import srgb8
    toned = srgb8(np.asarray(exr, np.float32)[..., :3]).astype(np.int64)
    assert png.shape == toned.shape
    far, on = distance > 3, distance < 0.5
    assert far.sum() >= 8 and on.sum() >= 8, (far.sum(), on.sum())
    assert np.abs(png[far].astype(np.int64) - toned[far]).max() <= 1
    assert np.mean(np.abs(png[on].astype(np.int64) - toned[on]).max(axis=1) > 8) > 0.5


def test06_data_scene_annotates_pngs_and_slices(llvm, tmp_path):
    """`DataScene`: ``render(annotate=...)`` keeps the float picture as
    rendered and shows the annotated one inline; ``save(annotate=...)``
    draws into the PNG only (read back: the EXR tone-mapped away from the
    outline, other pixels on it; a PNG without lines or of another picture
    fails the check); ``slice`` at a world position is the slice of
    the data at that unit-cube coordinate, as the medium holds the values."""
    import mi_amr
    from mi_amr.data.io import write_exabricks
    from mi_amr.data.volume import as_volume
    from mi_amr.images import read_exr, srgb8
    from mi_amr.slicing import slice_volume
    path = tmp_path / "d.cells"
    write_exabricks(random_amr(1, 8, 2), path)
    sc = mi_amr.scene(str(path), res=32, spp=4)
    plain = sc.render(seed=1)
    img = sc.render(seed=1, annotate="outline")
    np.testing.assert_array_equal(np.asarray(img), np.asarray(plain))
    assert img.annotated_srgb.shape == (32, 32, 3) and img._repr_png_()[:4] == b"\x89PNG"
    assert not np.array_equal(img.annotated_srgb, srgb8(plain))
    np.testing.assert_array_equal(img.annotated("outline"), img.annotated_srgb)
    written = sc.save(tmp_path / "a.exr", seed=1, annotate="outline")
    exr = read_exr(written["exr"])
    np.testing.assert_allclose(exr, plain, rtol=1e-6)
    png = np.asarray(mi.Bitmap(str(written["png"])), np.uint8)[..., :3]
    line = _line_points(sc.camera, outline(sc.placement))
    png_is_exr_with_lines(png, exr, _distance(line, *png.shape[:2]))
    with pytest.raises(AssertionError):                 # the check tells a PNG without the lines ...
        png_is_exr_with_lines(srgb8(exr), exr, _distance(line, *png.shape[:2]))
    with pytest.raises(AssertionError):                 # ... and one of another picture
        png_is_exr_with_lines(png, sc.render(seed=2), _distance(line, *png.shape[:2]))
    s = sc.slice("z", 0.0, 16)
    ref = slice_volume(as_volume(sc.plan.data), 2, 0.5, 16, transform="log10" if sc.log else None)
    np.testing.assert_array_equal(s.values, ref.values)
    with pytest.raises(ValueError, match="slice position"):
        sc.slice("x", 0.9)
