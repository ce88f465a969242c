"""The hybrid viewer (issue 59, item 2): while the camera or the TF moves,
``mi-amr view`` and the notebook widget answer with ray-marched fast passes
(``ray_march``: noise-free in the medium); at rest the view's own
path-traced mode refines from there on. A toggle per view (the ``hybrid``
message, the page's checkbox beside the mode selector, the widget's
``hybrid`` trait, ``mi-amr view --no-hybrid``) turns it off: drag frames are
then 1-spp ``emission_absorption`` passes. A snapshot renders the view's
own mode either way.

One engine of a small XML scene for the module: the 20,000-cell cloud in a
constant sky with no ground, so that a marched frame has nothing
path-traced in it (a planned scene's sunlit ground is path-traced in every
mode). Waits are for events, with deadlines only a hang reaches."""

import io
import json
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mi_amr.tools.cli import build_parser
from mi_amr.view import protocol as p
from mi_amr.view.camera import OrbitCamera
from mi_amr.plugins.integrator import MODES
from mi_amr.view.engine import FAST_BUDGET, FAST_MODE, FAST_STEP_SCALE, FAST_STEPS, PLAIN_FAST_MODE, SETTLE, ViewEngine
from mi_amr.view.scene import LoadedScene
from mi_amr.view.server import ViewServer
from mi_amr.view.tf_spec import TFSpec

from conftest import HANG_S, wait_until

pytest.importorskip("starlette")
#: Playwright's deadlines, in milliseconds: only a hang reaches them.
HANG_MS = HANG_S * 1000

RES = 64
MAX_SPP = 8
CLOUD = Path(__file__).resolve().parents[1] / "scenes" / "data" / "cloud.cells"

#: The cloud of scenes/demo.xml under a constant sky, no ground: amrvolpath refining in multi.
SCENE = f"""<scene version="3.0.0">
    <integrator type="amrvolpath"><string name="mode" value="multi"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="35"/>
        <transform name="to_world"><lookat origin="1.6, 0.9, 1.8" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{RES}"/><integer name="height" value="{RES}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.3"/></emitter>
    <medium type="amr" id="volume">
        <string name="filename" value="{CLOUD}"/>
        <string name="transfer_function" value="spiky"/>
        <float name="density_scale" value="120"/>
        <transform name="to_world"><translate value="-0.5, -0.5, -0.5"/></transform>
    </medium>
    <shape type="cube">
        <transform name="to_world"><scale value="0.5"/></transform>
        <bsdf type="null"/>
        <ref name="interior" id="volume"/>
    </shape>
</scene>
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The scene served on loopback at 64x64 (fast passes 32x32 alone), hybrid on by default."""
    root = tmp_path_factory.mktemp("hybrid")
    (root / "cloud.xml").write_text(SCENE)
    engine = ViewEngine(str(root / "cloud.xml"), res=RES, max_spp=MAX_SPP, preview_scale=0.5,
                        fast_ladder=(1.0,)).start()
    server = ViewServer(engine, out_dir=root / "snapshots", quiet=True).start()
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    yield server, root
    server.stop()
    engine.stop()


def _pixels(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), np.float64)


def _open(engine, arrivals=None):
    """A view whose frames are kept: (view, [(header, jpeg), ...]); ``arrivals``
    gets each frame's arrival (``time.monotonic``), in the same order."""
    frames = []

    def send(h, jpeg):
        if arrivals is not None:
            arrivals.append(time.monotonic())
        frames.append((h, jpeg))
    return engine.open_view(send), frames


def _fast_frame(engine, view, frames, azimuth) -> tuple:
    """Turn ``view`` to ``azimuth`` (degrees) and wait for the fast frame of that state."""
    engine.change(view, p.CameraChange(azimuth=azimuth))
    version = view.version
    return wait_until(lambda: next(((h, j) for h, j in list(frames) if h.fast and h.rendered == version), None),
                      f"the fast frame of version {version}")


def _seed_to_seed(engine, view, frames) -> tuple[float, list]:
    """Two fast frames of one state (there, away and back again: each pass
    has a seed of its own): their mean absolute difference (8-bit sRGB
    levels), and the fast frames' headers."""
    az = view.camera.azimuth
    first, _, again = (_fast_frame(engine, view, frames, a) for a in (az + 20, az - 20, az + 20))
    return float(np.abs(_pixels(first[1]) - _pixels(again[1])).mean()), [first[0], again[0]]


# ---- without a browser ------------------------------------------------------------------------
def test01_the_hybrid_message_and_its_bad_inputs():
    """``{"type": "hybrid", "on": bool}`` round-trips; anything else is one
    line naming the message (the page's error about ``hybrid``); the engine
    and the command line take the toggle's start."""
    msg = p.HybridChange(False)
    assert p.parse(p.dumps(msg)) == msg and p.to_json(msg) == {"type": "hybrid", "on": False}
    for bad, match in (({"type": "hybrid"}, "hybrid: 'on' must be true or false"),
                       ({"type": "hybrid", "on": "yes"}, "hybrid: 'on' must be true or false"),
                       ({"type": "hybrid", "on": 1}, "hybrid: 'on' must be true or false"),
                       ({"type": "hybrid", "on": True, "step": 2}, "hybrid: no field")):
        with pytest.raises(p.ProtocolError, match=match) as e:
            p.parse(json.dumps(bad))
        assert e.value.about == "hybrid" and "\n" not in str(e.value)
    with pytest.raises(ValueError, match="hybrid must be True or False"):
        ViewEngine("x.cells", hybrid="no")
    with pytest.raises(ValueError, match="fast_step_scale"):
        ViewEngine("x.cells", fast_step_scale=0.0)
    args = build_parser().parse_args(["view", "data.cells", "--no-hybrid"])
    assert args.no_hybrid is True and build_parser().parse_args(["view", "data.cells"]).no_hybrid is False


def test02_drag_frames_are_ray_marched_and_noise_free(served):
    """With the hybrid on, each camera change is answered by a fast frame
    in ray_march (1 spp, raw, half the view's width); two of them of the
    same state, rendered with different seeds, are the same picture (under
    0.5 levels of 255 apart on average: the centred sensor takes no random
    number the seed changes); two emission_absorption fast frames of that
    state (the hybrid off) differ by over 3 levels: its 1-spp Woodcock
    estimate is noisy."""
    server, _ = served
    engine = server.engine
    view, frames = _open(engine)
    try:
        assert view.hybrid and engine._fast_mode(view) == FAST_MODE
        wait_until(lambda: any(not h.preview for h, _ in frames), "the first full-size frame")
        marched, headers = _seed_to_seed(engine, view, frames)
        assert all(h.mode == FAST_MODE and h.fast and h.spp == 1 and not h.denoised
                   and (h.width, h.height) == (RES // 2, RES // 2) for h in headers), headers
        engine.change(view, p.HybridChange(False))
        tracked, headers = _seed_to_seed(engine, view, frames)
        assert all(h.mode == PLAIN_FAST_MODE and h.fast for h in headers), headers
    finally:
        engine.close_view(view)
    print(f"seed to seed, mean |difference| in 8-bit levels: ray_march {marched:.2f}, "
          f"emission_absorption {tracked:.2f}")
    assert marched < 0.5 and tracked > 3.0, (marched, tracked)


def test03_at_rest_the_views_mode_refines_from_the_drag(served):
    """After a drag of ray-marched frames, once the hand rests for SETTLE the
    view's own mode (multi) refines that state: a preview at the fast size,
    then full-size passes accumulating 1, 2, 3 spp, none of them fast or
    ray-marched, the first started no sooner than SETTLE after the last
    change (its arrival less its render time)."""
    server, _ = served
    engine = server.engine
    arrivals = []
    view, frames = _open(engine, arrivals)
    try:
        wait_until(lambda: any(not h.preview for h, _ in frames), "the first full-size frame")
        az = view.camera.azimuth
        for k in range(1, 6):
            header, _ = _fast_frame(engine, view, frames, az + 5 * k)
            assert header.mode == FAST_MODE
        last, rested = view.version, view.changed_at
        wait_until(lambda: any(h.rendered == last and h.spp >= 3 and not h.preview for h, _ in list(frames)),
                   "three refined passes after the drag")
    finally:
        engine.close_view(view)
    after = [(t, h) for t, (h, _) in zip(arrivals, frames) if h.rendered == last and not h.fast]
    first = after[0][1]
    assert first.preview and first.mode == "multi" and first.width == RES // 2
    full = [h for _, h in after if not h.preview]
    assert all(h.mode == "multi" and h.width == RES for h in full) and [h.spp for h in full[:3]] == [1, 2, 3]
    assert after[0][0] - first.render_ms / 1e3 >= rested + SETTLE - 0.005


def test04_the_toggle_is_per_view_and_recorded_ahead(served, tmp_path):
    """One view's hybrid off, another's on: each drags in its own fast mode
    and its hello says so; turning it off asks for emission_absorption's
    recordings ahead (the fast mode in use); the marcher's drag frames use
    a fast step (`FAST_STEPS` of the engine's), its refining passes the integrator's own; a
    snapshot writes the view's own mode, not the drag frames'."""
    server, _ = served
    engine = server.engine
    off, off_frames = _open(engine)
    on, on_frames = _open(engine)
    try:
        engine.change(off, p.HybridChange(False))
        size = engine._ladder(PLAIN_FAST_MODE)[0]
        assert (size, PLAIN_FAST_MODE) in engine._warm or engine.loaded.recorded(size, PLAIN_FAST_MODE)
        assert (off.hybrid, on.hybrid) == (False, True)
        hello_off, hello_on = engine.describe(off), engine.describe(on)
        assert (hello_off.hybrid, hello_off.fast_mode) == (False, PLAIN_FAST_MODE)
        assert (hello_on.hybrid, hello_on.fast_mode) == (True, FAST_MODE)
        assert hello_on.fast_modes == {"on": FAST_MODE, "off": PLAIN_FAST_MODE}
        for view, frames, mode in ((off, off_frames, PLAIN_FAST_MODE), (on, on_frames, FAST_MODE),
                                   (off, off_frames, PLAIN_FAST_MODE)):
            header, _ = _fast_frame(engine, view, frames, view.camera.azimuth + 15)
            assert header.mode == mode
        assert engine.fast_step_scale == FAST_STEP_SCALE
        assert engine.loaded.applied[("step", FAST_MODE)] in {FAST_STEP_SCALE * k for k in FAST_STEPS}
        # the marcher refining: its own step again
        engine.change(on, p.ModeChange(FAST_MODE))
        wait_until(lambda: any(h.mode == FAST_MODE and not h.fast and not h.preview for h, _ in list(on_frames)),
                   "a full-size ray_march pass")
        assert engine.loaded.applied[("step", FAST_MODE)] == engine.loaded.steps[FAST_MODE] == 0.5
        engine.change(on, p.ModeChange("multi"))
        wait_until(lambda: on.accum_epoch == on.epoch and on.spp >= 2, "multi refined again")
        shot = engine.take_snapshot(on, tmp_path, "hybrid")
    finally:
        engine.close_view(off)
        engine.close_view(on)
    xml = next(f for f in shot.files if str(f).endswith(".xml"))
    modes = [e.get("value") for e in ET.parse(xml).getroot().iter("string") if e.get("name") == "mode"]
    assert modes == ["multi"]


def _stub(res=256, **options) -> ViewEngine:
    """An engine (never started) over a scene stub that offers every mode."""
    engine = ViewEngine("unused.cells", res=res, mode="multi", **options)
    engine.loaded = LoadedScene("unused.cells", None, "test", [res, res],
                                OrbitCamera.looking((2, 0, 0), (0, 0, 0), (0, 0, 1), 35.0), TFSpec(), ("plasma",),
                                stored_log=False, integrators=dict.fromkeys(MODES))
    engine._new_scene()
    return engine


def test05_the_hybrids_budget_coarsens_the_step_never_the_width():
    """Ray-marched drag frames keep to `FAST_BUDGET` by their step first
    (`FAST_STEPS` times ``fast_step_scale``), never below half the view's
    width: at the default preview scale only the step moves; with a
    preview at full size the size steps down to half the width, no
    further, once the coarsest step does not fit; back again (size first,
    then step) once the finer one would fit. The recordings ahead are the
    centred fast pass and the engine's mode."""
    engine = _stub()
    ladder = engine._ladder()
    assert ladder == [[128, 128]] and engine._fast_step() == FAST_STEP_SCALE
    assert engine._warm_list() == [([128, 128], FAST_MODE, True), ([128, 128], "multi"), ([256, 256], "multi")]
    for k in (1, 2, 2):                              # slow: a coarser step, down to the coarsest
        engine._fast_timed(ladder[0], 3 * FAST_BUDGET)
        assert engine._march_level == k and engine._sizes(FAST_MODE)[0] == ladder[0]
    assert engine._fast_step() == FAST_STEP_SCALE * FAST_STEPS[-1]
    calls = 0
    while engine._march_level and calls < 60:       # fast again: finer once its estimate fits
        engine._fast_timed(ladder[0], 0.1 * FAST_BUDGET)
        calls += 1
    assert engine._march_level == 0 and 1 < calls < 60

    engine = _stub(preview_scale=1.0, fast_step_scale=2.0)
    ladder = engine._ladder()
    assert ladder == [[256, 256], [192, 192], [128, 128]] and engine._ladder(PLAIN_FAST_MODE)[-1] == [128, 128]
    engine.loaded.passes._frozen.update({(tuple(q), (FAST_MODE, "centred")): None for q in ladder})
    engine.loaded.centre = object()                  # the stub's centred passes count as recorded
    for _ in range(8):
        engine._fast_timed(engine._sizes(FAST_MODE)[0], 10 * FAST_BUDGET)
    assert engine._march_level == len(FAST_STEPS) - 1 and engine._sizes(FAST_MODE)[0] == [128, 128]
    assert engine._fast_step() == 2.0 * FAST_STEPS[-1]
    for _ in range(200):
        engine._fast_timed(engine._sizes(FAST_MODE)[0], 0.01 * FAST_BUDGET)
    assert engine._sizes(FAST_MODE)[0] == [256, 256] and engine._march_level == 0


def test06_without_the_marcher_the_toggle_says_why():
    """A scene whose integrator is not amrvolpath has no modes: its hello
    has no toggle (None) and turning it on is one line naming why."""
    engine = ViewEngine("unused.cells", res=64)          # never started: its state alone
    engine.loaded = LoadedScene("unused.cells", None, "test", [64, 64],
                                OrbitCamera.looking((2, 0, 0), (0, 0, 0), (0, 0, 1), 35.0), TFSpec(), ("plasma",),
                                stored_log=False, mode_note="the scene's integrator is volpath: lighting modes "
                                                            "need amrvolpath")
    engine.ready.set()
    view = engine.open_view(lambda *a: None)
    assert engine._fast_mode(view) is None and engine.describe(view).hybrid is None
    with pytest.raises(ValueError, match="hybrid: .*volpath") as e:
        engine.change(view, p.HybridChange(True))
    assert "\n" not in str(e.value) and view.hybrid is True and view.version == 0
    engine.change(view, p.HybridChange(False))               # off is always possible
    assert view.hybrid is False


def test07_the_widgets_trait(llvm, tmp_path):
    """The widget's ``hybrid`` trait: False at construction or set from
    Python turns the view's toggle off (its drag frames emission_absorption),
    the page's message turns it back and the trait follows; a bad message
    is one error line for the page, nothing changed."""
    pytest.importorskip("anywidget")
    import mi_amr
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    from mi_amr.view.widget import ViewWidget

    class Recorded(ViewWidget):
        def send(self, content, buffers=None):
            self.__dict__.setdefault("sent", []).append((content, buffers))

    cloud = save_cells(make_dataset("cloud", cells=20000, seed=0), tmp_path / "cloud.cells")
    w = Recorded(mi_amr.scene(str(cloud), res=32, spp=4), res=32, max_spp=4, hybrid=False)
    try:
        assert w.hybrid is False
        w.wait(HANG_S)
        assert w.view.hybrid is False and w.engine._fast_mode(w.view) == PLAIN_FAST_MODE
        w._on_page(w, {"type": "hybrid", "on": True}, [])
        w.sync()
        assert w.view.hybrid is True and w.hybrid is True
        w.hybrid = False
        assert w.view.hybrid is False
        hellos = [c for c, _ in w.sent if c.get("type") == "hello"]
        assert hellos[-1]["hybrid"] is False and hellos[-1]["fast_mode"] == PLAIN_FAST_MODE
        n = len(w.sent)
        w._on_page(w, {"type": "hybrid", "on": "off"}, [])
        errors = [c for c, _ in w.sent[n:] if c.get("type") == "error"]
        assert len(errors) == 1 and errors[0]["about"] == "hybrid" and "\n" not in errors[0]["message"]
        assert w.view.hybrid is False and w.hybrid is False
    finally:
        w.close()


# ---- in a browser -------------------------------------------------------------------------------
def _drag(page, steps=6):
    """Orbit by a few steps, each once the page shows a frame of the last one's change."""
    box = page.get_by_test_id("view").bounding_box()
    page.mouse.move(box["x"] + 100, box["y"] + 100)
    page.mouse.down()
    for k in range(1, steps + 1):
        changes = page.evaluate("window.viewerStats.changes")
        page.mouse.move(box["x"] + 100 + 6 * k, box["y"] + 100)
        page.wait_for_function(f"""() => {{ const s = window.viewerStats;
            return s.changes > {changes} && s.lastFrame.rendered >= s.changes; }}""", timeout=HANG_MS)
    page.mouse.up()


def _fast_frames(page) -> dict:
    return page.evaluate("({...window.viewerStats.frameModes})")


def test08_the_page_toggle(served, browser):
    """The checkbox beside the mode selector starts checked (the engine's
    hybrid) and the note says the drags' mode; a drag shows ray_march
    frames; unchecked, this tab's view drags in emission_absorption while a
    second tab's stays ray-marched; a bad hybrid message from a page is one
    error line to that page alone."""
    server, _ = served
    engine = server.engine
    pages = [browser.new_page(), browser.new_page()]
    errors = []
    for page in pages:
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(server.url)
        page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview",
                               timeout=HANG_MS)
    a, b = pages
    toggle = a.get_by_test_id("hybrid")
    assert toggle.is_checked() and toggle.is_enabled()
    assert FAST_MODE in a.get_by_test_id("mode-note").inner_text()
    before = _fast_frames(a)
    _drag(a)
    assert _fast_frames(a).get(FAST_MODE, 0) > before.get(FAST_MODE, 0)

    toggle.set_checked(False)
    wait_until(lambda: sum(not v.hybrid for v in list(engine._views.values())) == 1, "one view's hybrid off")
    assert PLAIN_FAST_MODE in a.get_by_test_id("mode-note").inner_text()
    before = _fast_frames(a)
    _drag(a)
    after = _fast_frames(a)
    assert after.get(PLAIN_FAST_MODE, 0) > before.get(PLAIN_FAST_MODE, 0)
    assert after.get(FAST_MODE, 0) == before.get(FAST_MODE, 0)
    assert b.get_by_test_id("hybrid").is_checked()
    before = _fast_frames(b)
    _drag(b)
    assert _fast_frames(b).get(FAST_MODE, 0) > before.get(FAST_MODE, 0)

    # a bad message on a's own connection: one line to a, nothing to b
    n_b = b.evaluate("window.viewerStats.errors.length")
    reply = a.evaluate("""() => new Promise((done) => {
        const token = document.querySelector('meta[name="mi-amr-token"]').content;
        const ws = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(token)}`);
        ws.onopen = () => ws.send(JSON.stringify({ type: "hybrid", on: "yes" }));
        ws.onmessage = (ev) => { if (typeof ev.data !== "string") return;
            const m = JSON.parse(ev.data); if (m.type === "error") { ws.close(); done(m); } };
    })""")
    assert reply["about"] == "hybrid" and "'on' must be true or false" in reply["message"]
    assert "\n" not in reply["message"]
    assert b.evaluate("window.viewerStats.errors.length") == n_b
    assert errors == []
    for page in pages:
        page.close()
