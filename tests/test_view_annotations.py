"""``mi-amr view``'s annotations, clip plane and slice (mi_amr/view/
view_annotations.py, static/annotations.js, static/slice.js) on a small
two-level Enzo output through yt: the engine answers the geometry and the
slice a page asks for (the slice is `mi_amr.slicing`'s of the medium's
values), a view's clip plane is in the medium when its pass renders, a
snapshot burns the annotations into its PNG only, and a snapshot asked for
during a field reload is written once the reload ends (or refused with a
message), never lost. In chromium: the page projects the corners where
Python does, the toggles, the level filter, the clip control and the slice
panel work (screenshots in docs/images/)."""

import base64
import dataclasses
import os
import threading
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mi_amr.annotations import PinholeCamera, look_at
from mi_amr.images import read_exr
from mi_amr.slicing import Slicer
from mi_amr.view import engine as engine_module
from mi_amr.view import protocol as p
from mi_amr.view.engine import ViewEngine
from mi_amr.view.view_annotations import placement

from conftest import HANG_S, wait_until

pytest.importorskip("starlette")
pytest.importorskip("yt")
#: Playwright's deadlines, in milliseconds: only a hang reaches them.
HANG_MS = HANG_S * 1000

IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"


def test01_protocol_refuses_bad_requests():
    """Clip, annotate and slice messages: what a message alone can tell is
    checked, the field named."""
    assert p.parse('{"type": "clip", "normal": [1, 0, 0], "offset": 0.25}') == p.ClipChange((1.0, 0.0, 0.0), 0.25)
    assert p.parse('{"type": "clip", "normal": null}') == p.ClipChange(None, 0.0)
    assert p.parse('{"type": "slice", "axis": "y", "position": 0.1}') == p.SliceRequest("y", 0.1, 256)
    assert p.parse('{"type": "annotate", "levels": true, "level_filter": [0, 2]}').level_filter == (0, 2)
    for bad, field in (('{"type": "clip", "normal": [0, 0, 0]}', "clip normal"),
                       ('{"type": "clip", "normal": [1, 0, 0], "offset": "a"}', "clip offset"),
                       ('{"type": "slice", "axis": "w", "position": 0}', "slice axis"),
                       ('{"type": "slice", "axis": "x", "position": 0, "res": 5000}', "slice res"),
                       ('{"type": "annotate", "level_filter": [-1]}', "level_filter"),
                       ('{"type": "annotate", "outline": 1}', "outline")):
        with pytest.raises(p.ProtocolError, match=field):
            p.parse(bad)


@pytest.fixture(scope="module")
def enzo(tmp_path_factory):
    """A viewer of a small two-level Enzo output (Density, Temperature)."""
    from amr_formats import write_enzo
    root = tmp_path_factory.mktemp("enzo")
    x, y, z = np.meshgrid(*[np.arange(16)] * 3, indexing="ij")
    top = 1.0 + 4.0 * np.exp(-((x - 9) ** 2 + (y - 7) ** 2 + (z - 8) ** 2) / 30.0)
    child = 3.0 + np.linspace(0, 2, 512).reshape(8, 8, 8)
    path = write_enzo(root / "DD0003", "DD0003", top, [((8, 8, 8), child)],
                      extra={"Temperature": lambda d: 100.0 * d ** 3})
    engine = ViewEngine(path, "Density", res=48, max_spp=2, preview_scale=1.0, mode="emission_absorption").start()
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    yield engine, root
    engine.stop()


def _settle(engine, view):
    """Wait for the view's full frame of its newest state."""
    def settled():
        with engine._wake:
            return view.accum_epoch == view.epoch and view.spp >= engine.max_spp
    wait_until(settled, "settled frame")


def test02_the_engine_answers_geometry_and_slices(enzo):
    """The geometry is the medium's placement (corners, two levels of
    boxes, a legend PNG); a slice's values and levels are `Slicer`'s of
    the medium's values, at the world position asked for; a bad position
    is one clear error."""
    engine, _ = enzo
    view = engine.open_view(lambda h, j: None)
    try:
        reply = engine.request(view, p.AnnotationsRequest())
        pl = placement(engine.loaded)
        corners = np.asarray(reply.corners).reshape(8, 3)
        np.testing.assert_allclose(corners[7] - corners[0], pl.to_world[:3, :3].diagonal(), rtol=1e-6)
        assert sorted(lv["refinement"] for lv in reply.levels) == [0, 1]
        fine = next(lv for lv in reply.levels if lv["refinement"] == 1)
        boxes = np.asarray(fine["boxes"]).reshape(-1, 2, 3)
        np.testing.assert_allclose(boxes[:, 1].max(0) - boxes[:, 0].min(0), 0.25 * (corners[7] - corners[0]),
                                   rtol=1e-6)             # the child grid: a quarter of the domain per side
        assert reply.legend == ""                               # the page draws its legend from its own TF
        from mi_amr.view.view_annotations import annotations_reply
        assert annotations_reply(engine.loaded, engine.loaded.table(view.spec), True).legend.startswith(
            "data:image/png;base64,")
        msg = p.SliceRequest("z", float(corners[0, 2] + 0.4 * (corners[7, 2] - corners[0, 2])), 32)
        s = engine.request(view, msg)
        values = np.frombuffer(base64.b64decode(s.values), "<f4").reshape(s.height, s.width)
        levels = np.frombuffer(base64.b64decode(s.levels), np.int8).reshape(s.height, s.width)
        ref = Slicer(engine.loaded.medium.volume).slice(2, 0.4, 32, engine.loaded.medium.reconstruction)
        np.testing.assert_allclose(values, ref.values, rtol=1e-6)
        assert np.array_equal(levels, ref.refinement) and set(np.unique(levels)) == {0, 1}
        assert s.png.startswith("data:image/png") and s.axes == ("x", "y")
        with pytest.raises(ValueError, match="slice position"):
            engine.request(view, p.SliceRequest("z", 5.0, 32))
        # the clip plane reaches the medium before the view's pass
        engine.request(view, p.ClipChange((1.0, 0.0, 0.0), 0.05))
        _settle(engine, view)
        assert engine.loaded.applied["clip"] == ((1.0, 0.0, 0.0), 0.05)
        assert engine.loaded.medium.clip[1] == 0.05
        with pytest.raises(ValueError, match="clip"):
            engine.set_clip(view, ((0.0, 0.0, 0.0), 1.0))
    finally:
        engine.close_view(view)


def test03_snapshots_burn_in_and_wait_for_a_reload(enzo, monkeypatch):
    """With ``burn_in`` the snapshot's PNG has the outline drawn where the
    camera projects it (pixels more than 3 px from it unchanged) and its
    EXR is the plain accumulation; a snapshot asked for while a field
    reloads is written after the reload, of the new field; one that would
    wait longer than it may is refused with a message (the reload held
    back until then: it cannot end while the test holds the lock its load
    takes)."""
    engine, root = enzo
    view = engine.open_view(lambda h, j: None)
    try:
        _settle(engine, view)
        plain = engine.take_snapshot(view, root / "shots", "plain")
        engine.set_clip(view, ((0.0, 1.0, 0.0), 0.125))         # a clip plane goes into the snapshot's XML
        _settle(engine, view)
        clipped = engine.take_snapshot(view, root / "shots", "clipped")
        import xml.etree.ElementTree as ET
        medium = next(e for e in ET.parse(clipped.files[2]).iter("medium") if e.get("type") == "amr")
        params = {c.get("name"): c.get("value") for c in medium}
        assert params["clip_normal"] == "0, 1, 0" and params["clip_offset"] == "0.125"
        assert "clip_normal" not in Path(plain.files[2]).read_text()
        engine.set_clip(view, None)
        _settle(engine, view)
        plain = engine.take_snapshot(view, root / "shots", "plain")
        engine.request(view, p.AnnotateChange(outline=True, burn_in=True))
        burnt = engine.take_snapshot(view, root / "shots", "burnt")
        np.testing.assert_array_equal(read_exr(plain.files[0]), read_exr(burnt.files[0]))
        a = np.asarray(mi.Bitmap(str(plain.files[1])), np.float64)[..., :3]
        b = np.asarray(mi.Bitmap(str(burnt.files[1])), np.float64)[..., :3]
        h, w = a.shape[:2]
        cam = view.camera
        pin = PinholeCamera(look_at(cam.origin, cam.target, cam.up), cam.fov, (w, h))
        from mi_amr.annotations import outline
        segs = pin.project_segments(outline(placement(engine.loaded)))
        t = np.linspace(0, 1, 200)
        line = (segs[:, None, 0] * (1 - t[:, None]) + segs[:, None, 1] * t[:, None]).reshape(-1, 2)
        yy, xx = np.mgrid[0:h, 0:w] + 0.5
        dist = np.min(np.hypot(xx[..., None] - line[:, 0], yy[..., None] - line[:, 1]), axis=2)
        changed = np.abs(a - b).max(axis=2) > 0
        assert changed.any() and not changed[dist > 3].any()
        assert changed[dist < 0.5].mean() > 0.5
        # a snapshot asked for during a field reload: written once it ends, of the new field
        worker = threading.Thread(target=engine.switch_field, args=("enzo,Temperature",))
        worker.start()
        wait_until(lambda: engine._reloads or not worker.is_alive(), "field reload under way", poll=0.001)
        shot = engine.take_snapshot(view, root / "shots", "during")
        worker.join(HANG_S)
        assert "Temperature" in Path(shot.files[2]).read_text() and engine.field == "enzo,Temperature"
        # ... refused with a message when the reload outlasts the wait (0.01 s here): the reload
        # cannot end while this thread holds JIT_LOCK, which its load takes
        from mi_amr.view.engine import JIT_LOCK
        monkeypatch.setattr(engine_module, "SNAPSHOT_WAIT", 0.01)
        worker = threading.Thread(target=engine.switch_field, args=("enzo,Density",))
        with JIT_LOCK:
            worker.start()
            wait_until(lambda: engine._reloads, "field reload under way")
            with pytest.raises(ValueError, match="still reloading"):
                engine.take_snapshot(view, root / "shots", "refused")
        worker.join(HANG_S)
        assert not worker.is_alive() and engine.field == "enzo,Density"
    finally:
        engine.close_view(view)


#: The overlay canvas's pixels drawn on (alpha > 0), counted in the page.
DRAWN = ("() => { const c = document.getElementById('overlay'), d = c.getContext('2d').getImageData(0, 0, c.width, "
         "c.height).data; let n = 0; for (let k = 3; k < d.length; k += 4) n += d[k] > 0; return n; }")


def _alpha(page) -> np.ndarray:
    """The overlay canvas's alpha (H, W)."""
    data = page.evaluate("""() => { const c = document.getElementById('overlay');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data, a = new Uint8Array(d.length / 4);
        for (let k = 0; k < a.length; k++) a[k] = d[4 * k + 3];
        let s = ''; for (let k = 0; k < a.length; k += 8192) s += String.fromCharCode(...a.subarray(k, k + 8192));
        return [c.width, c.height, btoa(s)]; }""")
    return np.frombuffer(base64.b64decode(data[2]), np.uint8).reshape(data[1], data[0]).astype(np.float64)


def test04_the_page_draws_annotations_clips_and_slices(enzo, browser):
    """In chromium: the page's projection is Python's (`PinholeCamera`) for
    several cameras and film shapes (1e-6 px); the outline is drawn at the
    projected corners; AMR levels add lines and the level filter takes
    some away; the legend shows; the clip control sets the view's plane,
    the slice panel follows it, and the value under the cursor is the
    slice's. Its screenshot is docs/images/viewer-annotations.jpg when
    MI_AMR_SCREENSHOTS is set (else it goes to the test's folder)."""
    from mi_amr.view.server import ViewServer
    engine, root = enzo
    engine.switch_field("enzo,Density")
    server = ViewServer(engine, out_dir=root / "out", quiet=True).start()
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(server.url)
        page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview "
                               "&& window.viewerStats.annotations >= 1", timeout=HANG_MS)
        view = next(iter(engine._views.values()))
        geometry = engine.request(view, p.AnnotationsRequest())
        corners = np.asarray(geometry.corners, np.float64).reshape(8, 3)
        for cam, size in ((view.camera, (48, 48)), (view.camera.moved(p.CameraChange(azimuth=37.0, elevation=-20.0,
                                                                                        distance=2.1)), (64, 36)),
                          (view.camera.moved(p.CameraChange(azimuth=200.0, elevation=60.0, target=(0.1, 0, 0))),
                           (30, 50))):
            js = np.array(page.evaluate("([c, s, q]) => window.viewerAnnotations.project(c, s, q)",
                                        [cam.to_json(), list(size), corners.tolist()]))
            pin = PinholeCamera(look_at(cam.origin, cam.target, cam.up), cam.fov, size)
            px, depth = pin.project(corners)
            np.testing.assert_allclose(js[:, :2], px, atol=1e-6 * max(size))
            np.testing.assert_allclose(js[:, 2], depth, rtol=1e-9)
        # the outline where the corners project (the page's camera is the view's)
        alpha = _alpha(page)                  # drawn at the picture's displayed size: the film's projection, scaled
        h, w = alpha.shape
        pin = PinholeCamera(look_at(view.camera.origin, view.camera.target, view.camera.up), view.camera.fov, (w, h))
        px, _ = pin.project(corners)
        inside = [q for q in px if 1 <= q[0] < w - 1 and 1 <= q[1] < h - 1]
        assert inside and all(alpha[int(y) - 1:int(y) + 2, int(x) - 1:int(x) + 2].max() > 0 for x, y in inside)
        outline_only = (alpha > 0).sum()
        page.get_by_test_id("show-levels").check()
        page.wait_for_function("document.querySelector('[data-testid=level-1]') !== null", timeout=HANG_MS)
        page.wait_for_function(f"({DRAWN})() > {outline_only}", timeout=HANG_MS)      # the levels drawn
        with_levels = (_alpha(page) > 0).sum()
        page.get_by_test_id("level-1").uncheck()
        page.wait_for_function(f"({DRAWN})() < {with_levels}", timeout=HANG_MS)       # the finer one gone
        coarse_only = (_alpha(page) > 0).sum()
        assert with_levels > coarse_only >= outline_only, (outline_only, coarse_only, with_levels)
        page.get_by_test_id("level-1").check()
        # the legend: the view's TF colours at the ends of its range (its table's first and last entries,
        # 5/255: the pixel centres lie 1/456 of the range inside)
        assert page.get_by_test_id("legend").is_visible()
        ends = page.evaluate("""() => {
            const c = document.getElementById('legend'), d = window.devicePixelRatio || 1, g = c.getContext('2d');
            const px = (x) => Array.from(g.getImageData(Math.floor(x * d), 10 * d, 1, 1).data);
            return [px(6), px(233)]; }""")
        table = engine.loaded.table(view.spec).rgba[:, :3] * 255
        assert np.abs(np.array(ends[0][:3]) - table[0]).max() <= 5
        assert np.abs(np.array(ends[1][:3]) - table[-1]).max() <= 5
        wait_until(lambda: view.annotate is not None and view.annotate.levels, "levels in the view's annotations")
        # the clip plane, and the slice panel following it
        page.get_by_test_id("show-slice").check()
        page.get_by_test_id("clip-axis").select_option("x")
        page.eval_on_selector("#clip-offset", "s => { s.value = '400'; s.dispatchEvent(new Event('input')); }")
        lo, hi = geometry.box[0][0], geometry.box[1][0]
        offset = lo + 0.4 * (hi - lo)
        wait_until(lambda: view.clip is not None and abs(view.clip[1] - offset) <= 1e-9, "clip offset of the page")
        assert view.clip[0] == (1.0, 0.0, 0.0)
        page.get_by_test_id("clip-axis").select_option("free")          # a free normal, then back to x
        page.get_by_test_id("clip-nz").fill("2")
        page.get_by_test_id("clip-nz").dispatch_event("change")
        wait_until(lambda: view.clip is not None and view.clip[0] == (1.0, 1.0, 2.0), "free clip normal")
        page.get_by_test_id("clip-axis").select_option("x")
        wait_until(lambda: view.clip is not None and view.clip[0] == (1.0, 0.0, 0.0), "x clip normal again")
        assert view.clip[1] == pytest.approx(offset, rel=1e-9)
        # the page counts the change messages the view counts
        wait_until(lambda: page.evaluate("window.viewerStats.changes") == view.version,
                   "page's change count equal to the view's version", poll=0.05)
        assert page.evaluate("window.viewerStats.errors") == []
        page.wait_for_function(f"window.viewerStats.lastSlice && window.viewerStats.lastSlice.axis === 'x' && "
                               f"Math.abs(window.viewerStats.lastSlice.position - {offset}) < 1e-9", timeout=HANG_MS)
        _settle(engine, view)
        def readout():
            """The readout once the pointer is over (0.3, 0.7) of the panel (in view,
            moved there again from its corner: a panel laid out after a move gets another)."""
            page.get_by_test_id("slice").scroll_into_view_if_needed()
            box = page.get_by_test_id("slice").bounding_box()
            page.mouse.move(box["x"] + 1, box["y"] + 1)
            page.mouse.move(box["x"] + 0.3 * box["width"], box["y"] + 0.7 * box["height"])
            return page.evaluate("document.getElementById('slice-readout').dataset.value")
        shown = float(wait_until(readout, "value under the cursor", poll=0.1))
        last = page.evaluate("window.viewerStats.lastSlice")
        ref = Slicer(engine.loaded.medium.volume).slice(0, 0.4, 256, engine.loaded.medium.reconstruction)
        i, j = int(0.3 * last["width"]), int(0.7 * last["height"])
        assert shown == pytest.approx(ref.values[j, i], rel=1e-6)
        assert "level" in page.get_by_test_id("slice-readout").inner_text()
        page.get_by_test_id("show-axes").check()
        page.wait_for_timeout(200)
        shot = (IMAGES if os.environ.get("MI_AMR_SCREENSHOTS") else root) / "viewer-annotations.jpg"
        page.locator("main").screenshot(path=str(shot), type="jpeg", quality=80)
        assert shot.stat().st_size > 10_000
        assert not errors, errors
    finally:
        page.close()
        server.stop()


def same_numbers(widget_geometry: dict, widget_slice: dict, server_geometry, server_slice):
    """The widget's replies (JSON over the comm channel) hold the server's
    numbers: the domain's corners and box, each level's boxes (1e-6 of the
    domain), a slice's window, values and levels (NaN where none)."""
    size = float(np.ptp(np.asarray(server_geometry.corners, np.float64).reshape(8, 3), axis=0).max())
    np.testing.assert_allclose(widget_geometry["corners"], server_geometry.corners, atol=1e-6 * size)
    np.testing.assert_allclose(np.asarray(widget_geometry["box"], np.float64), np.asarray(server_geometry.box),
                               atol=1e-6 * size)
    levels = {lv["refinement"]: lv for lv in server_geometry.levels}
    assert sorted(lv["refinement"] for lv in widget_geometry["levels"]) == sorted(levels)
    for lv in widget_geometry["levels"]:
        np.testing.assert_allclose(np.asarray(lv["boxes"], np.float64),
                                   np.asarray(levels[lv["refinement"]]["boxes"], np.float64), atol=1e-6 * size)
    assert (widget_slice["width"], widget_slice["height"], tuple(widget_slice["axes"])) == \
        (server_slice.width, server_slice.height, tuple(server_slice.axes))
    np.testing.assert_allclose(widget_slice["window"], server_slice.window, atol=1e-6 * size)

    def arrays(values, lv, w, h):
        return (np.frombuffer(base64.b64decode(values), "<f4").reshape(h, w),
                np.frombuffer(base64.b64decode(lv), np.int8).reshape(h, w))
    wv, wl = arrays(widget_slice["values"], widget_slice["levels"], widget_slice["width"], widget_slice["height"])
    sv, sl = arrays(server_slice.values, server_slice.levels, server_slice.width, server_slice.height)
    np.testing.assert_allclose(wv, sv, rtol=1e-6)                   # NaN where the other has NaN
    np.testing.assert_array_equal(wl, sl)
    assert np.isfinite(sv).sum() > 0.5 * sv.size and set(np.unique(sl)) >= {0, 1}      # a slice through both levels


def test05_the_notebook_widget_answers_the_same_requests(enzo, llvm):
    """The notebook widget (the same page code and markup) routes the
    annotations, clip and slice messages to its engine as the server does:
    its geometry (corners, box, each level's boxes) and its slice (window,
    values, levels) are the server's numbers for the same data; the clip
    plane reaches its view, a bad plane is one clear error. The comparison
    fails on the server's slice at another position and on geometry
    missing a level's box."""
    pytest.importorskip("anywidget")
    import mi_amr
    from test_widget import Recorded, _wait_for

    def wait_for(w, kind):
        """The last message of ``kind`` the widget sent (test_widget's wait)."""
        return _wait_for(w, lambda c: c.get("type") == kind)[-1][0]

    engine, _ = enzo
    server_view = engine.open_view(lambda h, j: None)
    try:
        geometry = engine.request(server_view, p.AnnotationsRequest())
        at = p.SliceRequest("y", -0.1, 16)              # through the child grid (-0.25 .. 0 a side) and the root's
        server_slice = engine.request(server_view, at)
        elsewhere = engine.request(server_view, p.SliceRequest("y", 0.2, 16))
    finally:
        engine.close_view(server_view)
    sc = mi_amr.scene(str(engine.source), "Density", mode="emission_absorption", res=48, spp=2)
    w = Recorded(sc, res=48, max_spp=2)
    try:
        w.wait(HANG_S)                   # a widget renders once a page or a call needs its view
        w._on_page(w, {"type": "annotations"}, [])
        reply = wait_for(w, "annotations")
        w._on_page(w, {"type": "slice", "axis": at.axis, "position": at.position, "res": at.res}, [])
        s = wait_for(w, "slice")
        assert tuple(s["axes"]) == ("z", "x") and len(reply["levels"]) == 2
        same_numbers(reply, s, geometry, server_slice)
        with pytest.raises(AssertionError):                 # the comparison sees another slice ...
            same_numbers(reply, s, geometry, elsewhere)
        fewer = [dict(lv, boxes=lv["boxes"][:-1]) if lv["refinement"] == 1 else lv for lv in geometry.levels]
        with pytest.raises(AssertionError):                 # ... and a box missing
            same_numbers(reply, s, dataclasses.replace(geometry, levels=tuple(fewer)), server_slice)
        w._on_page(w, {"type": "clip", "normal": [0, 0, 1], "offset": 0.0}, [])
        wait_until(lambda: w.view.clip is not None, "clip plane in the widget's view")
        assert w.view.clip == ((0.0, 0.0, 1.0), 0.0)
        w._on_page(w, {"type": "clip", "normal": [0, 0, 0]}, [])
        assert "clip normal" in wait_for(w, "error")["message"]
    finally:
        w.close()
