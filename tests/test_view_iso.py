"""``mi-amr view``'s isosurfaces (docs/manual/viewer.md, "Isosurfaces"): the
``iso`` message and its checks (hostile input gets an error naming the
field, never a crash; a value outside the data is refused with the view's
values as they stay); the first value of a scene loaded without any records
the passes again once, after which moving, adding and removing values
compiles nothing (no new ``dr.freeze`` recording: replays only); in
Debian's chromium, the iso control over the TF editor's histogram adds a
value by a click, moves it by a drag and removes it, the server's medium
following in its log10 units; the widget's ``iso`` trait both ways; a
snapshot's XML carries the values."""

import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from mi_amr.device.isosurface import MAX_ISO_VALUES
from mi_amr.view import protocol as p

from conftest import HANG_S, wait_until

pytest.importorskip("starlette")
#: Playwright's deadlines, in milliseconds: only a hang reaches them.
HANG_MS = HANG_S * 1000
#: The TF editor's plot inside its canvas, as static/tf_editor.js's PAD (the iso strip shares it).
PAD_L, PAD_R = 8, 8


def test01_iso_messages_are_checked():
    """Numbers, finite, at most `MAX_ISO_VALUES`, ``only`` a bool; anything
    else is a `ProtocolError` naming the field, and a message round-trips."""
    msg = p.parse(json.dumps({"type": "iso", "values": [0.25, 1, 3e-27], "only": True}))
    assert msg == p.IsoChange(values=(0.25, 1.0, 3e-27), only=True)
    assert p.parse('{"type": "iso", "values": []}') == p.IsoChange(values=())
    assert p.parse('{"type": "iso"}') == p.IsoChange()
    assert p.to_json(msg) == {"type": "iso", "values": [0.25, 1.0, 3e-27], "only": True}
    bad = ['{"type": "iso", "values": [NaN]}', '{"type": "iso", "values": [Infinity]}',
           '{"type": "iso", "values": [1e999]}', '{"type": "iso", "values": ["0.3"]}',
           '{"type": "iso", "values": [true]}', '{"type": "iso", "values": 0.3}',
           '{"type": "iso", "values": [[0.3]]}', '{"type": "iso", "values": {"a": 1}}',
           json.dumps({"type": "iso", "values": [0.1] * (MAX_ISO_VALUES + 1)}),
           '{"type": "iso", "values": [' + "9" * 400 + "]}", '{"type": "iso", "values": [' + "1" * 320 + "]}",
           '{"type": "iso", "only": "yes"}', '{"type": "iso", "only": 1}', '{"type": "iso", "value": [1]}']
    for text in bad:
        with pytest.raises(p.ProtocolError) as e:
            p.parse(text)
        assert "\n" not in str(e.value) and ("iso" in str(e.value) or "message" in str(e.value)), text


@pytest.fixture(scope="module")
def radial_file(tmp_path_factory):
    """The radial field |x - centre| on two levels (the isosurface tests'
    data: its level sets are spheres cut by the level boundaries; all
    values positive, so the medium stores log10 of them) as a .cells file."""
    from mi_amr.data.io import save_cells
    from mi_amr.data.radial_example import radial_cells
    return save_cells(radial_cells(2, root=16), tmp_path_factory.mktemp("iso") / "radial.cells")


@pytest.fixture(scope="module")
def radial(radial_file):
    """A viewer of `radial_file` at 32x32, 4 spp at most, loaded without
    iso values, on loopback; one size of drag frames (their passes: one
    ray-marched recording, one ``multi``)."""
    from mi_amr.view.engine import ViewEngine
    from mi_amr.view.server import ViewServer
    root = radial_file.parent
    engine = ViewEngine(radial_file, res=32, max_spp=4, preview_scale=1.0, fast_ladder=(1.0,)).start()
    server = ViewServer(engine, out_dir=root / "snapshots", quiet=True).start()
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    yield engine, server, root
    server.stop()
    engine.stop()


def test02_the_widget_iso_trait_both_ways(radial_file, llvm):
    """The widget's ``iso`` and ``iso_only`` traits: set from Python they
    move the view's surfaces (a bad value is a `ValueError`, nothing
    changed); the page's iso message reaches them and the DataScene. (Run
    before the viewer of the tests below starts: one live medium at a time.)"""
    pytest.importorskip("anywidget")
    import mi_amr
    from mi_amr.view.widget import ViewWidget
    sc = mi_amr.scene(str(radial_file), res=32, spp=4)
    w = ViewWidget(sc, res=32, max_spp=4)
    w.send = lambda content, buffers=None: None
    try:
        w.wait(HANG_S)
        w.iso = [0.25]
        assert w.view.iso == (0.25,) and w.iso == [0.25]
        with pytest.raises(ValueError, match="outside"):
            w.iso = [7.0]
        assert w.view.iso == (0.25,)
        w.iso_only = True
        assert w.view.iso_only
        w._on_page(w, {"type": "iso", "values": [0.2, 0.3], "only": False}, [])
        w.sync()
        assert w.iso == [0.2, 0.3] and not w.iso_only and w.view.iso == (0.2, 0.3)
        assert tuple(sc.iso) == (0.2, 0.3)
    finally:
        w.close()


def recordings(engine) -> int:
    """Every ``dr.freeze`` recording the viewer made of its passes so far
    (a recording traces and compiles; a replay does neither). A pass may be
    recorded again in its first few replays after the one made ahead
    (``dr.freeze``'s ``auto_opaque`` making a literal that changed opaque;
    TF drags alike): counts are compared once a view has made a few changes."""
    return sum(f.n_recordings for f in engine.loaded.passes._frozen.values())


def refined(engine, view, spp=1):
    """Wait until ``view``'s accumulation of its newest state has ``spp`` samples."""
    wait_until(lambda: view.accum_epoch == view.epoch and view.spp >= spp, "refined picture")
    return view.accum / view.spp


def medium_iso(engine):
    return engine.loaded.medium.iso_values


def test03_first_value_records_once_then_moves_compile_nothing(radial):
    """On a scene loaded without iso values, the first one (field units:
    the medium gets its log10) records the passes again, once, and changes
    the picture; then moving it, adding a second, removing one and
    switching the gas off make no recording; a value outside the data is
    refused with the view's values as they stay."""
    from mi_amr.view.dispatch import answer
    engine, server, root = radial
    frames = []
    view = engine.open_view(lambda header, jpeg: frames.append(header))
    try:
        hello = engine.describe(view)["iso"]
        lo, hi = hello["range"]
        assert hello["values"] == [] and hello["note"] == "" and not hello["searching"]
        assert engine.loaded.stored_log and lo > 0 and hi < 1.0
        before = refined(engine, view, 2).copy()
        first = engine.change(view, p.IsoChange(values=(0.25,)))
        assert first is False                                # the histogram is the same
        image = refined(engine, view, 2)
        assert engine.loaded.medium.has_iso and medium_iso(engine) == pytest.approx((math.log10(0.25),), abs=1e-6)
        assert np.abs(image - before).max() > 0.05           # the sphere is in the picture
        for value in (0.26, 0.27, 0.28):                     # a few changes first (see `recordings`)
            engine.change(view, p.IsoChange(values=(value,)))
            refined(engine, view, 1)
        refined(engine, view, 2)
        wait_until(lambda: not engine.warming, "passes recorded ahead")
        made = recordings(engine)
        drag = [((float(v),), None) for v in np.linspace(0.1, 0.6, 40)]    # as a drag sends them
        for values, only in drag + [((0.3,), None), ((0.3, 0.2), None), ((0.2,), None), (None, True), (None, False)]:
            engine.change(view, p.IsoChange(values=values, only=only))
            refined(engine, view, 1)
            want = values if values is not None else view.iso
            assert medium_iso(engine) == pytest.approx(tuple(math.log10(v) for v in want), abs=1e-6)
            assert engine.loaded.medium.iso_only == (only is True)
        assert recordings(engine) == made, "a move of an iso value recorded a pass again (compiled)"
        # refused: outside the data, or a bad message; the view keeps its value
        for text in ('{"type": "iso", "values": [5.0]}', '{"type": "iso", "values": [-1]}'):
            reply = answer(engine, view, p.parse(text), root)
            assert isinstance(reply, p.Error) and reply.about == "iso" and "outside the data's values" in reply.message
            assert reply.iso["values"] == [0.2]
        assert view.iso == (0.2,)
        # a snapshot's XML carries the view's values in the medium's (log10) units
        engine.change(view, p.IsoChange(values=(0.2, 0.3), only=True))
        refined(engine, view, 1)
        shot = engine.take_snapshot(view, root / "snapshots", "iso")
        medium = ET.parse(shot.files[2]).getroot().find(".//medium[@type='amr']")
        iso = {c.get("name"): c.get("value") for c in medium}
        assert [float(v) for v in iso["iso"].split()] == pytest.approx([math.log10(0.2), math.log10(0.3)], abs=1e-8)
        assert iso["iso_only"] == "true"
        engine.change(view, p.IsoChange(values=(), only=False))
    finally:
        engine.close_view(view)


def _strip_x(box, canvas_width, u):
    """Page x of the display value share ``u`` on the iso strip (its canvas scaled to its box)."""
    return box["x"] + (PAD_L + u * (canvas_width - PAD_L - PAD_R)) * box["width"] / canvas_width


def test04_the_iso_control_over_the_histogram(radial, browser):
    """In chromium: a click on the strip under the histogram adds a value
    there (field units, as the page shows it); a drag moves it and the
    server's medium follows (its log10), no pass recorded again; the log10
    display keeps the values; a second value, then its × removes it;
    "surfaces only" switches the gas off; an out-of-range value typed in
    is refused in the page."""
    engine, server, root = radial
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url)
    page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview", timeout=HANG_MS)
    view = next(iter(engine._views.values()))
    assert page.get_by_test_id("iso-note").inner_text().startswith("values in")
    spec, width = view.spec, 460
    box = page.get_by_test_id("iso-strip").bounding_box()
    lo, hi = spec.range

    def field(u):                                      # the field value at display share u (the page's valueAt)
        d = lo + u * (hi - lo)
        return 10 ** d if spec.log else d

    y = box["y"] + box["height"] / 2
    page.mouse.click(_strip_x(box, width, 0.3), y)
    wait_until(lambda: len(view.iso) == 1, "the clicked value in the view")
    shown = json.loads(page.get_by_test_id("iso-strip").get_attribute("data-values"))
    assert list(view.iso) == shown and view.iso[0] == pytest.approx(field(0.3), rel=0.02 * (hi - lo) / abs(field(0.3)))
    wait_until(lambda: medium_iso(engine) and engine.loaded.medium.has_iso, "the value in the medium")
    refined(engine, view, 1)
    # typed in: the view takes it (a few changes before counting: see `recordings`)
    for u in (0.4, 0.45, 0.35):
        page.get_by_test_id("iso-value-0").fill(f"{field(u):.6g}")
        page.get_by_test_id("iso-value-0").press("Enter")
        wait_until(lambda: view.iso == (float(f"{field(u):.6g}"),), "the typed value in the view")
        refined(engine, view, 1)
    refined(engine, view, 2)
    wait_until(lambda: not engine.warming, "passes recorded ahead")
    made = recordings(engine)

    # drag it to u = 0.6: the view and the medium follow, nothing recorded again
    page.mouse.move(_strip_x(box, width, 0.35), y)
    page.mouse.down()
    page.mouse.move(_strip_x(box, width, 0.6), y, steps=12)
    page.mouse.up()
    wait_until(lambda: view.iso and abs(view.iso[0] - field(0.6)) < 0.02 * (hi - lo), "the dragged value in the view")
    page.wait_for_function("window.viewerStats.changes > 0 && !window.viewerStats.lastFrame.fast", timeout=HANG_MS)
    refined(engine, view, 2)
    moved = view.iso[0]
    assert json.loads(page.get_by_test_id("iso-strip").get_attribute("data-values")) == [moved]
    assert float(page.get_by_test_id("iso-value-0").input_value()) == pytest.approx(moved, rel=1e-3)
    assert medium_iso(engine) == pytest.approx((math.log10(moved),), abs=1e-6)
    assert recordings(engine) == made, "dragging an iso value recorded a pass again (compiled)"

    # the log10 display: the same values (field units), shown where their log10 lies
    if engine.loaded.log_available and not view.spec.log:
        page.get_by_test_id("log").check()
        wait_until(lambda: view.spec.log, "the log10 display")
        assert view.iso == (moved,)
        page.wait_for_timeout(200)
        assert float(page.get_by_test_id("iso-value-0").input_value()) == pytest.approx(moved, rel=1e-3)

    # a second value by the button, removed by its x; surfaces only
    page.get_by_test_id("iso-add").click()
    wait_until(lambda: len(view.iso) == 2, "the added value")
    page.get_by_test_id("iso-remove-0").click()
    wait_until(lambda: len(view.iso) == 1 and view.iso[0] != moved, "the first value removed")
    page.get_by_test_id("iso-only").check()
    wait_until(lambda: view.iso_only, "surfaces only")
    refined(engine, view, 1)
    assert engine.loaded.medium.iso_only and medium_iso(engine) == pytest.approx((math.log10(view.iso[0]),), abs=1e-6)
    assert recordings(engine) == made

    # typed out of the data's range: refused in the page, the view unchanged
    kept = view.iso
    page.get_by_test_id("iso-value-0").fill("1e9")
    page.get_by_test_id("iso-value-0").press("Enter")
    page.wait_for_function("document.getElementById('message').textContent.startsWith('iso:')", timeout=HANG_MS)
    assert view.iso == kept
    assert errors == [] and page.evaluate("window.viewerStats.errors") == []
    page.close()
